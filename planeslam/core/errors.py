"""One exception hierarchy for the whole library.

The CLI turns any `PlaneSlamError` into a one-line message and exit code 2;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class PlaneSlamError(Exception):
    """Base class of every error planeslam raises on purpose."""


class ConfigError(PlaneSlamError):
    """A config file or value is missing, malformed or has unknown keys."""


class DatasetFormatError(PlaneSlamError):
    """A dataset folder, list file, image or trajectory file is not as expected."""


class FrameReadError(DatasetFormatError):
    """One frame's image is missing or cannot be decoded; a run skips that frame."""


class GeometryError(PlaneSlamError):
    """Degenerate geometry: ill-conditioned plane triples, too few points, ..."""


class AssociationError(PlaneSlamError):
    """Data association failed (no pairs in a time window, no matching planes, ...)."""


class MapError(PlaneSlamError):
    """Bad input to the map (shapes, unknown ids) or an unreadable / unknown map file."""


class EvaluationError(PlaneSlamError):
    """Trajectory evaluation cannot be done (empty files, no associated poses, ...)."""


class DownloadError(PlaneSlamError):
    """A download failed: HTTP error, unreachable server, interrupted transfer."""


class OutputFolderError(PlaneSlamError):
    """An output folder cannot be used: another run holds it, or it is not empty."""
