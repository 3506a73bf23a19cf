"""Shared fixtures: the real data folder (skipped with a reason when absent); and the check
that every test module declares its tier, `unit` or `integration` (`make test-fast` runs
`-m "unit and not integration and not slow and not data"`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.corpus.tally import (  # noqa: F401  (the fault corpus's figures, across xdist workers)
    pytest_sessionfinish,
    pytest_terminal_summary,
    pytest_testnodedown,
)

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEQUENCES = ("7scenes_redkitchen_1000f", "tum_fr1_desk_9f", "tum_fr1_xyz_10f")

TIERS = ("unit", "integration")


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test module declares its tier (`pytestmark = pytest.mark.unit` or
    `pytest.mark.integration`); a test of a unit module that crosses stages carries its own
    `@pytest.mark.integration`, which wins (`make test-fast` selects "unit and not
    integration"). A module without a tier is an error, so none falls out of both."""
    untiered = sorted(
        {item.path.name for item in items if not any(item.get_closest_marker(n) for n in TIERS)}
    )
    if untiered:
        raise pytest.UsageError(
            f"test modules without a tier: {', '.join(untiered)}; add "
            "`pytestmark = pytest.mark.unit` (or `.integration`) below their imports"
        )


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
