"""One robust pose estimator over every primitive: planes, points (keypoints, corners) and
line ends, each weighted by its covariance.

Unknown: T_world_cam, perturbed on the right, R <- R exp([w]x), t <- t + R v, with
xi = (w, v) (6,) in the camera frame. Residuals, all in the camera frame except lines:

- plane (observed n_c, d_c with its fit covariance; map n_w, d_w): the map plane moved
  into the camera, m = R^T n_w, d = d_w + n_w . t, against the observation:
  e = (B^T (m - n_c), d - d_c) with B = `tangent_basis(n_c)`, the coordinates of the fit
  covariance (gtsam OrientedPlane3 local coordinates); de/dw = (B^T [m]x, 0),
  de/dv = (0, m^T). Covariance: the fit's plus a floor (`plane_sigma_*`), which stands for
  what a fit from thousands of points does not see (depth bias, segmentation borders).
- point (observed p_c with covariance C_c; matched world point p_w with C_w): q = R^T (p_w - t)
  against p_c; dq/dw = [q]x, dq/dv = -I; covariance C_c + R^T C_w R.
- line end (an observed edge end p_c that is a real end, not cut by the image border;
  the matched map edge's direction u_w and end e_w): along-line offset
  u_w . (R p_c + t - e_w). Across the line the edge's two planes already constrain it.

Gauss-Newton with Huber weights on each term's whitened norm (iteratively reweighted).
The result keeps each kind's information matrix, so `constraints` can say which degrees
of freedom the planes fixed and which other kind filled the rest.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from planeslam.core.geometry import tangent_basis
from planeslam.tracking.estimator_kernels import gauss_newton_kernel


class Primitive(str, enum.Enum):
    """A kind of measurement that constrains a pose."""

    PLANES = "planes"
    POINTS = "points"
    """Keypoints with depth."""
    CORNERS = "corners"
    """Trihedral corner points."""
    LINES = "lines"
    """Ends of real plane intersections."""
    ODOMETRY = "odometry"
    """RGB-D odometry against the previous frame."""
    ICP = "icp"
    """Point-to-plane ICP against the previous frame."""
    MOTION = "motion"
    """The constant-velocity prediction."""

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class PlaneTerms:
    """Plane correspondences: observed (camera frame) against map (world frame)."""

    n_cam: np.ndarray
    """(N, 3) observed unit normals."""
    d_cam: np.ndarray
    """(N,) observed offsets [m]."""
    n_world: np.ndarray
    """(N, 3) map unit normals."""
    d_world: np.ndarray
    """(N,) map offsets [m]."""
    covariance: np.ndarray
    """(N, 3, 3) observed fit covariance in OrientedPlane3 local coordinates of n_cam
    (rad^2, rad m, m^2)."""

    def __len__(self) -> int:
        return len(self.d_cam)


@dataclass(frozen=True)
class PointTerms:
    """Point correspondences: observed (camera frame) against map (world frame)."""

    p_cam: np.ndarray
    """(M, 3) observed points [m]."""
    p_world: np.ndarray
    """(M, 3) map points [m]."""
    cov_cam: np.ndarray
    """(M, 3, 3) observed covariances [m^2], camera frame."""
    cov_world: np.ndarray
    """(M, 3, 3) map covariances [m^2], world frame."""
    kind: Primitive = Primitive.POINTS

    def __len__(self) -> int:
        return len(self.p_cam)


def corner_terms(p_cam: np.ndarray, p_world: np.ndarray, sigma_m: float) -> PointTerms:
    """Point terms of matched corners: (M, 3) observed points (camera frame) against (M, 3)
    corner landmarks (world frame) [m], the isotropic `sigma_m` split between the two."""
    cov = np.broadcast_to(sigma_m**2 / 2 * np.eye(3), (len(p_cam), 3, 3))
    return PointTerms(
        np.reshape(p_cam, (-1, 3)), np.reshape(p_world, (-1, 3)), cov, cov, Primitive.CORNERS
    )


@dataclass(frozen=True)
class LineTerms:
    """Observed edge ends (camera frame) against map edge ends along the edge (world)."""

    p_cam: np.ndarray
    """(L, 3) observed ends [m]."""
    u_world: np.ndarray
    """(L, 3) unit directions of the matched map edges."""
    e_world: np.ndarray
    """(L, 3) the matched map ends [m]."""

    def __len__(self) -> int:
        return len(self.p_cam)


@dataclass(frozen=True)
class EstimatorSettings:
    """Noise floors and the robust kernel of `estimate_pose`."""

    plane_sigma_angle_rad: float = np.radians(1.0)
    """Normal noise added to each plane's fit covariance [rad]."""
    plane_sigma_offset_m: float = 0.01
    """Offset noise added to each plane's fit covariance [m]."""
    line_sigma_m: float = 0.03
    """Noise of an edge end along its edge [m]."""
    huber_k: float = 2.0
    """Huber threshold on a term's whitened norm (sigmas)."""
    reject_k: float = 6.0
    """After `settle_iterations`, terms beyond this many sigmas get no weight (gross
    outliers: Huber alone still lets each pull linearly)."""
    settle_iterations: int = 3
    """Iterations with Huber weights alone, before gross outliers are rejected."""
    iterations: int = 10
    """Gauss-Newton iterations at most."""


@dataclass(frozen=True)
class PoseConstraints:
    """Which degrees of freedom of a pose the planes fixed, and what fixed the rest."""

    plane_rotation_dof: int
    """Rotation axes (0-3) the matched planes constrain: 2 for one normal, 3 for two or
    more non-parallel ones."""
    plane_translation_dof: int
    """Translation directions (0-3) the matched planes constrain: the rank of their normals."""
    filled_by: tuple[Primitive, ...] = ()
    """Other primitives that constrain the directions the planes left free."""
    free: tuple[str, ...] = ()
    """Directions nothing constrained ('rotation', 'translation'), taken from a prior."""
    terms: dict[str, int] = field(default_factory=dict)
    """Correspondences used per primitive (inliers of the robust estimate)."""

    @property
    def planes_full(self) -> bool:
        return self.plane_rotation_dof == 3 and self.plane_translation_dof == 3

    def to_record(self) -> dict[str, object]:
        """The frames.jsonl entry."""
        return {
            "planes": {
                "rotation": self.plane_rotation_dof,
                "translation": self.plane_translation_dof,
            },
            "filled_by": [str(p) for p in self.filled_by],
            "free": list(self.free),
            "terms": dict(self.terms),
        }


@dataclass(frozen=True)
class PoseEstimate:
    """Result of `estimate_pose`."""

    T_world_cam: np.ndarray
    """(4, 4)"""
    information: dict[Primitive, np.ndarray] = field(repr=False)
    """Per primitive, the (6, 6) information (robust weights applied) at the solution,
    in xi = (w, v) camera-frame coordinates."""
    plane_inliers: np.ndarray = field(repr=False)
    """(N,) bool: plane terms within the Huber threshold at the solution."""
    point_inliers: list[np.ndarray] = field(repr=False)
    """Per PointTerms, (M,) bool."""
    line_inliers: np.ndarray = field(repr=False)
    """(L,) bool."""

    @property
    def total_information(self) -> np.ndarray:
        return sum(self.information.values(), np.zeros((6, 6)))


# ----------------------------------------------------------------------------- terms


def _plane_bases(terms: PlaneTerms) -> np.ndarray:
    """(N, 2, 3) rows: the tangent basis of each observed normal (the covariance's)."""
    return np.array([tangent_basis(n).T for n in terms.n_cam]).reshape(-1, 2, 3)


def _point_whiteners(T, terms: PointTerms) -> np.ndarray:
    """(M, 3, 3) whiteners of point terms: observed plus map covariance, the latter turned
    into the camera frame by T's rotation (fixed for one estimate: it barely changes)."""
    R = T[:3, :3]
    return _whitener(terms.cov_cam + np.einsum("ji,njk,kl->nil", R, terms.cov_world, R))


def _whitener(cov: np.ndarray) -> np.ndarray:
    """(..., 3, 3) W with W^T W = cov^-1 (upper Cholesky factor of the information)."""
    info = np.linalg.inv(cov)
    L = np.linalg.cholesky(0.5 * (info + np.swapaxes(info, -1, -2)))
    return np.swapaxes(L, -1, -2)


# ----------------------------------------------------------------------------- solve


def estimate_pose(
    T_init: np.ndarray,
    planes: PlaneTerms | None,
    points: list[PointTerms],
    lines: LineTerms | None,
    settings: EstimatorSettings,
) -> PoseEstimate:
    """Robust Gauss-Newton estimate of T_world_cam (4, 4) from T_init (4, 4) over every
    term; a direction no term constrains keeps T_init's value (damped normal equations).
    The iterations run compiled (`estimator_kernels.gauss_newton_kernel`)."""
    T = np.array(T_init, dtype=np.float64)
    planes = planes if planes is not None else _NO_PLANES
    floor = np.diag([settings.plane_sigma_angle_rad**2] * 2 + [settings.plane_sigma_offset_m**2])
    bases, W = _plane_bases(planes), _whitener(planes.covariance.reshape(-1, 3, 3) + floor)
    sets = [terms for terms in points if len(terms)]
    sizes = [len(terms) for terms in sets]
    p_cam, p_world, W_p = (
        np.concatenate([_as_rows(terms.p_cam) for terms in sets] + [np.zeros((0, 3))]),
        np.concatenate([_as_rows(terms.p_world) for terms in sets] + [np.zeros((0, 3))]),
        np.concatenate([_point_whiteners(T, terms) for terms in sets] + [np.zeros((0, 3, 3))]),
    )
    lines = lines if lines is not None else _NO_LINES
    T, information, inliers = gauss_newton_kernel(
        T,
        (
            _as_rows(planes.n_cam),
            _as_values(planes.d_cam),
            _as_rows(planes.n_world),
            _as_values(planes.d_world),
            bases,
            np.ascontiguousarray(W),
        ),
        (p_cam, p_world, np.ascontiguousarray(W_p), np.repeat(np.arange(len(sets)), sizes)),
        len(sets),
        (_as_rows(lines.p_cam), _as_rows(lines.u_world), _as_rows(lines.e_world)),
        float(settings.line_sigma_m),
        float(settings.huber_k),
        float(settings.reject_k),
        int(settings.settle_iterations),
        int(settings.iterations),
    )
    # Systems in the kernel's order: planes, the point sets, lines; kinds summed.
    info: dict[Primitive, np.ndarray] = {}
    systems = [(Primitive.PLANES, len(planes))] + [(t.kind, len(t)) for t in sets]
    for s, (kind, count) in enumerate([*systems, (Primitive.LINES, len(lines))]):
        if count:
            info[kind] = info.get(kind, np.zeros((6, 6))) + information[s]
    n_planes, n_points = len(planes), len(p_cam)
    per_set = iter(
        np.split(inliers[n_planes : n_planes + n_points], np.cumsum(sizes, dtype=np.int64)[:-1])
    )
    return PoseEstimate(
        T_world_cam=T,
        information=info,
        plane_inliers=inliers[:n_planes],
        point_inliers=[next(per_set) if len(t) else np.zeros(0, bool) for t in points],
        line_inliers=inliers[n_planes + n_points :],
    )


def warm_up() -> None:
    """Compile (or load from numba's cache) `estimate_pose`'s kernel, for the argument
    types it always passes, on an empty problem: at start-up, where an interrupt waits
    (`app.runner`), rather than inside the first estimate (about 15 s the first time on a
    machine, then well under a second)."""
    estimate_pose(np.eye(4), None, [], None, EstimatorSettings())


def _as_rows(a: np.ndarray) -> np.ndarray:
    """(K, 3) contiguous float64 rows of `a` (the kernel is compiled for these types)."""
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 3))


def _as_values(a: np.ndarray) -> np.ndarray:
    """(K,) contiguous float64 values of `a`."""
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1))


_NO_PLANES = PlaneTerms(
    np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3, 3))
)
_NO_LINES = LineTerms(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)))


# ----------------------------------------------------------------------------- constraints


@dataclass(frozen=True)
class ConstraintThresholds:
    """When a direction counts as constrained."""

    plane_rank_ratio: float = 0.02
    """A plane-constrained direction has at least this fraction of the largest plane
    information eigenvalue (of its block: rotation or translation): for translation, two
    normals less than about 16 deg apart count as one (tan^2 of half the angle)."""
    max_sigma_rad: float = np.radians(2.0)
    """A direction is constrained by a primitive when its information alone gives at most
    this rotation sigma [rad] ..."""
    max_sigma_m: float = 0.03
    """... or this translation sigma [m]."""


def _block_rank(H: np.ndarray, ratio: float) -> tuple[int, np.ndarray]:
    """(rank, (3, 3-rank) free directions) of a 3x3 information block: eigenvalues above
    `ratio` of the largest (none when the block is zero)."""
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    good = (lam >= ratio * lam[-1]) & (lam > 0.0)
    return int(np.count_nonzero(good)), V[:, ~good]


def constraints(
    estimate: PoseEstimate, thresholds: ConstraintThresholds, terms: dict[str, int]
) -> PoseConstraints:
    """Which directions the planes constrain, which other primitives constrain the rest
    (each on its own information), and what nothing constrains."""
    info = estimate.information
    H_planes = info.get(Primitive.PLANES, np.zeros((6, 6)))
    # A sigma at the threshold is within it: 1e-9 relative slack for rounding (one line
    # end at `line_sigma_m` gives exactly the translation floor).
    rot_floor = (1.0 - 1e-9) / thresholds.max_sigma_rad**2
    trans_floor = (1.0 - 1e-9) / thresholds.max_sigma_m**2
    r_rank, r_free = _block_rank(H_planes[:3, :3], thresholds.plane_rank_ratio)
    t_rank, t_free = _block_rank(H_planes[3:, 3:], thresholds.plane_rank_ratio)
    filled: list[Primitive] = []
    total = estimate.total_information
    free: list[str] = []
    for block, U, floor_value, name in (
        (slice(0, 3), r_free, rot_floor, "rotation"),
        (slice(3, 6), t_free, trans_floor, "translation"),
    ):
        if not U.shape[1]:
            continue
        for kind, Hk in info.items():
            if kind is Primitive.PLANES:
                continue
            along = np.linalg.eigvalsh(U.T @ Hk[block, block] @ U)
            if along.min() >= floor_value and kind not in filled:
                filled.append(kind)
        if np.linalg.eigvalsh(U.T @ total[block, block] @ U).min() < floor_value:
            free.append(name)
    return PoseConstraints(
        plane_rotation_dof=r_rank,
        plane_translation_dof=t_rank,
        filled_by=tuple(filled),
        free=tuple(free),
        terms=terms,
    )


def fully_constrained(estimate: PoseEstimate, thresholds: ConstraintThresholds) -> bool:
    """Whether all six directions are constrained by all terms together: the marginal
    rotation and translation sigmas of the estimate within the thresholds."""
    H = estimate.total_information
    scale = max(float(np.trace(H)), 1e-12)
    C = np.linalg.inv(H + 1e-12 * scale * np.eye(6))
    return bool(
        np.linalg.eigvalsh(C[:3, :3])[-1] <= thresholds.max_sigma_rad**2
        and np.linalg.eigvalsh(C[3:, 3:])[-1] <= thresholds.max_sigma_m**2
    )
