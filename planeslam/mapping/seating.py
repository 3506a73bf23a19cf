"""Seat map geometry on its planes: points and outlines projected onto a plane, edge
segments put on the intersection line of their two planes."""

from __future__ import annotations

from collections.abc import Set
from dataclasses import replace

import numpy as np

from planeslam.core.geometry import convex_hull_2d, convex_polygon_gap, plane_basis, polygon_area
from planeslam.mapping.contents import MapContents


def project_to_plane(points: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    """Orthogonal projection of (K, 3) points onto the plane n . x + d = 0 (unit n)."""
    return points - np.outer(points @ n + d, n)


def hull_on_plane(points: np.ndarray, n: np.ndarray, d: float) -> tuple[np.ndarray, float]:
    """Convex hull of (K, 3) points projected onto the plane (unit n, d): ((H, 3) polygon on
    the plane, counter-clockwise about n, and its area [m^2]). Degenerate input (fewer than
    3 points, collinear) gives the projected points and area 0."""
    foot = -d * n
    axes = plane_basis(n)
    ring = convex_hull_2d((points - foot) @ axes.T)  # counter-clockwise in (u, v), u x v = n
    if len(ring) == 0:
        return project_to_plane(points, n, d), 0.0
    return foot + ring @ axes, polygon_area(ring)


def outline_gap(outline_a: np.ndarray, outline_b: np.ndarray, n: np.ndarray, d: float) -> float:
    """Gap [m] between the convex hulls of two outlines ((K, 3), world frame) projected onto
    the plane (unit n, d); 0 when they overlap."""
    axes, foot = plane_basis(n), -d * n
    return convex_polygon_gap(
        convex_hull_2d((outline_a - foot) @ axes.T), convex_hull_2d((outline_b - foot) @ axes.T)
    )


def seat_segments(
    segments: np.ndarray,
    lengths_m: np.ndarray,
    n1: np.ndarray,
    d1: np.ndarray,
    n2: np.ndarray,
    d2: np.ndarray,
    min_sin: float = 0.1,
) -> np.ndarray:
    """(E, 2, 3) segments of `lengths_m` (E,) on the intersection lines of the plane pairs
    (n1 (E, 3), d1 (E,)) and (n2, d2): centred on the projection of each old segment's
    midpoint and pointing like it. Pairs closer to parallel than `min_sin` keep their old
    segment (as `planeslam.core.geometry.plane_line` refuses them)."""
    u = np.cross(n1, n2)
    s = np.linalg.norm(u, axis=1)
    ok = s >= min_sin
    out = np.array(segments, dtype=np.float64, copy=True)
    if not ok.any():
        return out
    u = u[ok] / s[ok, None]
    A = np.stack([n1[ok], n2[ok], u], axis=1)  # (E', 3, 3)
    b = np.stack([-d1[ok], -d2[ok], np.zeros(int(ok.sum()))], axis=1)
    p0 = np.linalg.solve(A, b[..., None])[..., 0]  # the line's point closest to the origin
    seg = out[ok]
    u = u * np.where(np.einsum("ei,ei->e", u, seg[:, 1] - seg[:, 0]) < 0, -1.0, 1.0)[:, None]
    mid = p0 + np.einsum("ei,ei->e", seg.mean(axis=1) - p0, u)[:, None] * u
    half = 0.5 * np.asarray(lengths_m, dtype=np.float64)[ok, None] * u
    out[ok] = np.stack([mid - half, mid + half], axis=1)
    return out


def reseat_edges(contents: MapContents, plane_ids: Set[int], update_angles: bool = False) -> None:
    """Put the segments of the map edges touching `plane_ids` on the current intersection
    lines of their planes (lengths kept); optionally recompute their dihedral angles from
    the normals."""
    keys = [k for k in contents.edges if k[0] in plane_ids or k[1] in plane_ids]
    if not keys:
        return
    edges = [contents.edges[k] for k in keys]
    a = [contents.planes[k[0]] for k in keys]
    b = [contents.planes[k[1]] for k in keys]
    n1, n2 = np.stack([p.normal for p in a]), np.stack([p.normal for p in b])
    segs = seat_segments(
        np.stack([e.segment for e in edges]),
        np.array([e.length_m for e in edges]),
        n1,
        np.array([p.d for p in a]),
        n2,
        np.array([p.d for p in b]),
    )
    angles = np.arctan2(np.linalg.norm(np.cross(n1, n2), axis=1), -np.einsum("ei,ei->e", n1, n2))
    for k, key in enumerate(keys):
        e = edges[k]
        angle = float(angles[k]) if update_angles else e.angle_rad
        contents.edges[key] = replace(e, segment=segs[k], angle_rad=angle)
