"""Assertion helpers shared by the tests."""

from __future__ import annotations

import numpy as np


def assert_pose_close(
    T_actual: np.ndarray, T_expected: np.ndarray, trans_tol_m: float, rot_tol_deg: float
) -> None:
    """Compare two (4, 4) poses; on failure print both with the translation and rotation errors."""
    T_err = np.linalg.inv(T_expected) @ T_actual
    trans_err = float(np.linalg.norm(T_err[:3, 3]))
    R = T_err[:3, :3]
    # atan2 of sin and cos: accurate near 0 (arccos alone resolves no better than 1e-6 deg)
    sin = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    rot_err = float(np.degrees(np.arctan2(sin, (np.trace(R) - 1.0) / 2.0)))
    if trans_err > trans_tol_m or rot_err > rot_tol_deg:
        with np.printoptions(precision=5, suppress=True):
            raise AssertionError(
                f"poses differ: translation {trans_err:.5f} m (tol {trans_tol_m}), "
                f"rotation {rot_err:.4f} deg (tol {rot_tol_deg})\n"
                f"actual:\n{T_actual}\nexpected:\n{T_expected}"
            )
