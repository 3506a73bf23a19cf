"""Planes only their first frame saw leave the map after `cull_single_view_after` more
frames, with their edges and corners; planes seen twice, or recently, stay."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_segment_merge import contents_with, edge, patch

from planeslam.backend.config import BackendConfig
from planeslam.backend.factory import create_backend, map_config_for
from planeslam.core.errors import ConfigError
from planeslam.mapping.config import MapConfig
from planeslam.mapping.culling import cull_single_view
from planeslam.mapping.records import MapCorner

pytestmark = pytest.mark.unit


def test_single_view_planes_leave_after_the_given_frames_with_their_edges_and_corners():
    floor = replace(patch(0, [0, 0, 0], [1, 0, 0], [0, 1, 0], 2), seen_in=frozenset({0, 5}))
    wall = replace(patch(1, [0, 0, 0], [0, 0, 1], [1, 0, 0], 1), seen_in=frozenset({2}))
    side = replace(patch(2, [0, 0, 0], [0, 1, 0], [0, 0, 1], 1), seen_in=frozenset({9}))
    legacy = patch(3, [3, 0, 0], [0, 1, 0], [0, 0, 1], 1)  # loaded from an older map file
    contents = contents_with(floor, wall, side, legacy)
    contents.edges = {(0, 1): edge(0, 1, 0.0, 1.0), (0, 2): edge(0, 2, 0.0, 1.0)}
    contents.corners = {4: MapCorner(4, (0, 1, 2), np.zeros(3), 0, 1)}
    contents.frames_merged = 12  # merge numbers 0..11 done
    assert cull_single_view(contents, 0) == []  # off
    assert cull_single_view(contents, 10) == []  # the wall's frame 2 is 9 frames back
    contents.frames_merged = 13
    assert cull_single_view(contents, 10) == [1]
    assert sorted(contents.planes) == [0, 2, 3]
    assert list(contents.edges) == [(0, 2)] and contents.corners == {}
    assert list(contents.culled) == [1]  # remembered: seen again, it is not new


def test_a_plane_culled_again_is_remembered_once():
    first = replace(patch(0, [0, 0, 0], [1, 0, 0], [0, 1, 0], 1), seen_in=frozenset({0}))
    again = replace(patch(1, [0.1, 0, 0.01], [1, 0, 0], [0, 1, 0], 1), seen_in=frozenset({3}))
    apart = replace(patch(2, [3, 0, 0], [1, 0, 0], [0, 1, 0], 1), seen_in=frozenset({3}))
    above = replace(patch(3, [0, 0, 0.3], [1, 0, 0], [0, 1, 0], 1), seen_in=frozenset({3}))
    contents = contents_with(first)
    contents.frames_merged = 2
    assert cull_single_view(contents, 1) == [0]
    contents.planes = {p.id: p for p in (again, apart, above)}
    contents.frames_merged = 5
    assert cull_single_view(contents, 1) == [1, 2, 3]
    assert sorted(contents.culled) == [0, 2, 3]  # 1 is the same patch, 1 cm up and 10 cm on


def test_cull_setting_is_checked():
    with pytest.raises(ConfigError, match="cull_single_view_after"):
        MapConfig(cull_single_view_after=-1)
    with pytest.raises(ConfigError, match="merge_segments"):
        MapConfig(merge_segments=1)  # type: ignore[arg-type]


@pytest.mark.integration  # starts the iSAM2 worker process
def test_the_backend_chooses_culling_and_segment_merge_unless_the_config_does():
    """null (the default): iSAM2 culls after 5 keyframes and merges segments; the paper's
    merge backend, which merges every frame and never revises a pose, does neither."""
    isam2, merge = (
        create_backend("isam2", BackendConfig()),
        create_backend("merge", BackendConfig()),
    )
    try:
        chosen = map_config_for(MapConfig(), isam2)
        assert (chosen.cull_single_view_after, chosen.merge_segments) == (5, True)
        chosen = map_config_for(MapConfig(), merge)
        assert (chosen.cull_single_view_after, chosen.merge_segments) == (0, False)
        explicit = MapConfig(cull_single_view_after=10, merge_segments=False)
        assert map_config_for(explicit, isam2) == explicit
    finally:
        isam2.close()
        merge.close()
