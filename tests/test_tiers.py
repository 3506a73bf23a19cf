"""The check in conftest.py that every test module declares its tier."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest
from conftest import pytest_collection_modifyitems

pytestmark = pytest.mark.unit


@dataclass
class _Item:
    """Stands in for a collected pytest.Item: its module's path and its marker names."""

    path: Path
    markers: set[str] = field(default_factory=set)

    def get_closest_marker(self, name: str) -> object | None:
        return name if name in self.markers else None


def test_a_module_without_a_tier_stops_collection_and_is_named() -> None:
    items = [_Item(Path("test_tiered.py"), {"unit"}), _Item(Path("test_bare.py"), {"slow"})]
    with pytest.raises(pytest.UsageError, match="without a tier: test_bare.py;"):
        pytest_collection_modifyitems(None, items)  # type: ignore[arg-type]


def test_modules_with_a_tier_pass() -> None:
    items = [_Item(Path("test_a.py"), {"unit"}), _Item(Path("test_b.py"), {"integration", "data"})]
    pytest_collection_modifyitems(None, items)  # type: ignore[arg-type]
