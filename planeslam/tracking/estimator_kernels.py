"""The robust Gauss-Newton of `estimator.estimate_pose` compiled (numba): a few hundred
small numpy calls per estimate in Python, one call here. The math, frames and term
layout are the estimator module's docstring's; the whiteners are computed by the caller.

Systems, in the order their normal equations are summed: 0 the planes, 1..S the point
sets (`point_set` (M,) says which), S + 1 the line ends.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _add_term(
    H: np.ndarray, g: np.ndarray, e: np.ndarray, J: np.ndarray, W: np.ndarray, k: float, cut: float
) -> bool:
    """Whiten one term's residual e (r,) and Jacobian J (r, 6) by W (r, r), add it to the
    normal equations H (6, 6), g (6,) with its Huber weight (0 beyond `cut` sigmas);
    whether its whitened norm is within k."""
    r = e.shape[0]
    ew = np.zeros(r)
    Jw = np.zeros((r, 6))
    for i in range(r):
        for j in range(r):
            ew[i] += W[i, j] * e[j]
            for a in range(6):
                Jw[i, a] += W[i, j] * J[j, a]
    norm = np.sqrt(np.sum(ew * ew))
    weight = 1.0 if norm <= k else k / max(norm, 1e-12)
    root = np.sqrt(weight if norm <= cut else 0.0)
    for i in range(r):
        for a in range(6):
            Jw[i, a] *= root
        ew[i] *= root
    for a in range(6):
        for b in range(6):
            s = 0.0
            for i in range(r):
                s += Jw[i, a] * Jw[i, b]
            H[a, b] += s
        s = 0.0
        for i in range(r):
            s += Jw[i, a] * ew[i]
        g[a] += s
    return norm <= k


@njit(cache=True, nogil=True)
def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for (3,) vectors."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


@njit(cache=True, nogil=True)
def _rotate_back(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R^T v for R (3, 3), v (3,)."""
    out = np.zeros(3)
    for j in range(3):
        out[j] = R[0, j] * v[0] + R[1, j] * v[1] + R[2, j] * v[2]
    return out


@njit(cache=True, nogil=True)
def _rotate(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R v for R (3, 3), v (3,)."""
    out = np.zeros(3)
    for i in range(3):
        out[i] = R[i, 0] * v[0] + R[i, 1] * v[1] + R[i, 2] * v[2]
    return out


@njit(cache=True, nogil=True)
def plane_term(
    R: np.ndarray,
    t: np.ndarray,
    n_cam: np.ndarray,
    d_cam: float,
    n_world: np.ndarray,
    d_world: float,
    basis: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Residual (3,) and Jacobian (3, 6) of one plane term at T = (R, t), unwhitened: the
    map plane moved into the camera, m = R^T n_w, against the observation n_c, d_c in the
    (2, 3) tangent basis rows of n_c."""
    m = _rotate_back(R, n_world)
    diff = m - n_cam
    e = np.zeros(3)
    J = np.zeros((3, 6))
    for j in range(2):
        e[j] = basis[j, 0] * diff[0] + basis[j, 1] * diff[1] + basis[j, 2] * diff[2]
        J[j, :3] = _cross(basis[j], m)  # b . (m x w) = (b x m) . w
    e[2] = d_world + (n_world[0] * t[0] + n_world[1] * t[1] + n_world[2] * t[2]) - d_cam
    J[2, 3:] = m
    return e, J


@njit(cache=True, nogil=True)
def point_term(
    R: np.ndarray, t: np.ndarray, p_cam: np.ndarray, p_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residual (3,) and Jacobian (3, 6) of one point term at T = (R, t), unwhitened:
    q = R^T (p_w - t) against p_c."""
    q = _rotate_back(R, p_world - t)
    J = np.zeros((3, 6))
    J[0, 1], J[0, 2] = -q[2], q[1]
    J[1, 0], J[1, 2] = q[2], -q[0]
    J[2, 0], J[2, 1] = -q[1], q[0]
    for j in range(3):
        J[j, 3 + j] = -1.0
    return q - p_cam, J


@njit(cache=True, nogil=True)
def line_term(
    R: np.ndarray, t: np.ndarray, p_cam: np.ndarray, u_world: np.ndarray, e_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residual (1,) and Jacobian (1, 6) of one line-end term at T = (R, t), unwhitened:
    u_w . (R p_c + t - e_w)."""
    d = _rotate(R, p_cam) + t - e_world
    e = np.zeros(1)
    e[0] = u_world[0] * d[0] + u_world[1] * d[1] + u_world[2] * d[2]
    uR = _rotate_back(R, u_world)
    J = np.zeros((1, 6))
    J[0, :3] = _cross(p_cam, uR)  # -u^T R [p]x, as a row
    J[0, 3:] = uR
    return e, J


@njit(cache=True, nogil=True)
def _normal_equations(
    T: np.ndarray,
    planes: tuple,
    points: tuple,
    lines: tuple,
    line_sigma: float,
    info: np.ndarray,
    inliers: np.ndarray,
    k: float,
    cut: float,
) -> None:
    """Each system's weighted normal equations at T (4, 4) into info (S + 2, 6, 7): H in
    [:, :, :6], g in [:, :, 6]; each term's inlier flag (within k) into `inliers`, planes,
    then points, then lines (`gauss_newton_kernel`'s arguments)."""
    plane_n_cam, plane_d_cam, plane_n_world, plane_d_world, plane_bases, plane_W = planes
    point_p_cam, point_p_world, point_W, point_set = points
    line_p_cam, line_u_world, line_e_world = lines
    R = np.ascontiguousarray(T[:3, :3])
    t = np.ascontiguousarray(T[:3, 3])
    info[:] = 0.0
    row = 0
    for i in range(plane_d_cam.shape[0]):
        e, J = plane_term(
            R, t, plane_n_cam[i], plane_d_cam[i], plane_n_world[i], plane_d_world[i],
            plane_bases[i],
        )  # fmt: skip
        inliers[row] = _add_term(info[0, :, :6], info[0, :, 6], e, J, plane_W[i], k, cut)
        row += 1
    for i in range(point_p_cam.shape[0]):
        e, J = point_term(R, t, point_p_cam[i], point_p_world[i])
        system = 1 + point_set[i]
        inliers[row] = _add_term(info[system, :, :6], info[system, :, 6], e, J, point_W[i], k, cut)
        row += 1
    last = info.shape[0] - 1  # the line ends' system
    W1 = np.full((1, 1), 1.0 / line_sigma)
    for i in range(line_p_cam.shape[0]):
        e, J = line_term(R, t, line_p_cam[i], line_u_world[i], line_e_world[i])
        inliers[row] = _add_term(info[last, :, :6], info[last, :, 6], e, J, W1, k, cut)
        row += 1


@njit(cache=True, nogil=True)
def retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """T exp(xi) on the right: R <- R exp([w]x), t <- t + R v (Rodrigues)."""
    w, v = xi[:3], xi[3:]
    angle = np.sqrt(np.sum(w * w))
    dR = np.eye(3)
    if angle > 1e-12:
        a = w / angle
        K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
        KK = np.zeros((3, 3))
        for i in range(3):
            for j in range(3):
                KK[i, j] = K[i, 0] * K[0, j] + K[i, 1] * K[1, j] + K[i, 2] * K[2, j]
        dR = dR + np.sin(angle) * K + (1.0 - np.cos(angle)) * KK
    out = T.copy()
    for i in range(3):
        for j in range(3):
            out[i, j] = T[i, 0] * dR[0, j] + T[i, 1] * dR[1, j] + T[i, 2] * dR[2, j]
        out[i, 3] = T[i, 3] + (T[i, 0] * v[0] + T[i, 1] * v[1] + T[i, 2] * v[2])
    return out


@njit(cache=True, nogil=True)
def gauss_newton_kernel(
    T_init: np.ndarray,
    planes: tuple,
    points: tuple,
    point_sets: int,
    lines: tuple,
    line_sigma: float,
    huber_k: float,
    reject_k: float,
    settle_iterations: int,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """T_world_cam (4, 4) from T_init, each system's information (S + 2, 6, 6) at it
    (robust weights with `reject_k`) and each term's inlier flag (within `huber_k`).
    planes: (N, 3) n_cam, (N,) d_cam, (N, 3) n_world, (N,) d_world, (N, 2, 3) tangent
    bases, (N, 3, 3) whiteners; points: (M, 3) p_cam, (M, 3) p_world, (M, 3, 3)
    whiteners, (M,) set of each in 0..point_sets - 1; lines: (L, 3) p_cam, u_world,
    e_world, with noise `line_sigma` [m]."""
    info = np.zeros((point_sets + 2, 6, 7))
    inliers = np.zeros(planes[1].shape[0] + points[0].shape[0] + lines[0].shape[0], np.bool_)
    T = T_init.copy()
    it = 0
    while True:
        it += 1
        last = it > iterations  # the pass at the solution: its information and inliers
        cut = np.inf if it <= settle_iterations and not last else reject_k
        _normal_equations(T, planes, points, lines, line_sigma, info, inliers, huber_k, cut)
        if last:
            return T, np.ascontiguousarray(info[:, :, :6]), inliers
        H = np.zeros((6, 6))
        g = np.zeros(6)
        for s in range(info.shape[0]):
            H += info[s, :, :6]
            g += info[s, :, 6]
        scale = max(np.trace(H), 1e-12)
        xi = -np.linalg.solve(H + 1e-9 * scale * np.eye(6), g)
        T = retract(T, xi)
        small = np.sqrt(np.sum(xi[:3] ** 2)) < 1e-7 and np.sqrt(np.sum(xi[3:] ** 2)) < 1e-7
        if small and it > settle_iterations:
            it = iterations  # converged: the next pass is the last
