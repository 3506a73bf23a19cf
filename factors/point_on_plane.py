"""Point on plane: a corner landmark lies on one of its plane landmarks (world frame).

Error (1,) [m], the signed distance of the point to the plane:

    e = n . p + d

Keys: (plane: OrientedPlane3, point: Point3). Jacobians: w.r.t. the plane's 3-D
local coordinates [p^T dn/dxi_n, 1] (via `OrientedPlane3.normal` / `distance`)
and w.r.t. the point, n^T. A trihedral corner gets one factor per plane.
"""

from __future__ import annotations

import gtsam
import numpy as np

from ._noise import distinct_keys, isotropic_noise


def point_on_plane_factor(plane_key: int, point_key: int, sigma: float) -> gtsam.CustomFactor:
    """Point `point_key` lies on plane `plane_key`; sigma [m] on the point-plane distance."""
    plane_key, point_key = distinct_keys(plane_key, point_key)

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        plane = values.atOrientedPlane3(plane_key)
        p_world = values.atPoint3(point_key)
        if H is None:
            return np.array([plane.normal().point3() @ p_world + plane.distance()])
        n_H_plane = np.zeros((2, 3), order="F")
        d_H_plane = np.zeros((1, 3), order="F")
        nvec_H_n = np.zeros((3, 2), order="F")
        n_world = plane.normal(n_H_plane).point3(nvec_H_n)
        e = n_world @ p_world + plane.distance(d_H_plane)
        H[0] = (p_world @ nvec_H_n @ n_H_plane)[None, :] + d_H_plane
        H[1] = n_world[None, :]
        return np.array([e])

    return gtsam.CustomFactor(isotropic_noise(sigma, 1), [plane_key, point_key], error)
