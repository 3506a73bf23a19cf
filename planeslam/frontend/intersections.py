"""Real intersections between planes of one frame (paper Section 4.1, eq. 1-6).

Two planes have a *real* intersection (an edge) when some of their inliers
lie close to both planes (eq. 1-5). Candidate pairs come from the label
image: only planes whose regions touch in the image (within a few pixels)
are tested, which keeps the stage fast and excludes far-apart planes.

For a candidate pair (A, B) with intersection line x(t) = p0 + t u:

- edge points of A are A's inliers with |n_B . x + d_B| < d_thresh (eq. 3),
  and symmetrically for B (eq. 5); eq. 2 and 4 (distance to the own plane)
  hold for inliers by construction;
- each side's edge points give an extent [lo, hi] along u, from the points
  farther than `extent_min_sigmas` sigma(z) from the other plane when a
  quarter of them are (points that fit both planes are ambiguous: where a box
  side's plane meets the floor beyond the side's end, a segmenter hands some
  floor pixels to the side, and they stretched box-floor edges by 2-4 cm): at most
  `extent_trim_points` (and at most 1 %) of them are trimmed at each end
  against stray inliers, and each end is pushed out by (k + 1) mean point
  spacings (samples stop about one spacing short of a true end; trimming k
  more). The edge is the *overlap* of the two sides' extents. The overlap
  matters: a floor's points near the plane of a box face run along the whole
  floor, but the box face's own points near the floor stop at the box;
- for a convex edge the union of the two extents is used instead (two faces of
  one solid end together; a side whose points stop early lost pixels to the
  segmenter where its face narrows to a thin wedge);
- `length_m` is that length; `length_eq6_m` is the paper's eq. 6 on
  the same edge points (farthest pair within the raw common extent, d_edge =
  sqrt(d_diag^2 - 4 d_thresh^2)). The overlap extent is the more accurate of
  the two: on the fully visible edges of the synthetic box/room frames at
  1-2 m (tests/test_intersections.py) it errs by -1.0 mm mean, 3.6 mm RMS
  against -2.9 mm, 4.8 mm RMS for eq. 6. Eq. 6 assumes the farthest pair
  lies on opposite sides of a cylinder of radius d_thresh, whereas edge
  points lie on the two faces (an L-shaped cross-section), so it tends to
  shorten edges by up to 2 d_thresh^2 / length.

d_min: the paper keeps points whose distances to both planes are "smaller
than d_thresh and greater than d_min", d_min "to deal with noise", with no
value. Read literally it removes the points nearest the line; it is offered
as `d_min_m` (default 0, off). Noise is handled instead by requiring
`min_edge_points` on each side and by the trimmed extent.

Convexity as seen from the camera (normals point toward the camera): let
u_A be the in-plane direction from the line into A's region. The edge is
convex (a box edge) when each region lies on the back side of the other
plane, n_B . u_A < 0 and n_A . u_B < 0: both faces are then outer faces of
one solid wedge whose outward normals face the camera. It is concave (a room
edge) when both lie on the front side (> 0). The side of each region is the
sign of the mean signed distance to the other plane of its edge points
within the edge's extent (about +-d_thresh / 2, far above the noise after
averaging); plane centroids would mislead when a floor extends on both sides
of a box face's plane. The rare mixed case (a thin sheet seen across) is
decided by the sum of both means.

Speed: a plane with more than `max_points_per_plane` inliers is strided
down; one compiled pass per plane (`kernels.band_points_kernel`) finds its
points near each partner plane, and everything after the sort of those few
points, for all pairs at once, is one more compiled pass
(`kernels.edge_extents_kernel`). Both do the arithmetic of the numpy code they
replaced in its order, so the edges are the same bit for bit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.errors import GeometryError
from planeslam.frontend.config import IntersectionConfig
from planeslam.frontend.kernels import (
    band_points_kernel,
    contact_counts_kernel,
    edge_extents_kernel,
)
from planeslam.frontend.types import Plane, Segmentation

logger = logging.getLogger(__name__)

EQ6_ENDS = 8
"""Eq. 6 searches the farthest pair among this many extreme edge points of each side at
each end of the common extent."""


@dataclass(frozen=True)
class Edge:
    """A real intersection of two planes, camera frame."""

    planes: tuple[int, int]
    """Ids of the two planes, smaller first."""
    segment: np.ndarray = field(repr=False)
    """(2, 3) end points of the edge on the planes' intersection line [m]."""
    length_m: float
    """Robust extent of the edge points along the line [m]."""
    length_eq6_m: float
    """Length by the paper's eq. 6 from the farthest pair of edge points [m]."""
    angle_rad: float
    """Dihedral angle between the two plane regions [rad] (pi/2 for a box edge)."""
    convex: bool
    """True when the edge points toward the camera (box edge), False for a concave (room) one."""
    num_points: int
    """Number of edge points supporting it (at full resolution: subsampled points
    count for the points they stand for)."""


def candidate_pairs(
    labels: np.ndarray, adjacency_px: int = 8, stride: int = 2, min_contact_px: int = 4
) -> np.ndarray:
    """Pairs of plane ids whose regions touch in the image -> (M, 2) int, smaller id first.

    `labels` (H, W) int with -1 for no plane. On the label grid subsampled by
    `stride`, a pixel and the one `adjacency_px` further right (or down) with
    two different plane ids count as one contact; pairs with at least
    `min_contact_px` contacts are returned, sorted.
    """
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise GeometryError(f"labels must be an (H, W) image, got shape {labels.shape}")
    grid = labels[::stride, ::stride]
    if grid.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    counts = contact_counts_kernel(grid, max(1, int(round(adjacency_px / stride))))
    if len(counts) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    return np.argwhere(counts >= min_contact_px).astype(np.int64, copy=False)


def intersection_lines(
    n_a: np.ndarray, d_a: np.ndarray, n_b: np.ndarray, d_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Intersection lines of P plane pairs, vectorised `geometry.plane_line`.

    (P, 3) unit normals and (P,) offsets of planes A and B -> points (P, 3) [m]
    closest to the origin (so p0 . u = 0) and unit directions u = n_a x n_b /
    |n_a x n_b| (P, 3). Raises GeometryError for a parallel pair.
    """
    cos = np.einsum("pk,pk->p", n_a, n_b)
    sin2 = 1.0 - cos**2
    if np.any(sin2 < 1e-12):
        raise GeometryError("intersection_lines: a plane pair is parallel")
    u = np.cross(n_a, n_b) / np.sqrt(sin2)[:, None]
    # p0 = a n_a + b n_b with n_a . p0 = -d_a and n_b . p0 = -d_b.
    p0 = ((d_b * cos - d_a) / sin2)[:, None] * n_a + ((d_a * cos - d_b) / sin2)[:, None] * n_b
    return p0, u


def _inlier_points(plane: Plane, max_points: int) -> tuple[np.ndarray, int]:
    """((K, 3) float64 inliers [m], stride): every stride-th of them is used, at most
    `max_points` when that is > 0."""
    pts = np.asarray(plane.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GeometryError(f"plane {plane.id}: points must be (K, 3), got shape {pts.shape}")
    stride = 1
    if max_points and len(pts) > max_points:
        stride = int(np.ceil(len(pts) / max_points))
    return pts, stride


def find_intersections(
    segmentation: Segmentation,
    config: IntersectionConfig | None = None,
    sensor: DepthNoiseConfig | None = None,
) -> list[Edge]:
    """All real intersections between the planes of one frame (paper eq. 1-6).

    Camera frame, metres. Candidate pairs are planes whose regions touch in
    `segmentation.labels` and are not nearly parallel. Each plane's points
    are scored against all its partners in one compiled pass; everything
    after that runs on the points near a partner plane, for all pairs at
    once. Returns the edges sorted by plane ids; an empty list for
    fewer than two planes. `sensor`: the depth noise sigma(z) of `extent_min_sigmas`
    (default `DepthNoiseConfig()`).
    """
    cfg = config or IntersectionConfig()
    noise = sensor or DepthNoiseConfig()
    planes = {int(p.id): p for p in segmentation.planes}
    if len(planes) < 2:
        return []
    pairs = np.array(
        [
            (int(i), int(j))
            for i, j in candidate_pairs(
                segmentation.labels, cfg.adjacency_px, cfg.label_stride, cfg.min_contact_px
            )
            if int(i) in planes and int(j) in planes
        ],
        dtype=np.int64,
    ).reshape(-1, 2)
    # Every plane's (3,) normal and offset [m] as one row of `normals`, `offsets`.
    row_of = {pid: r for r, pid in enumerate(planes)}
    normals = np.array([p.normal for p in planes.values()], dtype=np.float64).reshape(-1, 3)
    offsets = np.array([p.d for p in planes.values()], dtype=np.float64)
    row_a = np.array([row_of[i] for i in pairs[:, 0].tolist()], dtype=np.int64)
    row_b = np.array([row_of[j] for j in pairs[:, 1].tolist()], dtype=np.int64)
    n_a, n_b, d_a, d_b = normals[row_a], normals[row_b], offsets[row_a], offsets[row_b]
    cos = np.einsum("pk,pk->p", n_a, n_b)
    sin2 = 1.0 - cos**2
    ok = sin2 >= np.sin(np.deg2rad(cfg.min_angle_deg)) ** 2
    pairs, n_a, n_b, d_a, d_b, cos, sin2 = (v[ok] for v in (pairs, n_a, n_b, d_a, d_b, cos, sin2))
    npairs = len(pairs)
    if npairs == 0:
        return []
    p0, u = intersection_lines(n_a, d_a, n_b, d_b)

    # Band points of every directed pair: group 2p = A's points near plane B (eq. 3),
    # group 2p + 1 = B's points near plane A (eq. 5).
    partners: dict[int, list[tuple[int, int]]] = {}
    for p, (i, j) in enumerate(pairs.tolist()):
        partners.setdefault(i, []).append((j, 2 * p))
        partners.setdefault(j, []).append((i, 2 * p + 1))
    # Per plane, one compiled pass over its points against all its partner planes: their
    # signed distances, and for the points near a partner the coordinate t along the
    # pair's line (the products of a (2 deg, 3) @ (3, K) BLAS product, bit for bit).
    ss, ts, gs, xyzs = [], [], [], []
    stride = np.ones(2 * npairs)  # per group: subsampling of the plane its points come from
    for i, plist in partners.items():
        pts, stride_i = _inlier_points(planes[i], cfg.max_points_per_plane)
        gids = np.array([g for _, g in plist], dtype=np.int64)
        stride[gids] = stride_i
        rows = [row_of[j] for j, _ in plist]
        g_i, s_i, t_i, xyz_i = band_points_kernel(
            pts,
            stride_i,
            normals[rows],
            offsets[rows],
            u[gids // 2],
            gids,
            float(cfg.d_thresh_m),
            float(cfg.d_min_m),
        )
        gs.append(g_i)
        ss.append(s_i)
        ts.append(t_i)
        xyzs.append(xyz_i)
    # Edge points of all directed pairs, sorted by (group, t along the line).
    t = np.concatenate(ts)
    g = np.concatenate(gs)
    # One argsort of a composite (group, t) key: ~10x faster than np.lexsort.
    width = 2.0 * float(np.max(np.abs(t), initial=0.0)) + 1.0
    key = g * width + t
    order = np.argsort(key)
    se, xyz_e = np.concatenate(ss)[order], np.concatenate(xyzs)[order]
    if cfg.extent_min_sigmas > 0:
        # Extents from the points that fit only their own plane, where enough remain;
        # where that band would be most of d_thresh (far points) all points count.
        amb = cfg.extent_min_sigmas * noise.sigma_m(xyz_e[:, 2])
        core = (np.abs(se) >= amb) | (amb >= 0.5 * cfg.d_thresh_m)
    else:
        core = np.ones(len(se), dtype=bool)
    lo, hi, valid, convex, support, eq6, side = edge_extents_kernel(
        key[order],
        g[order],
        t[order],
        se,
        core,
        xyz_e,
        stride,
        width,
        int(cfg.extent_trim_points),
        int(cfg.min_edge_points),
        max(float(cfg.min_length_m), 1e-9),
        4.0 * float(cfg.d_thresh_m) ** 2,
        EQ6_ENDS,
    )
    mixed = valid & ((side[0::2] < 0) != (side[1::2] < 0))
    if np.any(mixed):
        logger.debug("pairs %s: regions on mixed sides, decided by the sum", pairs[mixed].tolist())
    angle = np.arctan2(np.sqrt(sin2), -cos)  # pi - angle between the normals
    edges = []
    for p in np.flatnonzero(valid).tolist():
        edges.append(
            Edge(
                planes=(int(pairs[p, 0]), int(pairs[p, 1])),
                segment=p0[p] + np.array([[lo[p]], [hi[p]]]) * u[p],
                length_m=float(hi[p] - lo[p]),
                length_eq6_m=float(eq6[p]),
                angle_rad=float(angle[p]),
                convex=bool(convex[p]),
                num_points=int(support[p]),
            )
        )
    logger.debug("%d candidate pairs -> %d real intersections", npairs, len(edges))
    return edges
