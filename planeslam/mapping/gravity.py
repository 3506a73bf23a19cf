"""The map's up vector: where it came from, and how an estimated up follows the map.

The map's up (opposite to gravity, world frame) comes from, most trusted first:
`Map.set_gravity` (kept as given); the first merged frame whose up came from a plane
or the config; until such a frame, the first merged frame, whose up fell back to the
camera's -y axis. An up taken from a frame then follows the merged map: at every
re-aggregation it becomes the normal of the largest map plane near horizontal.
"""

from __future__ import annotations

import enum
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from planeslam.core.errors import MapError
from planeslam.core.types import GravitySource
from planeslam.mapping.records import MapPlane


class UpOrigin(enum.Enum):
    """Where the map's up vector came from."""

    UNKNOWN = "unknown"
    """No up yet."""
    SET = "set"
    """Given to `Map.set_gravity` (or of unknown provenance in a map file): kept as is."""
    FRAME = "frame"
    """A frame's estimate from a plane or the config; follows the merged map."""
    FRAME_FALLBACK = "frame fallback"
    """A frame's camera fallback; replaced by the first frame with a plane-based up."""


_FRAME_TEXT = re.compile(r"frame (\S+)( \(fallback\))?")


@dataclass(frozen=True)
class UpSource:
    """The provenance of the map's up vector. `str()` gives the text `map.json` stores:
    '' (unknown), 'set', 'frame <timestamp>' or 'frame <timestamp> (fallback)'."""

    origin: UpOrigin = UpOrigin.UNKNOWN
    timestamp: float | None = None
    """The frame's timestamp [s] for FRAME and FRAME_FALLBACK, else None."""

    def __post_init__(self) -> None:
        from_frame = self.origin in (UpOrigin.FRAME, UpOrigin.FRAME_FALLBACK)
        if from_frame != (self.timestamp is not None):
            raise MapError(
                f"up source {self.origin.value!r}: a frame timestamp is expected with "
                f"(and only with) 'frame' and 'frame fallback', got {self.timestamp!r}"
            )

    @classmethod
    def of_frame(cls, timestamp: float, source: GravitySource) -> UpSource:
        """The up of the frame at `timestamp` [s] whose up came from `source`."""
        origin = UpOrigin.FRAME_FALLBACK if source.is_fallback else UpOrigin.FRAME
        return cls(origin, timestamp)

    @property
    def is_fallback(self) -> bool:
        """Whether the first frame with a plane-based up replaces it."""
        return self.origin is UpOrigin.FRAME_FALLBACK

    @property
    def follows_map(self) -> bool:
        """Whether re-aggregation snaps it to the largest near-horizontal map plane."""
        return self.origin in (UpOrigin.FRAME, UpOrigin.FRAME_FALLBACK)

    def __str__(self) -> str:
        if self.origin is UpOrigin.UNKNOWN:
            return ""
        if self.origin is UpOrigin.SET:
            return "set"
        return f"frame {self.timestamp}" + (" (fallback)" if self.is_fallback else "")

    @classmethod
    def parse(cls, text: str) -> UpSource:
        """The inverse of `str()`. Any other text (not written by planeslam) reads as SET:
        an up of unknown provenance is kept as given."""
        if text == "":
            return cls()
        match = _FRAME_TEXT.fullmatch(text)
        if match is None:  # 'set' or free text
            return cls(UpOrigin.SET)
        try:
            timestamp = _number(match[1])
        except ValueError:
            return cls(UpOrigin.SET)
        return cls(UpOrigin.FRAME_FALLBACK if match[2] else UpOrigin.FRAME, timestamp)


def _number(text: str) -> float:
    """An int for an integer literal (so 'frame 7' reads back as written), else a float."""
    try:
        return int(text)
    except ValueError:
        return float(text)


def refine_up(up: np.ndarray, planes: Iterable[MapPlane], orientation_tol_deg: float) -> np.ndarray:
    """(3,) the normal, signed to point like `up` (3,), of the largest-area plane within
    `orientation_tol_deg` [deg] of horizontal; `up` itself when no plane is."""
    cos_tol = math.cos(math.radians(orientation_tol_deg))
    best: MapPlane | None = None
    for p in planes:
        if abs(float(p.normal @ up)) >= cos_tol and (best is None or p.area_m2 > best.area_m2):
            best = p
    if best is None:
        return up
    return best.normal * np.sign(float(best.normal @ up))
