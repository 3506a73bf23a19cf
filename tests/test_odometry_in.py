"""Odometry in, covariances out: the caller's odometry (`SLAM.process(odometry=...)`) as
a between factor of the iSAM2 graph and the tracker's prediction; every frame's pose
covariance; the covariance algebra it rests on (checked against gtsam and by sampling)."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from conftest import shared_sequence

from planeslam import SLAM, TumDataset, load_config
from planeslam.core.errors import GeometryError
from planeslam.core.geometry import compose_covariance, invert_pose, pose_adjoint
from planeslam.core.types import RelativePose

pytestmark = pytest.mark.unit


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return gtsam.Pose3.Expmap(rng.normal(0.0, [0.5] * 3 + [1.0] * 3)).matrix()


def random_covariance(rng: np.random.Generator, scale: float) -> np.ndarray:
    A = rng.normal(0.0, scale, (6, 6))
    return A @ A.T + scale**2 * np.eye(6)


def test_pose_adjoint_is_gtsams():
    rng = np.random.default_rng(0)
    for _ in range(5):
        T = random_pose(rng)
        np.testing.assert_allclose(pose_adjoint(T), gtsam.Pose3(T).AdjointMap(), atol=1e-12)


def test_composed_covariance_matches_sampled_compositions():
    """T_a_c = T_a_b Exp(xi_ab) T_b_c Exp(xi_bc), sampled: the spread of Log(T_a_c^-1 ...)
    is the composed covariance (within sampling error)."""
    rng = np.random.default_rng(1)
    T_a_b, T_b_c = random_pose(rng), random_pose(rng)
    cov_a_b, cov_b_c = random_covariance(rng, 0.01), random_covariance(rng, 0.005)
    T_a_c_inv = invert_pose(T_a_b @ T_b_c)
    xi_ab = rng.multivariate_normal(np.zeros(6), cov_a_b, 4000)
    xi_bc = rng.multivariate_normal(np.zeros(6), cov_b_c, 4000)
    samples = np.array(
        [
            gtsam.Pose3.Logmap(
                gtsam.Pose3(
                    T_a_c_inv
                    @ T_a_b
                    @ gtsam.Pose3.Expmap(a).matrix()
                    @ T_b_c
                    @ gtsam.Pose3.Expmap(b).matrix()
                )
            )
            for a, b in zip(xi_ab, xi_bc, strict=True)
        ]
    )
    expected = compose_covariance(cov_a_b, T_b_c, cov_b_c)
    sampled = np.cov(samples.T)
    sigmas = np.sqrt(np.diag(expected))
    scale = np.outer(sigmas, sigmas)  # compared as correlations, sigmas on the diagonal
    np.testing.assert_allclose(sampled / scale, expected / scale, atol=0.08)
    chained = RelativePose(T_a_b, cov_a_b).then(RelativePose(T_b_c, cov_b_c))
    np.testing.assert_allclose(chained.covariance, expected)
    np.testing.assert_allclose(chained.T_a_b, T_a_b @ T_b_c)


@pytest.mark.parametrize(
    ("odometry", "message"),
    [
        (np.eye(4), r"odometry is a ndarray, expected \(T_prev_cur"),
        ((np.eye(4), np.eye(5)), r"information of shape \(5, 5\)"),
        ((np.eye(4), -np.eye(6)), "symmetric positive definite"),
        ((np.diag([1.0, 1.0, 1.01, 1.0]), np.eye(6)), "rotation block is .* from orthonormal"),
    ],
)
def test_bad_odometry_is_a_named_error(odometry, message):
    with pytest.raises(GeometryError, match=message):
        RelativePose.from_odometry(odometry)


def tum_frames(clip: str):
    config = load_config("tum_fr1")
    config = dataclasses.replace(config, backend=dataclasses.replace(config.backend, lag_frames=0))
    sequence = TumDataset(shared_sequence(clip), config.camera, config.dataset)
    T_true = np.array([sequence.groundtruth_pose(t) for t in sequence.timestamps])
    return config, sequence, T_true


@pytest.mark.data
def test_the_callers_odometry_is_a_between_factor_and_every_frame_has_a_covariance():
    """On TUM fr1/xyz: odometry biased by 1 cm per frame along x with a very confident
    information pulls the optimised keyframes onto its chain, so it is in the graph;
    without it they stay near the truth. Every frame's pose covariance is symmetric
    positive definite; a keyframe's is its backend marginal."""
    config, sequence, T_true = tum_frames("tum_fr1_xyz_10f")
    bias = np.eye(4)
    bias[0, 3] = 0.01
    steps = [invert_pose(a) @ b @ bias for a, b in zip(T_true[:-1], T_true[1:], strict=True)]
    information = np.diag([1e10] * 6)
    chain = [T_true[0]]
    for step in steps:
        chain.append(chain[-1] @ step)
    poses = {}
    for with_odometry in (False, True):
        with SLAM(config, T_world_first=T_true[0]) as slam:
            results = []
            for i in range(len(sequence)):
                frame = sequence[i]
                odometry = (steps[i - 1], information) if with_odometry and i else None
                results.append(slam.process(frame.depth_m, frame.timestamp, frame.rgb, odometry))
            slam.finish()
        poses[with_odometry] = slam.backend_result.keyframe_poses
        for result in results:
            assert not result.lost
            cov = result.pose_covariance
            assert cov is not None and cov.shape == (6, 6), result.index
            np.testing.assert_allclose(cov, cov.T, atol=1e-15)
            assert np.linalg.eigvalsh(cov).min() > 0
        keyframes = [r for r in results if r.keyframe]
        assert len(keyframes) >= 2
    for k, T in poses[True].items():
        assert np.linalg.norm(T[:3, 3] - chain[k][:3, 3]) < 2e-3, k
    far = max(np.linalg.norm(T[:3, 3] - chain[k][:3, 3]) for k, T in poses[False].items())
    assert far > 0.02, "without it the keyframes should stay off the biased chain"
