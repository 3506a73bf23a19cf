"""Which frames of a synthetic sequence pin the camera's position: a frame whose
noise-free image (colour and depth) does not change when its camera slides a few
centimetres along a world axis cannot be placed along that axis by any method that reads
only the images (one bare wall filling the view, a bare floor and wall seen along their
edge). The robustness benchmark reports such frames beside each sequence's figures
(`planeslam bench robust`, the 'blind frames' column).

World frame z up, metres; poses T_world_cam (4, 4), camera x right, y down, z forward.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.safe_files import write_text_atomic
from planeslam.sim.procedural import GENERATOR_VERSION, Recipe, build_sequence
from planeslam.sim.render import RenderedFrame, render_frame
from planeslam.sim.scene_model import Scene

SLIDE_M = 0.05
"""How far each test slide moves the camera [m]: a robot's half step."""
UNCHANGED_SHARE = 1e-4
"""A slide that changes fewer than this share of the image's pixels (about 30 of 640 x
480) leaves the frame blind along it: rasterisation at the borders, not evidence."""
DEPTH_CHANGE_M = 1e-4
"""A pixel's depth changed by more than this [m] counts as changed (noise-free render:
the rest is float rounding)."""
AXES = "xyz"
SIGHT_FILE = "sight.json"
"""A rendered sequence's blind frames, kept in its folder (`count_blind_frames`)."""


@dataclass(frozen=True)
class FrameSight:
    """What one frame's image says about its position."""

    frame: int
    changed_share: tuple[float, float, float]
    """Share of the image's pixels (colour or depth) that a slide of SLIDE_M along the world
    x, y and z axes changes, in [0, 1]."""

    @property
    def blind_axes(self) -> str:
        """The world axes ('x', 'y', 'z') along which the image does not place the camera."""
        shares = zip(AXES, self.changed_share, strict=True)
        return "".join(axis for axis, share in shares if share < UNCHANGED_SHARE)


def _changed_share(a: RenderedFrame, b: RenderedFrame) -> float:
    """Share of all pixels whose colour or depth differ between two noise-free renders."""
    colour = np.any(a.rgb != b.rgb, axis=2)
    depth = np.abs(a.depth_true_m - b.depth_true_m) > DEPTH_CHANGE_M
    return float(np.count_nonzero(colour | depth)) / colour.size


def frame_sight(
    scene: Scene, T_world_cam: np.ndarray, camera: CameraConfig, frame: int = 0
) -> FrameSight:
    """How much of the view at T_world_cam (4, 4) each world-axis slide changes."""
    rng = np.random.default_rng(0)  # unused: noise-free renders draw nothing
    base = render_frame(scene, T_world_cam, camera, rng, noise=False)
    shares = []
    for axis in range(3):
        slid = np.array(T_world_cam, dtype=np.float64)
        slid[axis, 3] += SLIDE_M
        shares.append(_changed_share(base, render_frame(scene, slid, camera, rng, noise=False)))
    return FrameSight(frame, (shares[0], shares[1], shares[2]))


def blind_frames(scene: Scene, T_world_cam: np.ndarray, camera: CameraConfig) -> list[FrameSight]:
    """The frames of the path T_world_cam (N, 4, 4) whose images leave some world axis
    unplaced (`FrameSight.blind_axes`), in order."""
    sights = (frame_sight(scene, T, camera, i) for i, T in enumerate(T_world_cam))
    return [s for s in sights if s.blind_axes]


def count_blind_frames(
    recipe: Recipe, folder: Path, camera: CameraConfig, max_frames: int | None = None
) -> int:
    """How many frames of `recipe`'s path (`max_frames`: its first frames only), seen by
    `camera`, are blind (`blind_frames`); counted once and kept in folder/sight.json with
    what the count depends on, and the blind frames with their axes."""
    file = folder / SIGHT_FILE
    key = {
        "recipe": recipe.record(),
        "generator_version": GENERATOR_VERSION,
        "camera": [camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height],
        "max_frames": max_frames,
        "slide_m": SLIDE_M,
        "unchanged_share": UNCHANGED_SHARE,
    }
    if file.is_file():
        try:
            stored = json.loads(file.read_text(encoding="utf-8"))
            if stored["key"] == key:
                return int(stored["blind_frames"])
        except (OSError, ValueError, KeyError, TypeError):
            pass  # unreadable or another count's: counted afresh
    scene, path = build_sequence(recipe)
    blind = blind_frames(scene, path.T_world_cam[:max_frames], camera)
    record = {
        "key": key,
        "blind_frames": len(blind),
        "frames": [[sight.frame, sight.blind_axes] for sight in blind],
    }
    write_text_atomic(file, json.dumps(record) + "\n")  # a reader never sees half of it
    return len(blind)
