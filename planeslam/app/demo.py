"""The built-in demo: the paper's experiment on the project's own synthetic scene.

Renders the box-in-a-room circle (24 poses, Section 5 of the paper) with exact truth, runs
full SLAM on it (front end, tracking, iSAM2 backend, plane-object map) with every output of
`planeslam run`, and compares the trajectory and the object sizes against the truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from planeslam.app.runner import RunResult, run_sequence
from planeslam.sim.sequence import synthesize

SCENE = "box_room_circle"


@dataclass(frozen=True)
class DemoResult:
    """What the demo computed and where it wrote it."""

    data_dir: Path
    """The rendered scene (TUM layout, truth.json)."""
    run: RunResult
    """The SLAM run on it (outputs in run.out_dir)."""

    def summary(self) -> str:
        lines = [f"planeslam demo: full SLAM on the synthetic scene '{SCENE}' ({self.data_dir})"]
        lines.append(self.run.text())
        evaluation = self.run.evaluation
        for err in evaluation.evaluation.object_size_errors if evaluation else []:
            est = err["estimated_size_m"]
            est_text = " x ".join(f"{v:.3f}" for v in est) if est else "not found"
            true_text = " x ".join(f"{v:.3f}" for v in err["true_size_m"])
            mae = err["mean_abs_error_m"]
            error_text = f" (mean abs error {1000 * mae:.1f} mm)" if mae is not None else ""
            lines.append(f"  {err['class']}: {est_text} m vs truth {true_text} m{error_text}")
        return "\n".join(lines)


def run_demo(
    out_dir: Path, seed: int = 0, progress: bool = False, backend: str = "isam2"
) -> DemoResult:
    """Render SCENE (once) into out_dir/SCENE and run SLAM on it into out_dir/run."""
    out_dir = Path(out_dir)
    data_dir = out_dir / SCENE
    if not (data_dir / "truth.json").is_file():
        synthesize(SCENE, data_dir, seed=seed)
    run = run_sequence(data_dir, out_dir / "run", backend=backend, progress=progress, seed=seed)
    return DemoResult(data_dir=data_dir, run=run)
