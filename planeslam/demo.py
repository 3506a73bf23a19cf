"""The built-in demo: render the paper's box-in-a-room scene and run the per-frame
front end on every frame, comparing the box found against the scene's truth."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from planeslam.config import resolve_config
from planeslam.dataset import TumDataset
from planeslam.frontend import FrontEnd
from planeslam.synth import load_truth, synthesize

SCENE = "box_room_circle"


@dataclass(frozen=True)
class DemoResult:
    """What the demo computed and where it wrote it."""

    data_dir: Path
    frames_path: Path
    frames: int
    frame_ms_median: float
    box_frames: int
    """Frames in which an object classified 'box' was found."""
    box_size_median_m: tuple[float, ...]
    box_size_true_m: tuple[float, ...]
    stage_ms: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        est = " x ".join(f"{v:.3f}" for v in self.box_size_median_m) or "-"
        true = " x ".join(f"{v:.3f}" for v in self.box_size_true_m)
        return (
            f"planeslam demo ({SCENE}): {self.frames} frames, front end "
            f"{self.frame_ms_median:.1f} ms/frame median\n"
            f"  box found in {self.box_frames}/{self.frames} frames; median size {est} m "
            f"(truth {true} m)\n"
            f"  data: {self.data_dir}\n  per-frame results: {self.frames_path}\n"
            "  (full SLAM and evaluation join the demo as the pipeline grows)"
        )


def run_demo(out_dir: Path, seed: int = 0, progress: bool = False) -> DemoResult:
    """Render the scene (once) into out_dir/SCENE and run the front end on each frame,
    writing one frame.json record per line to out_dir/frames.jsonl as it goes."""
    out_dir = Path(out_dir)
    data_dir = out_dir / SCENE
    if not (data_dir / "truth.json").is_file():
        synthesize(SCENE, data_dir, seed=seed)
    truth = load_truth(data_dir)
    config = resolve_config(data_dir)
    dataset = TumDataset(data_dir, config.camera, config.dataset)
    front_end = FrontEnd(config, seed=seed)
    frames_path = out_dir / "frames.jsonl"
    frame_ms: list[float] = []
    box_sizes: list[list[float]] = []
    indices = range(len(dataset))
    if progress:
        from tqdm import tqdm

        indices = tqdm(indices, desc="front end", unit="frame")
    with open(frames_path, "w", encoding="utf-8") as fh:
        for i in indices:
            frame = dataset[i]
            obs = front_end.process(frame.depth_m, frame.timestamp)
            frame_ms.append(sum(obs.stage_ms.values()))
            record = obs.to_dict()
            fh.write(json.dumps(record) + "\n")
            fh.flush()
            boxes = [o["size_m"] for o in record["objects"] if o["class"] == "box"]
            if boxes:
                box_sizes.append(boxes[0])
    true_box = next(o["size_m"] for o in truth["objects"] if o["class"] == "box")
    median = tuple(float(v) for v in np.median(box_sizes, axis=0)) if box_sizes else ()
    return DemoResult(
        data_dir=data_dir,
        frames_path=frames_path,
        frames=len(dataset),
        frame_ms_median=float(np.median(frame_ms)),
        box_frames=len(box_sizes),
        box_size_median_m=median,
        box_size_true_m=tuple(true_box),
    )
