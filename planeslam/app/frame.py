"""`planeslam frame`: run the front end on one frame of a dataset and write
frame.json (the shared map schema, camera frame), overlay.png and the resolved
config.yaml."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from planeslam.app.dataset_options import TopicOverrides
from planeslam.app.overlay import draw_overlay, format_size, write_png
from planeslam.config import ConfigLayer, open_configured, resolve_config
from planeslam.core.config import save_yaml
from planeslam.core.errors import DatasetFormatError
from planeslam.core.safe_files import write_text_atomic
from planeslam.frontend.pipeline import FrameObservation, FrontEnd

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameResult:
    """What `process_frame` computed and wrote."""

    dataset_dir: Path
    index: int
    """Frame index in the dataset's frame list."""
    timestamp: float
    """Frame time stamp [s]."""
    frame_json: Path
    """frame.json: observation.to_dict() (schema 'planeslam.map/1', camera frame)."""
    overlay_png: Path
    """overlay.png: planes, edges, corners and object labels on the RGB image."""
    config_yaml: Path
    """config.yaml: the resolved config the frame was processed with."""
    observation: FrameObservation = field(repr=False)

    def summary(self) -> str:
        """One paragraph: planes, edges, corners, objects (class, size), stage ms, reason."""
        seg, st = self.observation.segmentation, self.observation.structure
        convex = sum(bool(e.convex) for e in st.edges)
        objects = ", ".join(f"{o.cls} {format_size(o.size_m)}".strip() for o in st.objects)
        stages = ", ".join(f"{k} {v:.1f}" for k, v in self.observation.stage_ms.items())
        total = sum(self.observation.stage_ms.values())
        text = (
            f"frame {self.index} of {self.dataset_dir} (t = {self.timestamp:.6f} s): "
            f"{len(seg.planes)} planes, {len(st.edges)} edges ({convex} convex, "
            f"{len(st.edges) - convex} concave), {len(st.corners)} corners, "
            f"{len(st.objects)} objects{': ' + objects if objects else ''}. "
            f"Front end {total:.1f} ms ({stages} ms)."
        )
        if self.observation.reason:
            text += f" Reason: {self.observation.reason}."
        return f"{text}\nwrote {self.frame_json}, {self.overlay_png}, {self.config_yaml}"


def process_frame(
    dataset_dir: str | Path,
    index: int,
    config: str | Path | None = None,
    camera: str | ConfigLayer | None = None,
    out_dir: str | Path = Path("out/frame"),
    seed: int = 0,
    topics: TopicOverrides | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
) -> FrameResult:
    """Front end on frame `index` of a dataset (TUM folder or ROS bag) -> files in `out_dir`.

    `config` is a preset name or YAML path and `camera` a 'fx,fy,cx,cy[,depth_scale]'
    override, resolved with the `overrides` ('section.key=value') by
    `planeslam.config.resolve_config`. Writes frame.json
    (camera frame, metres), overlay.png and config.yaml. DatasetFormatError when
    `index` is outside 0..len-1. `topics` chooses a bag's topics.
    """
    dataset_dir = Path(dataset_dir)
    out_dir = Path(out_dir)
    cfg = resolve_config(dataset_dir, config, camera, overrides)
    if topics is not None:
        cfg = topics.apply(cfg)
    dataset, cfg = open_configured(dataset_dir, cfg)
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(dataset):
        raise DatasetFormatError(
            f"{dataset_dir}: frame index {index!r} out of range; valid 0..{len(dataset) - 1} "
            f"({len(dataset)} frames)"
        )
    frame = dataset[index]
    observation = FrontEnd(cfg, seed=seed).process(frame.depth_m, frame.timestamp)
    out_dir.mkdir(parents=True, exist_ok=True)
    frame_json = out_dir / "frame.json"
    data = observation.to_dict()
    data["dataset"] = str(dataset_dir)
    data["index"] = int(index)
    write_text_atomic(frame_json, json.dumps(data, indent=1) + "\n")
    overlay_png = write_png(
        out_dir / "overlay.png", draw_overlay(frame.rgb, observation, cfg.camera)
    )
    config_yaml = out_dir / "config.yaml"
    save_yaml(cfg, config_yaml)
    log.info("frame %d of %s -> %s", index, dataset_dir, out_dir)
    return FrameResult(
        dataset_dir=dataset_dir,
        index=index,
        timestamp=frame.timestamp,
        frame_json=frame_json,
        overlay_png=overlay_png,
        config_yaml=config_yaml,
        observation=observation,
    )
