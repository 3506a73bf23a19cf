"""Building a backend by name: the one module that knows every backend (`base` knows none,
so the backends depend on it and not the other way round)."""

from __future__ import annotations

from planeslam.backend.base import Backend, BackendKind
from planeslam.backend.config import BackendConfig
from planeslam.backend.merge import MergeBackend
from planeslam.backend.worker import Isam2Worker
from planeslam.core.errors import ConfigError


def create_backend(kind: BackendKind | str, config: BackendConfig) -> Backend:
    """The backend `kind` ('isam2' or 'merge') with its config section."""
    try:
        kind = BackendKind(kind)
    except ValueError:
        valid = ", ".join(k.value for k in BackendKind)
        raise ConfigError(f"backend {kind!r} unknown; expected one of {valid}") from None
    if kind is BackendKind.MERGE:
        return MergeBackend()
    return Isam2Worker(config, inline=not config.separate_process)
