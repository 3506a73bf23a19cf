"""Shared fixtures: the real data folder (skipped with a reason when absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEQUENCES = ("7scenes_redkitchen_1000f", "tum_fr1_desk_9f", "tum_fr1_xyz_10f")


def shared_sequence(name: str) -> Path:
    """Path of a sequence in ../shared/data, or skip the test saying why."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"real data not available: {path} is absent (CI and developers have it)")
    return path


@pytest.fixture
def rng():
    import numpy as np

    return np.random.default_rng(12345)
