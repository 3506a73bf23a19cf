"""How well the dense fallback's landing cost tells right results from wrong ones, over
many sequences (docs/experiments.md, "What the landing cost can and cannot tell").

    python docs/scripts/dense_landing.py record SEQUENCE OUT
    python docs/scripts/dense_landing.py summary OUT [OUT ...]

`record` runs `planeslam run` on the TUM-layout folder SEQUENCE (groundtruth.txt with one
pose per frame, as `planeslam synth` writes) into OUT and writes OUT/dense.jsonl: per call
of the dense fallback, every result it accepted as its landing cost and its step error
against the true step [m], and the error of the result taken. `summary` reads those files:
the landing costs of right results (error under 3 cm) and wrong ones (over 10 cm), and
every frame where the result taken was wrong.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def record(sequence: str, out: str) -> None:
    from _run_probe import count_frames, step_error_m

    import planeslam.tracking.dense as dense
    from planeslam.app.runner import run_sequence
    from planeslam.io.trajectory import read_tum

    truth = list(read_tum(f"{sequence}/groundtruth.txt").T_world_cam)
    current = count_frames()
    accepted: list[tuple[float, float]] = []
    """(landing cost, step error [m]) of each result the call being recorded accepted."""
    Path(out).mkdir(parents=True, exist_ok=True)

    def error(fallback: dense.DenseFallback, T: np.ndarray) -> float:
        return step_error_m(truth, current["frame"], fallback.previous_pose, T)

    def noting(landing_cost):  # `register` asks it of each result it accepted, once
        def wrapper(self, cloud, rgbd, T):
            cost = landing_cost(self, cloud, rgbd, T)
            accepted.append((cost, error(self, T)))
            return cost

        return wrapper

    def recording(register):
        def wrapper(self, *args, **kwargs):
            accepted.clear()
            taken = register(self, *args, **kwargs)
            if self.previous_pose is not None:
                taken_error = None if taken is None else error(self, taken.T)
                entry = {"frame": current["frame"], "results": accepted, "taken": taken_error}
                log.write(json.dumps(entry) + "\n")
                log.flush()
            return taken

        return wrapper

    dense.DenseFallback._landing_cost = noting(dense.DenseFallback._landing_cost)
    dense.DenseFallback.register = recording(dense.DenseFallback.register)
    with open(Path(out) / "dense.jsonl", "w") as log:
        run_sequence(sequence, out)


def summary(outs: list[str]) -> None:
    right, wrong, taken_wrong = [], [], []
    for out in outs:
        for line in open(Path(out) / "dense.jsonl"):
            entry = json.loads(line)
            costs = [(c, e) for c, e in entry["results"] if np.isfinite(c)]
            right += [c for c, e in costs if e < 0.03]
            wrong += [c for c, e in costs if e > 0.10]
            if entry["taken"] is not None and entry["taken"] > 0.10:
                shown = ", ".join(f"{c:.4f} ({100 * e:.1f} cm)" for c, e in costs)
                taken_wrong.append(
                    f"{Path(out).name} frame {entry['frame']}: taken "
                    f"{100 * entry['taken']:.1f} cm off; results {shown}"
                )
    print(f"{len(right)} right results (< 3 cm), {len(wrong)} wrong (> 10 cm)")
    for q in (50, 90, 99, 100):
        shown = [f"{np.percentile(c, q):.4f}" if c else "-" for c in (right, wrong)]
        print(f"  landing cost p{q}: right {shown[0]}, wrong {shown[1]}")
    for threshold in (0.01, 0.1, 0.3):
        print(
            f"  above {threshold}: right {sum(c > threshold for c in right)}, "
            f"wrong {sum(c > threshold for c in wrong)}"
        )
    print(f"{len(taken_wrong)} frames took a wrong result:")
    print("\n".join("  " + line for line in taken_wrong))


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "record":
        record(sys.argv[2], sys.argv[3])
    elif len(sys.argv) > 2 and sys.argv[1] == "summary":
        summary(sys.argv[2:])
    else:
        sys.exit(__doc__)
