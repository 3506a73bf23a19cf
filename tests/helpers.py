"""Assertion helpers shared by the tests."""

from __future__ import annotations

import numpy as np


def assert_pose_close(
    T_actual: np.ndarray, T_expected: np.ndarray, trans_tol_m: float, rot_tol_deg: float
) -> None:
    """Compare two (4, 4) poses; on failure print both with the translation and rotation errors."""
    T_err = np.linalg.inv(T_expected) @ T_actual
    trans_err = float(np.linalg.norm(T_err[:3, 3]))
    cos = np.clip((np.trace(T_err[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    rot_err = float(np.degrees(np.arccos(cos)))
    if trans_err > trans_tol_m or rot_err > rot_tol_deg:
        with np.printoptions(precision=5, suppress=True):
            raise AssertionError(
                f"poses differ: translation {trans_err:.5f} m (tol {trans_tol_m}), "
                f"rotation {rot_err:.4f} deg (tol {rot_tol_deg})\n"
                f"actual:\n{T_actual}\nexpected:\n{T_expected}"
            )
