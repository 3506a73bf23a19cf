"""The backend's sliding window (`planeslam.backend.window`): conditioning on held variables."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from planeslam.backend.window import FactorHistory, split_factors
from planeslam.factors import LandmarkKeys, plane_factor

pytestmark = pytest.mark.unit

KEYS = LandmarkKeys()


def pose(rx: float, tx: float) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Rx(rx), np.array([tx, 0.2, -0.1]))


def solve(factors: list, initial: gtsam.Values) -> gtsam.Values:
    graph = gtsam.NonlinearFactorGraph()
    for factor in factors:
        graph.add(factor)
    return gtsam.GaussNewtonOptimizer(graph, initial).optimize()


def test_odometry_from_a_held_pose_pins_the_free_pose_where_the_whole_graph_would():
    """x0 held, x1 free, a prior-free chain x0 -> x1 -> p: the conditioned odometry puts x1
    at x0 * z (the held pose's value is exact there), and the plane's estimate follows."""
    x0, x1, p0 = KEYS.pose(0), KEYS.pose(1), KEYS.plane(0)
    T0, z = pose(0.1, 1.0), pose(0.05, 0.3)
    odometry = gtsam.BetweenFactorPose3(x0, x1, z, gtsam.noiseModel.Isotropic.Sigma(6, 0.01))
    history = FactorHistory(KEYS)
    history.add([odometry])
    history.estimate.insert(x0, T0)
    history.estimate.insert(x1, T0.compose(pose(0.0, 0.25)))  # off by 5 cm and 0.05 rad
    assert history.factors_of([x1]) == [history.graph.at(0)]
    assert history.neighbours([x1]) == {x0, x1}
    whole, conditioned = split_factors(history.factors_of({x1}), {x1})
    assert whole == [] and len(conditioned) == 1
    prior = history.conditioned(conditioned, {x1})
    assert len(prior) == 1 and list(prior[0].keys()) == [x1]
    # a plane seen from x1 only: free with it
    n_cam = np.array([0.0, 0.0, -1.0, 2.0])
    seen = plane_factor(n_cam, np.diag([1e-4, 1e-4, 1e-4]), x1, p0)
    initial = history.values_of([x1])
    initial.insert(p0, gtsam.OrientedPlane3(n_cam).transform(T0.compose(z).inverse()))
    result = solve(prior + [seen], initial)
    np.testing.assert_allclose(result.atPose3(x1).matrix(), T0.compose(z).matrix(), atol=1e-6)


def test_conditioning_sums_every_factor_of_a_free_variable_and_splits_by_membership():
    """A plane seen from three held poses: one conditioned factor with the information of
    all three (its solution the plane that fits them with the poses held); a factor on two
    free variables stays whole; a factor on a variable already inside is left out."""
    plane = gtsam.OrientedPlane3(0.0, 0.0, 1.0, 1.5)
    p0, p1 = KEYS.plane(0), KEYS.plane(1)
    history = FactorHistory(KEYS)
    observations = []
    for i in range(3):
        T = pose(0.1 * i, 0.2 * i)
        history.estimate.insert(KEYS.pose(i), T)
        offset = np.r_[0.0, 0.0, 0.0, 0.01 * (i - 1)]  # planes at 1.49, 1.5, 1.51 m
        z = plane.transform(T).planeCoefficients() + offset
        observations.append(plane_factor(z, np.diag([1e-4] * 3), KEYS.pose(i), p0))
    history.add(observations)
    # near the solution: the conditioned factor is linear about this estimate
    history.estimate.insert(p0, gtsam.OrientedPlane3(0.0, 0.002, 1.0, 1.49))
    history.estimate.insert(p1, gtsam.OrientedPlane3(1.0, 0.0, 0.0, 0.5))
    tie = gtsam.BetweenFactorPose3(
        KEYS.pose(0), KEYS.pose(1), pose(0, 0), gtsam.noiseModel.Unit.Create(6)
    )
    whole, conditioned = split_factors(observations, {p0})
    assert whole == [] and len(conditioned) == 3
    assert split_factors([tie], {KEYS.pose(0), KEYS.pose(1)}) == ([tie], [])
    assert split_factors(observations, {p0}, inside={KEYS.pose(2)})[1] == observations[:2]
    prior = history.conditioned(conditioned, {p0})
    assert len(prior) == 1
    result = solve(prior, history.values_of([p0])).atOrientedPlane3(p0)
    # the same with the poses pinned by tight priors, solved as a nonlinear problem
    pinned = [
        gtsam.PriorFactorPose3(
            KEYS.pose(i),
            history.estimate.atPose3(KEYS.pose(i)),
            gtsam.noiseModel.Isotropic.Sigma(6, 1e-9),
        )
        for i in range(3)
    ]
    initial = history.values_of([KEYS.pose(0), KEYS.pose(1), KEYS.pose(2), p0])
    exact = solve(pinned + observations, initial).atOrientedPlane3(p0)
    np.testing.assert_allclose(result.normal().point3(), exact.normal().point3(), atol=1e-5)
    assert abs(result.distance() - exact.distance()) < 1e-4
    assert abs(exact.distance() - 1.5) < 0.005
    with pytest.raises(ValueError, match="2 free variables"):
        history.conditioned(observations[:1], {p0, KEYS.pose(0)})
