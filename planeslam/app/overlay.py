"""Draw one frame's front-end result on its colour image (the `overlay.png` of
`planeslam frame`).

Planes are tinted semi-transparently by id with a fixed palette and outlined;
real intersections are drawn as their projected 3-D segments (convex: solid
orange, concave: dashed cyan); corners as dots; each object is labelled with
its class and size near the projection of its planes' centroid. A line at the
top summarises the counts and, for an empty or partial frame, the reason.
Colours are RGB. Projection is the pinhole model of `CameraConfig` without
distortion, the same model the front end back-projects depth with.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.errors import DatasetFormatError
from planeslam.core.safe_files import atomic_output

log = logging.getLogger(__name__)

PALETTE = np.array(
    [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (188, 189, 34),
        (23, 190, 207),
        (174, 199, 232),
        (255, 187, 120),
        (152, 223, 138),
        (255, 152, 150),
        (197, 176, 213),
        (196, 156, 148),
        (247, 182, 210),
        (219, 219, 141),
        (158, 218, 229),
        (127, 127, 127),
        (199, 199, 199),
    ],
    dtype=np.uint8,
)
"""(20, 3) RGB plane colours (Tableau 20 reordered: strong colours first); plane id k gets
PALETTE[k % 20]."""

CONVEX_RGB = (255, 140, 0)
"""Colour of convex edges (solid)."""
CONCAVE_RGB = (0, 230, 255)
"""Colour of concave edges (dashed)."""
CORNER_RGB = (255, 0, 255)
"""Fill colour of corner dots."""
PLANE_ALPHA = 0.45
"""Opacity of the plane tint."""
MIN_OUTLINE_AREA_PX = 40.0
"""Pieces of a plane's mask smaller than this get no outline (speckle) [pixels]."""
MIN_DEPTH_M = 0.05
"""Segments are clipped to z >= this before projection [m]."""


def project_points(points_cam: np.ndarray, camera: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of camera-frame points.

    (N, 3) points [m] (x right, y down, z forward) -> ((N, 2) float64 pixel
    coordinates (u, v), (N,) bool in front of the camera, z >= MIN_DEPTH_M).
    Points behind the camera get (nan, nan).
    """
    pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = pts[:, 2]
    ok = np.isfinite(pts).all(axis=1) & (z >= MIN_DEPTH_M)
    zs = np.where(ok, z, 1.0)
    uv = np.stack(
        [camera.fx * pts[:, 0] / zs + camera.cx, camera.fy * pts[:, 1] / zs + camera.cy], 1
    )
    uv[~ok] = np.nan
    return uv, ok


def _clip_segment_near(segment: np.ndarray) -> np.ndarray | None:
    """(2, 3) segment -> the part with z >= MIN_DEPTH_M, or None when none is."""
    a, b = np.asarray(segment, dtype=np.float64)
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        return None
    za, zb = a[2] - MIN_DEPTH_M, b[2] - MIN_DEPTH_M
    if za < 0 and zb < 0:
        return None
    if za < 0 or zb < 0:
        t = za / (za - zb)
        cut = a + t * (b - a)
        a, b = (cut, b) if za < 0 else (a, cut)
    return np.stack([a, b])


def _pt(uv: np.ndarray) -> tuple[int, int]:
    return int(round(float(uv[0]))), int(round(float(uv[1])))


def _draw_line(
    image: np.ndarray,
    p0: np.ndarray,
    p1: np.ndarray,
    rgb: tuple[int, int, int],
    width: int,
    dashed: bool,
) -> None:
    """A line with a dark halo for contrast; dashed as 10 px on, 6 px off."""
    length = float(np.hypot(*(p1 - p0)))
    if not np.isfinite(length) or length > 1e5:
        return
    if dashed and length > 16:
        starts = np.arange(0.0, length, 16.0)
        pieces = [
            (p0 + (p1 - p0) * s / length, p0 + (p1 - p0) * min(s + 10.0, length) / length)
            for s in starts
        ]
    else:
        pieces = [(p0, p1)]
    for colour, w in (((0, 0, 0), width + 2), (rgb, width)):
        for a, b in pieces:
            cv2.line(image, _pt(a), _pt(b), colour, w, cv2.LINE_AA)


def _draw_label(
    image: np.ndarray,
    text: str,
    anchor: tuple[int, int],
    scale: float,
    rgb: tuple[int, int, int],
    above: bool = False,
) -> None:
    """Text on a dark box, centred on `anchor` (or just above it) and kept inside the image."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    thick = max(1, int(round(scale * 2)))
    (tw, th), base = cv2.getTextSize(text, font, scale, thick)
    h, w = image.shape[:2]
    x = int(np.clip(anchor[0] - tw // 2, 2, max(2, w - tw - 2)))
    y = anchor[1] - base - 4 if above else anchor[1] + th // 2
    y = int(np.clip(y, th + 2, max(th + 2, h - base - 2)))
    cv2.rectangle(image, (x - 2, y - th - 2), (x + tw + 2, y + base + 1), (0, 0, 0), -1)
    cv2.putText(image, text, (x, y), font, scale, rgb, thick, cv2.LINE_AA)


def _wrap(text: str, font: int, scale: float, thick: int, max_width: int) -> list[str]:
    """Split `text` at spaces into lines no wider than max_width pixels (greedy)."""
    lines: list[str] = []
    for word in text.split(" "):
        trial = f"{lines[-1]} {word}" if lines else word
        if lines and cv2.getTextSize(trial, font, scale, thick)[0][0] <= max_width:
            lines[-1] = trial
        else:
            lines.append(word)
    return lines


def _draw_banner(image: np.ndarray, text: str, scale: float) -> None:
    """Text (wrapped) on a darkened band across the top of the image."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    thick = max(1, int(round(scale * 2)))
    (_, th), base = cv2.getTextSize(text, font, scale, thick)
    lines = _wrap(text, font, scale, thick, image.shape[1] - 8)
    step = th + base + 2
    band = step * len(lines) + 4
    image[:band] = (image[:band].astype(np.float32) * 0.35).astype(np.uint8)
    for k, line in enumerate(lines):
        org = (4, th + 3 + k * step)
        cv2.putText(image, line, org, font, scale, (255, 255, 255), thick, cv2.LINE_AA)


def format_size(size_m: tuple[float, ...] | list[float]) -> str:
    """(0.38, 0.29, 0.19) -> '0.38x0.29x0.19 m' (largest first); '' for no size."""
    values = sorted((float(v) for v in size_m), reverse=True)
    return "x".join(f"{v:.2f}" for v in values) + " m" if values else ""


def summary_line(observation: Any) -> str:
    """'7 planes, 5 edges (2 convex), 1 corner, 1 object' plus ': <reason>' when there is one."""
    seg, st = observation.segmentation, observation.structure
    convex = sum(bool(e.convex) for e in st.edges)

    def n(k: int, word: str) -> str:
        return f"{k} {word}{'' if k == 1 else 's'}"

    text = (
        f"{n(len(seg.planes), 'plane')}, {n(len(st.edges), 'edge')} ({convex} convex), "
        f"{n(len(st.corners), 'corner')}, {n(len(st.objects), 'object')}"
    )
    reason = observation.reason
    return f"{text}: {reason}" if reason else text


def tint_planes(rgb: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB with every pixel of plane k (labels (H, W), -1 off planes)
    blended with PALETTE[k % 20] at PLANE_ALPHA; a new image."""
    on_plane = labels >= 0
    tint = PALETTE[np.where(on_plane, labels, 0) % len(PALETTE)]
    blended = (1.0 - PLANE_ALPHA) * rgb + PLANE_ALPHA * tint
    return np.where(on_plane[..., None], np.rint(blended), rgb).astype(np.uint8)


def draw_overlay(
    rgb: np.ndarray, observation: Any, camera: CameraConfig, legend: bool = True
) -> np.ndarray:
    """The front end's result drawn on the frame's colour image.

    rgb: (H, W, 3) uint8 RGB; observation: a `planeslam.frontend.pipeline.FrameObservation`
    of the same frame (camera frame, metres); camera: its intrinsics. Returns a
    new (H, W, 3) uint8 RGB image. Pixels on no plane keep their colour except
    where edges, corners, labels and (with `legend`) the top summary line are drawn.
    """
    image = np.asarray(rgb)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise DatasetFormatError(
            f"overlay needs an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}"
        )
    seg, st = observation.segmentation, observation.structure
    labels = np.asarray(seg.labels)
    if labels.shape != image.shape[:2]:
        raise DatasetFormatError(
            f"overlay: labels are {labels.shape} but the image is {image.shape[:2]} (H, W)"
        )
    scale = max(0.35, 0.5 * image.shape[1] / 640.0)
    width = max(2, int(round(2 * image.shape[1] / 640.0)))

    out = tint_planes(image, labels)

    # Outlines and id tags per plane, from the pixel masks (what the tint shows).
    for plane in seg.planes:
        mask = (labels == plane.id).astype(np.uint8)
        if not mask.any():
            continue
        r, g, b = (int(c) for c in PALETTE[plane.id % len(PALETTE)])
        colour = (r, g, b)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        contours = [c for c in contours if cv2.contourArea(c) >= MIN_OUTLINE_AREA_PX]
        cv2.drawContours(out, contours, -1, colour, width, cv2.LINE_AA)
        inner = cv2.distanceTransform(mask, cv2.DIST_L2, 3)
        v, u = np.unravel_index(int(np.argmax(inner)), inner.shape)
        _draw_label(out, str(plane.id), (int(u), int(v)), scale * 0.8, colour)

    for edge in st.edges:
        seg3 = _clip_segment_near(edge.segment)
        if seg3 is None:
            continue
        uv, _ = project_points(seg3, camera)
        _draw_line(
            out, uv[0], uv[1], CONVEX_RGB if edge.convex else CONCAVE_RGB, width, not edge.convex
        )

    # Labels just above their planes' centroid and before the corners, which stay visible.
    centroids = {p.id: np.asarray(p.centroid, dtype=np.float64) for p in seg.planes}
    for obj in st.objects:
        pts = [centroids[k] for k in obj.planes if k in centroids]
        if not pts:
            continue
        uv, ok = project_points(np.mean(pts, axis=0)[None], camera)
        if not ok[0]:
            continue
        text = f"{obj.cls} {format_size(obj.size_m)}".strip()
        _draw_label(out, text, _pt(uv[0]), scale, (255, 255, 255), above=True)

    if st.corners:
        uv, ok = project_points(np.array([c.point for c in st.corners]), camera)
        radius = max(3, 2 * width + 1)
        for p in uv[ok]:
            cv2.circle(out, _pt(p), radius + 1, (0, 0, 0), -1, cv2.LINE_AA)
            cv2.circle(out, _pt(p), radius, CORNER_RGB, -1, cv2.LINE_AA)

    if legend or observation.reason:
        _draw_banner(out, summary_line(observation), scale)
    return out


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an (H, W, 3) uint8 RGB image as PNG (parent folders created) -> the path."""
    path = Path(path)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise DatasetFormatError(
            f"{path}: expected an (H, W, 3) uint8 RGB image, got {image.shape}"
        )
    with atomic_output(path, keep_suffix=True) as tmp:  # never through a link at `path`
        if not cv2.imwrite(str(tmp), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
            raise DatasetFormatError(f"{path}: could not write the PNG image")
    return path
