"""Relocalisations on trial: placements in the map that later keyframes can take back.

A relocalised keyframe (placed by a whole-map search, or after lost frames) has no
measured motion from the previous keyframe; in a box, a cabinet or a square room its
place may be a half turn off and still fit every plane. So the iSAM2 backend
(`planeslam.backend.isam2`):

1. ties it to the previous keyframe only by a weak link (`WEAK_LINK_SIGMAS`: enough to
   keep the system determinate, too weak to hold a wrong place against evidence);
2. opens a *group*: the relocalised keyframe and the keyframes tracked from it, until
   the next relocalisation. For `relocalisation_trial_keyframes` keyframes the group's
   factors on landmarks older than it (its *ties*: what placed it in the map, made
   under the relocalisation's hypothesis) are recorded;
3. each loop from a keyframe of a group on trial to a keyframe older than the group is
   an independent placement of the group (`implied_placement`). One that agrees with
   the group's place (`agree`) enters the graph and supports the relocalisation; one
   that does not waits outside the graph;
4. when more waiting loops agree with each other than support the relocalisation
   (itself counted once), `decide` rejects it: the backend removes the group's ties
   and weak link, moves the group's keyframes and the landmarks it created rigidly to
   where the loops put it, re-seeds the weak links there, adds the loops and restarts
   iSAM2 on the whole (the rebuild re-initialises the moved variables, which iSAM2's
   `removeFactorIndices` alone cannot). A group whose trial ends stays, and the loops
   still waiting on it are rejected.

This is pairwise consistency (PCM, Mangelson et al. 2018) between the relocalisation
and the loops on the group's one placement, with the relocalisation trusted over a
single loop: a single wrong loop (repetitive texture) cannot move a group, two
agreeing ones can.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np

from planeslam.core.geometry import invert_pose, pose_distances
from planeslam.core.types import LoopConstraint

HYPOTHESIS_GATE_M = 0.3
"""Two placements of a keyframe (by a relocalisation, by a loop) agree within this
distance [m] and HYPOTHESIS_GATE_DEG; after an update a loop factor whose residual exceeds
them is removed. Constants, not keys: no benchmark sequence has shown a value to prefer."""
HYPOTHESIS_GATE_DEG = 15.0
"""See HYPOTHESIS_GATE_M [deg]."""
WEAK_LINK_SIGMAS = np.r_[[1.0] * 3, [3.0] * 3]
"""Sigmas (rotation [rad], then translation [m]) of the link from the previous keyframe to
a relocalised one: about what a room-sized scene leaves unknown."""


@dataclass
class Relocalisation:
    """A relocalised keyframe's group and its trial."""

    first: int
    """Frame index of the relocalised keyframe."""
    previous: int
    """Frame index of the keyframe before it (the weak link's other end)."""
    opened_at: int
    """Keyframes added before it (the trial runs `relocalisation_trial_keyframes` more)."""
    link: gtsam.NonlinearFactor
    """The weak link from `previous` (replaced when the group moves)."""
    old_keys: frozenset[int]
    """gtsam keys of the landmarks that existed before it."""
    keyframes: list[int] = field(default_factory=list)
    """Frame indices of its keyframes (it first), until the next relocalisation."""
    ties: list[gtsam.NonlinearFactor] = field(default_factory=list)
    """Its keyframes' committed factors on `old_keys`, during the trial."""
    created: set[int] = field(default_factory=set)
    """gtsam keys of the landmarks its keyframes created."""
    support: int = 0
    """Loops that agreed with its place and entered the graph."""
    waiting: list[tuple[LoopConstraint, np.ndarray]] = field(default_factory=list)
    """Loops that put it elsewhere, each with the T_world_cam (4, 4) of `first` it implies."""
    on_trial: bool = True

    def holds(self, index: int) -> bool:
        """Whether keyframe `index` belongs to the group."""
        return index in self.keyframes


def implied_placement(
    T_world_old: np.ndarray,
    loop: LoopConstraint,
    T_world_first: np.ndarray,
    T_world_cam: np.ndarray,
) -> np.ndarray:
    """T_world_cam (4, 4) of a group's first keyframe that `loop` implies: the loop's older
    keyframe at T_world_old (4, 4), the loop's pose in it, and the group's own relative
    pose from its first keyframe (at T_world_first) to the loop's keyframe (at T_world_cam)."""
    T_first_cam = invert_pose(T_world_first) @ T_world_cam
    return T_world_old @ loop.T_old_cam @ invert_pose(T_first_cam)


def agree(T_a: np.ndarray, T_b: np.ndarray, gate_m: float, gate_deg: float) -> bool:
    """Whether two poses (4, 4) are within `gate_m` [m] and `gate_deg` [deg] of each other."""
    metres, degrees = pose_distances(T_a, T_b)
    return bool(metres <= gate_m and degrees <= gate_deg)


def decide(
    group: Relocalisation, gate_m: float, gate_deg: float
) -> tuple[list[int], np.ndarray] | None:
    """Whether `group`'s waiting loops outvote its relocalisation: the largest set of them
    that agree pairwise (rows of `group.waiting`, and the placement of its latest member),
    when it has more members than the relocalisation's `1 + support`; else None."""
    best = _largest_agreeing([T for _, T in group.waiting], gate_m, gate_deg)
    if len(best) <= 1 + group.support:
        return None
    return best, group.waiting[best[-1]][1]


def _largest_agreeing(
    placements: Sequence[np.ndarray], gate_m: float, gate_deg: float
) -> list[int]:
    """Indices of the largest subset of `placements` that agree pairwise (greedy from each
    member in turn: a handful of loops wait at most)."""
    best: list[int] = []
    for seed in range(len(placements)):
        members = [seed]
        for other in range(len(placements)):
            if other != seed and all(
                agree(placements[other], placements[m], gate_m, gate_deg) for m in members
            ):
                members.append(other)
        if len(members) > len(best):
            best = sorted(members)
    return best
