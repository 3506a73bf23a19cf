"""Assertion helpers shared by the tests."""

from __future__ import annotations

import numpy as np

from planeslam.tracking.hypotheses import pose_difference


def assert_pose_close(
    T_actual: np.ndarray, T_expected: np.ndarray, trans_tol_m: float, rot_tol_deg: float
) -> None:
    """Compare two (4, 4) poses; on failure print both with the translation and rotation errors."""
    trans_err, rot_err = pose_difference(T_expected, T_actual)
    if trans_err > trans_tol_m or rot_err > rot_tol_deg:
        with np.printoptions(precision=5, suppress=True):
            raise AssertionError(
                f"poses differ: translation {trans_err:.5f} m (tol {trans_tol_m}), "
                f"rotation {rot_err:.4f} deg (tol {rot_tol_deg})\n"
                f"actual:\n{T_actual}\nexpected:\n{T_expected}"
            )
