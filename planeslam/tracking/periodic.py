"""A repetitive texture's period, and the poses a period away that keypoints cannot tell
apart.

On a wall papered with one motif, keypoint matches agree with every pose shifted by a
whole number of periods along the wall; where the planes leave that direction free, the
points' best pose may be a period off, and the constant-velocity prediction then carries
the error on (a robot in the paper's square room drifted 1, 2, 3, 4, 5 periods in five
frames). `texture_period` finds the period from the frame itself: keypoints with a
near-identical twin in the same image, whose 3-D offsets agree. `period_shifts` are the
best pose moved by one and two periods each way, where the tracker matches again by
projection and solves; the existing rule for rivals (`joint.JointEstimator`) then takes
the one nearest the prediction when the evidence does not tell them apart.

Frames: keypoints in the camera frame, poses T_world_cam (4, 4), periods in the world
frame [m].
"""

from __future__ import annotations

import numpy as np

from planeslam.tracking.keypoints import Keypoints

TWIN_MAX_BITS = 40
"""Two keypoints of one image within this Hamming distance [bits] are copies of one motif
(ORB-SLAM's strict match threshold is 50)."""
MIN_PERIOD_M = 0.05
"""Offsets shorter than this [m] are one motif seen twice (neighbouring detections), not a
period."""
PERIOD_TOLERANCE_M = 0.03
"""Twin offsets within this [m] of each other are one period."""
SHIFTS = (-2, -1, 1, 2)
"""Periods a pose is moved by to look for the copy keypoints confuse it with."""


def texture_period(
    keypoints: Keypoints, R_world_cam: np.ndarray, min_twins: int
) -> np.ndarray | None:
    """(3,) the texture's dominant period in the world frame [m] (sign chosen so its
    largest component is positive), or None when fewer than `min_twins` pairs of
    near-identical keypoints agree on one offset. R_world_cam (3, 3) turns camera offsets
    into the world frame."""
    import cv2

    if len(keypoints) < 2:
        return None
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(
        keypoints.descriptors, keypoints.descriptors, k=min(4, len(keypoints))
    )
    pairs = np.array(
        [
            (m.queryIdx, m.trainIdx)
            for row in knn
            for m in row
            if m.queryIdx != m.trainIdx and m.distance <= TWIN_MAX_BITS
        ],
        dtype=np.int64,
    ).reshape(-1, 2)
    offsets = keypoints.points_cam[pairs[:, 1]] - keypoints.points_cam[pairs[:, 0]]
    offsets = offsets @ R_world_cam.T
    offsets = offsets[np.linalg.norm(offsets, axis=1) > MIN_PERIOD_M]
    if len(offsets) < min_twins:
        return None
    largest = np.argmax(np.abs(offsets), axis=1)
    offsets *= np.sign(offsets[np.arange(len(offsets)), largest])[:, None]
    close = np.linalg.norm(offsets[:, None] - offsets[None], axis=2) < PERIOD_TOLERANCE_M
    support = close.sum(axis=1)
    best = int(np.argmax(support))
    if support[best] < min_twins:
        return None
    return offsets[close[best]].mean(axis=0)


def period_shifts(T_world_cam: np.ndarray, period: np.ndarray) -> list[np.ndarray]:
    """The (4, 4) pose moved by each of `SHIFTS` whole periods (3,) [m], world frame."""
    shifted = []
    for k in SHIFTS:
        T = T_world_cam.copy()
        T[:3, 3] += k * period
        shifted.append(T)
    return shifted
