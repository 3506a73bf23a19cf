"""Building a backend by name: the one module that knows every backend (`base` knows none,
so the backends depend on it and not the other way round)."""

from __future__ import annotations

import dataclasses

from planeslam.backend.base import Backend, BackendKind
from planeslam.backend.config import BackendConfig
from planeslam.backend.merge import MergeBackend
from planeslam.backend.worker import Isam2Worker
from planeslam.core.errors import ConfigError
from planeslam.mapping.config import MapConfig


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


def map_config_for(config: MapConfig, backend: Backend) -> MapConfig:
    """`config` with the settings it leaves to the backend (null) set to the backend's
    choice (`Backend.map_cull_single_view_after`, `map_merge_segments`)."""
    return dataclasses.replace(
        config,
        cull_single_view_after=(
            backend.map_cull_single_view_after
            if config.cull_single_view_after is None
            else config.cull_single_view_after
        ),
        merge_segments=(
            backend.map_merge_segments if config.merge_segments is None else config.merge_segments
        ),
    )
