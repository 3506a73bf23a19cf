"""A sweep along the direction a partial plane pose leaves free, before the dense fallback.

When the frame's planes fix its rotation but leave one translation direction free (a floor
and a wall, or two walls: the line along both), RGB-D odometry and ICP start where the
last pose or the prediction puts the free part and converge only within a few
centimetres of it: a robot step of 10-20 cm between frames lies outside that basin. The
sweep moves the plane pose along the free direction over a grid and scores every
candidate at once by how well the frame, moved by it, lands on the previous frame: depth
residuals (furniture and edges that the planes do not fix) and grey-level residuals
(texture), each counted beyond the sensor's noise and clipped, so a few outliers cannot
dominate. The best candidate becomes one more start of the dense fallback, which still
refines and accepts it by its own evidence.

Planes that fix the rotation (two normals or more) leave at most one direction free. One
plane (a floor seen by a robot) leaves the turn about its normal and the two directions
along it free: a robot's step and turn. Those three, or two translation directions, are
swept over a coarse grid, whose lowest local minima, refined on a finer grid, become
later starts of the dense fallback (`sweep_free_motion`).

Frames: every pose is T_world_cam (4, 4); the direction in the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from planeslam.core.camera import CameraConfig, nearest_pixels
from planeslam.core.geometry import invert_pose
from planeslam.frontend.cloud import sampled_points

SWEEP_RANGE_M = 0.3
"""Half-width [m] of the sweep: a robot step and the last pose's error together."""
SWEEP_STEP_M = 0.01
"""Grid spacing [m] (61 candidates)."""
SWEEP_STRIDE_PX = 16
"""Every SWEEP_STRIDE_PX-th pixel in each direction is scored (up to 1,200 of 640 x 480)."""
DEPTH_NOISE_M = 0.01
"""Depth residuals count beyond DEPTH_NOISE_M * (1 + depth [m]) only: sensor noise and the
depth's quantisation, which repeats pixel for pixel and would otherwise favour the
candidate that maps every pixel onto itself."""
DEPTH_CLIP_M = 0.05
"""Depth residuals beyond the noise are clipped at this [m]."""
GREY_NOISE = 2.0
"""Grey-level residuals count beyond this: three sigmas of the difference of two frames'
sensor noise after the blur (3 grey levels per pixel, blurred by `COLOUR_BLUR_PX` = 2 px:
0.6), so that a low-contrast texture's few grey levels still count."""
GREY_CLIP = 30.0
"""Grey-level residuals beyond the noise are clipped at this."""
DISTINCT_RATIO = 0.7
"""The best candidate is taken only when its cost is at most this share of the median
cost over the sweep: a flat profile means the free direction is unobservable to depth
and colour too (bare walls), and the sweep says nothing."""
DISTINCT_MIN_COST = 0.02
"""... and at least this much below the median (a bare wall's costs are all near 0)."""
RIVAL_DISTANCE_M = 0.05
"""Local minima of the cost farther than this [m] from the best are its rivals (other
basins)."""
RIVAL_MARGIN = 0.5
"""The best rival must cost more than the best by this share of (median - best): a
repetitive texture's period, or a symmetric layout, leaves two basins alike, and then the
sweep says nothing."""
LANDING_MARGIN = 3e-3
"""Of two poses, the one whose landing cost is lower by less than this does not beat the
other (`lands_better`): 0.3 % of the points fully off, what the parallax of depth noise
costs the true pose at a bare wall's shading (a pose with no translation has none)."""
COARSE_TURN_DEG = 20.0
"""Half-width [deg] of the coarse grid's turn about a free axis: a robot's turn between
frames, with the last pose's error."""
COARSE_TURN_STEP_DEG = 4.0
"""Coarse grid spacing of the turn [deg] (11 turns)."""
COARSE_STEP_M = 0.05
"""Coarse grid spacing [m] along each free direction (13 shifts over SWEEP_RANGE_M)."""
COARSE_STRIDE_PX = 32
"""Every COARSE_STRIDE_PX-th pixel in each direction scores the coarse grid (up to 300)."""
BASINS = 2
"""Lowest local minima of the coarse grid refined on the fine grid: starts of the dense
methods."""
MIN_SCORED_SHARE = 0.3
"""A candidate that puts fewer than this share of the sampled points on the previous
frame's valid depth is not scored."""


@dataclass(frozen=True)
class LastFrame:
    """The previous tracked frame, which the sweep lands the frame on."""

    T_world_cam: np.ndarray
    """(4, 4) its pose."""
    depth: np.ndarray
    """(H, W) its depth [m] (0: invalid)."""
    grey: np.ndarray | None
    """(H, W) float its blurred grey levels, or None."""


def sweep_free_translation(
    T_center: np.ndarray,
    direction: np.ndarray,
    cloud: np.ndarray,
    grey: np.ndarray | None,
    last: LastFrame,
    camera: CameraConfig,
) -> np.ndarray | None:
    """T_center (4, 4) moved along `direction` (3,) (unit, world frame) to the grid shift
    with the lowest cost (`_shift_costs` of the frame's organised cloud (H, W, 3, camera
    frame) and grey levels ((H, W) float or None) against `last`), or None: fewer than 100
    valid points, or no distinct, unrivalled best (`_distinct_best`)."""
    xyz, values = sampled_points(cloud, SWEEP_STRIDE_PX, grey)
    if len(xyz) < 100:
        return None
    shifts = np.arange(-SWEEP_RANGE_M, SWEEP_RANGE_M + SWEEP_STEP_M / 2, SWEEP_STEP_M)
    moves = shifts[:, None] * direction  # (M, 3) world frame
    best = _distinct_best(shifts, _shift_costs(T_center, moves, xyz, values, last, camera))
    if best is None:
        return None
    T = T_center.copy()
    T[:3, 3] += moves[best]
    return T


def sweep_free_motion(
    T_center: np.ndarray,
    axes: np.ndarray,
    directions: np.ndarray,
    cloud: np.ndarray,
    grey: np.ndarray | None,
    last: LastFrame,
    camera: CameraConfig,
) -> list[np.ndarray]:
    """Poses (4, 4) of T_center turned about the free `axes` (K, 3) (unit, world frame,
    K <= 1; about the camera centre) and moved along the free `directions` (L, 3) (unit,
    world frame, 1 <= L <= 2) where the frame lands well on `last`, best first; none when
    nothing is swept, too few points are valid, or nothing lands distinctly well.

    A coarse grid (COARSE_*, every COARSE_STRIDE_PX-th pixel) whose BASINS lowest local
    minima, distinct from its median, are each refined on a grid of half its spacing
    (every SWEEP_STRIDE_PX-th pixel). A texture's basin is narrower than the coarse
    spacing, so these are only starts: the dense methods refine them and the landing cost
    chooses. (One free direction with the rotation fixed has `sweep_free_translation`'s
    finer line instead.)"""
    if len(axes) > 1 or not 1 <= len(directions) <= 2:
        return []
    turns = np.radians(np.arange(-COARSE_TURN_DEG, COARSE_TURN_DEG + 1e-9, COARSE_TURN_STEP_DEG))
    shifts = np.arange(-SWEEP_RANGE_M, SWEEP_RANGE_M + 1e-9, COARSE_STEP_M)
    xyz, values = sampled_points(cloud, COARSE_STRIDE_PX, grey)
    if len(xyz) < 50:
        return []
    grid = [turns] * len(axes) + [shifts] * len(directions)
    poses = _grid_poses(T_center, axes, directions, grid)
    basins = _coarse_basins(_pose_costs(poses, xyz, values, last, camera), [len(g) for g in grid])
    if not basins:
        return []
    half = [np.array([-1.0, -0.5, 0.0, 0.5, 1.0]) * (g[1] - g[0]) for g in grid]
    xyz, values = sampled_points(cloud, SWEEP_STRIDE_PX, grey)
    refined = []
    for basin in basins:
        fine = _grid_poses(poses[basin], axes, directions, half)
        fine_cost = _pose_costs(fine, xyz, values, last, camera)
        k = int(np.argmin(fine_cost))
        refined.append((float(fine_cost[k]), fine[k]))
    return [T for _, T in sorted(refined, key=lambda r: r[0])]


def _coarse_basins(cost: np.ndarray, shape: list[int]) -> list[int]:
    """Indices into `cost` (M,), a grid of `shape` (the last axis varying fastest), of its
    BASINS lowest local minima (no lower neighbour along any axis) that are distinct from
    its median (DISTINCT_RATIO, DISTINCT_MIN_COST); none when nothing is scored."""
    finite = cost[np.isfinite(cost)]
    if not len(finite):
        return []
    median = float(np.median(finite))
    grid = cost.reshape(shape)
    minima = np.isfinite(grid)
    for axis in range(grid.ndim):
        pad = [(1, 1) if a == axis else (0, 0) for a in range(grid.ndim)]
        padded = np.pad(grid, pad, constant_values=np.inf)
        below = np.take(padded, range(grid.shape[axis]), axis=axis)
        above = np.take(padded, range(2, grid.shape[axis] + 2), axis=axis)
        minima &= (grid <= below) & (grid <= above)
    distinct = minima.ravel() & (cost <= min(DISTINCT_RATIO * median, median - DISTINCT_MIN_COST))
    found = np.flatnonzero(distinct)
    return found[np.argsort(cost[found], kind="stable")][:BASINS].tolist()


def _grid_poses(
    T_center: np.ndarray, axes: np.ndarray, directions: np.ndarray, values: list[np.ndarray]
) -> np.ndarray:
    """Every combination of `values` (one array per free axis, then per free direction:
    turns [rad], shifts [m]) applied to T_center (4, 4) -> (M, 4, 4) poses, the last axis
    varying fastest."""
    steps = np.stack([g.ravel() for g in np.meshgrid(*values, indexing="ij")], axis=1)
    poses = np.repeat(T_center[None], len(steps), axis=0)
    for k, axis in enumerate(axes):
        turn = Rotation.from_rotvec(steps[:, k, None] * axis).as_matrix()
        poses[:, :3, :3] = turn @ poses[:, :3, :3]
    for k, direction in enumerate(directions):
        poses[:, :3, 3] += steps[:, len(axes) + k, None] * direction
    return poses


def landing_cost(
    T_world_cam: np.ndarray,
    cloud: np.ndarray,
    grey: np.ndarray | None,
    last: LastFrame,
    camera: CameraConfig,
    stride: int,
) -> float:
    """The sweep's cost (`_shift_costs`) of the frame at T_world_cam (4, 4): its organised
    cloud (H, W, 3, camera frame) and grey levels ((H, W) float or None), every
    `stride`-th pixel, landed on `last`; inf when too few points land. Unlike a median
    colour difference, it counts only residuals beyond the noise, so the few pixels that
    see an edge or a poster decide between two poses that a bare wall fits alike."""
    xyz, values = sampled_points(cloud, stride, grey)
    if len(xyz) < 100:
        return float("inf")
    return float(_shift_costs(T_world_cam, np.zeros((1, 3)), xyz, values, last, camera)[0])


def lands_better(cost: float, rival_cost: float) -> bool:
    """Whether a pose of `landing_cost` `cost` clearly beats one of `rival_cost`: at most
    DISTINCT_RATIO of it and LANDING_MARGIN below it (two poses on bare surfaces both cost
    about 0, and noise would decide)."""
    return cost <= DISTINCT_RATIO * rival_cost and cost < rival_cost - LANDING_MARGIN


def _distinct_best(shifts: np.ndarray, cost: np.ndarray) -> int | None:
    """Index of the lowest of `cost` (M,) over `shifts` (M,) [m] (of equal costs the
    smallest shift), or None: nothing scored, the best not distinct (DISTINCT_RATIO,
    DISTINCT_MIN_COST), or another basin nearly as good (RIVAL_MARGIN)."""
    finite = cost[np.isfinite(cost)]
    if not len(finite):
        return None
    best = int(np.lexsort((np.abs(shifts), cost))[0])
    median = float(np.median(finite))
    if cost[best] > min(DISTINCT_RATIO * median, median - DISTINCT_MIN_COST):
        return None
    padded = np.r_[np.inf, cost, np.inf]
    minima = (cost <= padded[:-2]) & (cost <= padded[2:])
    rivals = minima & (np.abs(shifts - shifts[best]) > RIVAL_DISTANCE_M)
    if np.any(rivals) and np.min(cost[rivals]) - cost[best] < RIVAL_MARGIN * (median - cost[best]):
        return None
    return best


def _shift_costs(
    T_center: np.ndarray,
    moves: np.ndarray,
    xyz: np.ndarray,
    grey: np.ndarray | None,
    last: LastFrame,
    camera: CameraConfig,
) -> np.ndarray:
    """(M,) `_landing_costs` of T_center (4, 4) moved by each of `moves` (M, 3) [m, world
    frame], for the frame's points `xyz` (N, 3, camera frame; grey levels (N,) or None)."""
    T_prev_world = invert_pose(last.T_world_cam)
    T_prev_cam = T_prev_world @ T_center
    p0 = xyz @ T_prev_cam[:3, :3].T + T_prev_cam[:3, 3]  # (N, 3) previous camera
    p = p0[None, :, :] + (moves @ T_prev_world[:3, :3].T)[:, None, :]  # (M, N, 3)
    return _landing_costs(p, grey, last, camera)


def _pose_costs(
    poses: np.ndarray,
    xyz: np.ndarray,
    grey: np.ndarray | None,
    last: LastFrame,
    camera: CameraConfig,
) -> np.ndarray:
    """(M,) `_landing_costs` of the frame at each of `poses` (M, 4, 4) T_world_cam, for its
    points `xyz` (N, 3, camera frame; grey levels (N,) or None)."""
    relative = invert_pose(last.T_world_cam)[None] @ poses  # (M, 4, 4) cam -> previous cam
    p = (relative[:, :3, :3] @ xyz.T).transpose(0, 2, 1) + relative[:, None, :3, 3]
    return _landing_costs(p, grey, last, camera)


def _landing_costs(
    p: np.ndarray, grey: np.ndarray | None, last: LastFrame, camera: CameraConfig
) -> np.ndarray:
    """(M,) cost of M placements `p` (M, N, 3) of the frame's N points in `last`'s camera
    frame (their grey levels (N,) or None): the mean depth residual beyond the noise
    (DEPTH_NOISE_M), clipped, / DEPTH_CLIP_M, plus (with both greys) the mean grey
    residual beyond GREY_NOISE, clipped, / GREY_CLIP; inf where fewer than
    MIN_SCORED_SHARE of the points were scored."""
    u, v, inside = nearest_pixels(camera, p)
    z, z_prev = p[..., 2], last.depth[v, u]
    scored = inside & (z_prev > 0) & np.isfinite(z_prev)
    counts = np.count_nonzero(scored, axis=1)
    depth_excess = np.abs(z_prev - z) - DEPTH_NOISE_M * (1.0 + z)
    residual = np.clip(depth_excess, 0.0, DEPTH_CLIP_M) / DEPTH_CLIP_M
    if grey is not None and last.grey is not None:
        grey_excess = np.abs(last.grey[v, u] - grey[None, :]) - GREY_NOISE
        residual = residual + np.clip(grey_excess, 0.0, GREY_CLIP) / GREY_CLIP
    cost = np.where(scored, residual, 0.0).sum(axis=1) / np.maximum(counts, 1)
    cost[counts < MIN_SCORED_SHARE * p.shape[1]] = np.inf
    return cost
