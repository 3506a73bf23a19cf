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
down; everything after one small matrix product per plane runs on the few
points near a partner plane, for all pairs at once.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.errors import GeometryError
from planeslam.frontend.config import IntersectionConfig
from planeslam.frontend.types import Plane, Segmentation

logger = logging.getLogger(__name__)


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
    n = int(grid.max()) + 1
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    k = max(1, int(round(adjacency_px / stride)))
    keys = []
    for a, b in ((grid[:, :-k], grid[:, k:]), (grid[:-k, :], grid[k:, :])):
        lo = np.minimum(a, b)
        hi = np.maximum(a, b)
        touch = (lo >= 0) & (lo != hi)
        keys.append(lo[touch].astype(np.int64) * n + hi[touch])
    counts = np.bincount(np.concatenate(keys), minlength=n * n)
    idx = np.flatnonzero(counts >= min_contact_px)
    return np.stack([idx // n, idx % n], axis=1)


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
    """((3, K') inliers as contiguous coordinate rows, stride): strided down to at most
    `max_points` when that is > 0 (contiguous rows keep the products below in BLAS)."""
    pts = np.asarray(plane.points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GeometryError(f"plane {plane.id}: points must be (K, 3), got shape {pts.shape}")
    stride = 1
    if max_points and len(pts) > max_points:
        stride = int(np.ceil(len(pts) / max_points))
    return np.ascontiguousarray(pts[::stride].T, dtype=np.float64), stride


def _group_starts(counts: np.ndarray) -> np.ndarray:
    """Start index of each group in an array sorted by group, from (G,) counts."""
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)


def find_intersections(
    segmentation: Segmentation,
    config: IntersectionConfig | None = None,
    sensor: DepthNoiseConfig | None = None,
) -> list[Edge]:
    """All real intersections between the planes of one frame (paper eq. 1-6).

    Camera frame, metres. Candidate pairs are planes whose regions touch in
    `segmentation.labels` and are not nearly parallel. Each plane's points
    are scored against all its partners with one (deg, 3) @ (3, K) product;
    everything after that runs on the points near a partner plane, for all
    pairs at once. Returns the edges sorted by plane ids; an empty list for
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
    n_a = np.array([planes[i].normal for i in pairs[:, 0]], dtype=np.float64).reshape(-1, 3)
    n_b = np.array([planes[j].normal for j in pairs[:, 1]], dtype=np.float64).reshape(-1, 3)
    d_a = np.array([planes[i].d for i in pairs[:, 0]], dtype=np.float64)
    d_b = np.array([planes[j].d for j in pairs[:, 1]], dtype=np.float64)
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
    # One (2 deg, 3) @ (3, K) product per plane gives its points' signed distances
    # to each partner plane and their coordinates t along each pair's line.
    point_sets: list[np.ndarray] = []
    ss, ts, gs, srcs, cols, zs = [], [], [], [], [], []
    stride = np.ones(2 * npairs)  # per group: subsampling of the plane its points come from
    for i, plist in partners.items():
        pts, stride_i = _inlier_points(planes[i], cfg.max_points_per_plane)
        deg = len(plist)
        gids = np.array([g for _, g in plist], dtype=np.int64)
        stride[gids] = stride_i
        rows = np.concatenate([[planes[j].normal for j, _ in plist], u[gids // 2]])
        proj = rows @ pts  # (2 deg, K)
        signed = proj[:deg] + np.array([planes[j].d for j, _ in plist])[:, None]  # [m]
        near = np.abs(signed) < cfg.d_thresh_m
        if cfg.d_min_m > 0:
            near &= np.abs(signed) >= cfg.d_min_m
        flat = np.flatnonzero(near)  # much faster than 2-D nonzero
        row, col = np.divmod(flat, near.shape[1])
        ss.append(signed.ravel()[flat])
        ts.append(proj[deg:].ravel()[flat])
        zs.append(pts[2, col])
        gs.append(gids[row])
        srcs.append(np.full(len(flat), len(point_sets), dtype=np.int64))
        cols.append(col)
        point_sets.append(pts)
    # Edge points of all directed pairs, sorted by (group, t along the line).
    t = np.concatenate(ts)
    g = np.concatenate(gs)
    # One argsort of a composite (group, t) key: ~10x faster than np.lexsort.
    width = 2.0 * float(np.max(np.abs(t), initial=0.0)) + 1.0
    order = np.argsort(g * width + t)
    se, ge, te = np.concatenate(ss)[order], g[order], t[order]
    ze = np.concatenate(zs)[order]
    src, col = np.concatenate(srcs)[order], np.concatenate(cols)[order]
    pe = ge // 2

    # Per group: trimmed extent (robust to stray inliers) and raw extent.
    ngroups = 2 * npairs
    cnt = np.bincount(ge, minlength=ngroups)
    start = _group_starts(cnt)
    last = start + np.maximum(cnt, 1) - 1
    te_pad = np.append(te, 0.0)  # groups without points read a dummy
    rlo_g = te_pad[np.where(cnt > 0, start, len(te))]
    rhi_g = te_pad[np.where(cnt > 0, last, len(te))]
    lo_g, hi_g = _trimmed_extents(te, ge, cnt, cfg.extent_trim_points)
    if cfg.extent_min_sigmas > 0:
        # Extents from the points that fit only their own plane, where enough remain.
        sigma = noise.sigma_m(ze)
        # Where that band would be most of d_thresh (far points) all points count.
        amb = cfg.extent_min_sigmas * sigma
        core = (np.abs(se) >= amb) | (amb >= 0.5 * cfg.d_thresh_m)
        cnt_core = np.bincount(ge[core], minlength=ngroups)
        lo_c, hi_c = _trimmed_extents(te[core], ge[core], cnt_core, cfg.extent_trim_points)
        # A thin core band (noise near d_thresh, far planes) samples the ends poorly.
        enough = (cnt_core * stride >= cfg.min_edge_points) & (cnt_core >= 0.25 * cnt)
        lo_g, hi_g = np.where(enough, lo_c, lo_g), np.where(enough, hi_c, hi_g)
    # The edge is the overlap of both sides' extents.
    lo = np.maximum(lo_g[0::2], lo_g[1::2])
    hi = np.minimum(hi_g[0::2], hi_g[1::2])
    # Edge-point counts in full-resolution terms, so the decision ignores subsampling.
    support_g = cnt * stride
    valid = (np.minimum(support_g[0::2], support_g[1::2]) >= cfg.min_edge_points) & (
        hi - lo >= max(cfg.min_length_m, 1e-9)
    )

    # Side of each region relative to the other plane: mean signed distance of its
    # edge points within the edge's extent (about +-d_thresh / 2; noise averages out).
    in_edge = (te >= lo[pe]) & (te <= hi[pe])
    w = in_edge.astype(np.float64)
    side = np.bincount(ge, weights=se * w, minlength=ngroups) / np.maximum(
        np.bincount(ge, weights=w, minlength=ngroups), 1.0
    )
    convex = side[0::2] + side[1::2] < 0
    mixed = valid & ((side[0::2] < 0) != (side[1::2] < 0))
    if np.any(mixed):
        logger.debug("pairs %s: regions on mixed sides, decided by the sum", pairs[mixed].tolist())
    support = np.bincount(pe[in_edge], weights=stride[ge[in_edge]], minlength=npairs)
    # A convex edge is where two faces of one solid meet: both faces end where it
    # ends, so a side whose points stop early lost pixels (a face seen as a thin
    # wedge toward its far corner): take the union of the two sides' extents.
    # (A concave edge keeps the overlap: a floor runs on past the box side it meets.)
    both = valid & convex & (np.minimum(cnt[0::2], cnt[1::2]) > 0)
    lo = np.where(both, np.minimum(lo_g[0::2], lo_g[1::2]), lo)
    hi = np.where(both, np.maximum(hi_g[0::2], hi_g[1::2]), hi)

    eq6 = _eq6_lengths(ge, te, src, col, point_sets, rlo_g, rhi_g, cnt, cfg.d_thresh_m)
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


def _trimmed_extents(
    te: np.ndarray, ge: np.ndarray, cnt: np.ndarray, trim: int
) -> tuple[np.ndarray, np.ndarray]:
    """Robust [lo, hi] along the line [m] of each group's points: `te` (K,) sorted by
    (group `ge`, t), `cnt` (G,) points per group. Groups without points get (0, 0)."""
    start = _group_starts(cnt)
    last = start + np.maximum(cnt, 1) - 1
    # Trim at most 1 % of a side's points per end: sparse sides keep all their points.
    k = np.minimum(trim, cnt // 100)
    te_pad = np.append(te, 0.0)  # groups without points read a dummy
    lo = te_pad[np.where(cnt > 0, start + k, len(te))]
    hi = te_pad[np.where(cnt > 0, last - k, len(te))]
    # Samples fall short of a segment's true ends by about one mean spacing, and
    # trimming shrinks it by k more: extend each end by (k + 1) spacings (the
    # unbiased end-point estimate for evenly spread samples).
    spacing = (hi - lo) / np.maximum(cnt - 1 - 2 * k, 1)
    return lo - (k + 1) * spacing, hi + (k + 1) * spacing


def _eq6_lengths(
    ge: np.ndarray,
    te: np.ndarray,
    src: np.ndarray,
    col: np.ndarray,
    point_sets: list[np.ndarray],
    rlo_g: np.ndarray,
    rhi_g: np.ndarray,
    cnt: np.ndarray,
    d_thresh: float,
    ends: int = 8,
) -> np.ndarray:
    """Paper eq. 6 for every pair -> (npairs,) lengths [m].

    The edge points of both sides within their raw common extent; the
    farthest pair of them (searched among the `ends` extreme points of each
    side at each end along the line) is the diagonal of a cylinder of radius
    d_thresh: d_edge = sqrt(d_diag^2 - 4 d_thresh^2). `ge`, `te` are the
    edge points' group and line coordinate sorted by (group, t); point k is
    column `col[k]` of `point_sets[src[k]]` ((3, K) coordinate rows).
    """
    npairs = len(cnt) // 2
    if len(te) == 0:
        return np.zeros(npairs)
    rlo = np.repeat(np.maximum(rlo_g[0::2], rlo_g[1::2]), 2)
    rhi = np.repeat(np.minimum(rhi_g[0::2], rhi_g[1::2]), 2)
    # Index range of each group inside the common extent, by searching (group, t) keys.
    width = 2.0 * float(np.max(np.abs(te))) + 1.0
    key = ge * width + te
    groups = np.arange(len(cnt))
    first = np.searchsorted(key, groups * width + rlo, side="left")
    stop = np.searchsorted(key, groups * width + rhi, side="right")
    n = np.maximum(stop - first, 0)
    offs = np.arange(ends)
    lo_idx = np.minimum(first[:, None] + offs, np.maximum(stop - 1, first)[:, None])
    hi_idx = np.maximum(stop[:, None] - 1 - offs, first[:, None])
    idx = np.clip(np.concatenate([lo_idx, hi_idx], axis=1), 0, len(te) - 1)  # (G, 2 ends)
    xyz = np.zeros(idx.shape + (3,))
    flat_src, flat_col = src[idx], col[idx]
    for k, pts in enumerate(point_sets):  # gather only the few candidates per plane
        mask = flat_src == k
        xyz[mask] = pts[:, flat_col[mask]].T
    # Per pair: low-end candidates of both sides against high-end candidates of both.
    low = xyz[:, :ends].reshape(npairs, 2 * ends, 3)
    high = xyz[:, ends:].reshape(npairs, 2 * ends, 3)
    diff = low[:, :, None, :] - high[:, None, :, :]
    diag2 = np.einsum("pabk,pabk->pab", diff, diff).reshape(npairs, -1)
    ok = np.repeat(n > 0, ends).reshape(npairs, 2 * ends)
    valid = ok[:, :, None] & ok[:, None, :]
    diag2 = np.max(np.where(valid.reshape(npairs, -1), diag2, 0.0), axis=1)
    return np.sqrt(np.maximum(diag2 - 4.0 * d_thresh**2, 0.0))
