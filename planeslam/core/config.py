"""Typed configuration machinery: frozen dataclasses from YAML mappings and back, and
layers of values overlaid key by key with the provenance of every key.

Loading rejects unknown keys and names the valid ones, so a misspelt key never
passes silently. Each stage's config dataclass lives beside its stage;
`planeslam.config` composes them and decides the layers (defaults, preset, file,
dataset camera, overrides).
"""

from __future__ import annotations

import dataclasses
import logging
import re
import types
import typing
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import yaml

from planeslam.core.bounded_parse import load_yaml, read_yaml_file, shown
from planeslam.core.errors import ConfigError
from planeslam.core.safe_files import write_text_atomic

logger = logging.getLogger(__name__)

T = TypeVar("T")


def from_mapping(cls: type[T], data: Any, source: str, section: str = "") -> T:
    """Build dataclass `cls` from a nested mapping, rejecting unknown keys.

    `source` names the file (or option) for error messages; `section` is the
    dotted path of this mapping inside it.
    """
    where = f"{source}: {section}" if section else source
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping of keys, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    data = renamed_keys(cls, data, where)
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(map(shown, unknown))}; "
            f"valid keys: {', '.join(fields)}"
        )
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        sub = f"{section}.{name}" if section else name
        kwargs[name] = _coerce(hints[name], value, source, sub)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def renamed_keys(cls: type, data: Mapping[str, Any], where: str, deep: bool = False) -> Any:
    """`data` with the old names of `cls`'s keys (its `RENAMED_KEYS`: old -> new) replaced
    by the new ones, with a warning; with `deep`, in its sections too. ConfigError when a
    mapping sets a key under both names."""
    if not isinstance(data, Mapping):
        return data
    for old, new in getattr(cls, "RENAMED_KEYS", {}).items():
        if old in data:
            if new in data:
                raise ConfigError(f"{where}: both {old} and {new}; {old} is {new}'s old name")
            logger.warning("%s: %s is now called %s", where, old, new)
            data = {(new if k == old else k): v for k, v in data.items()}
    if deep:
        hints = typing.get_type_hints(cls)
        data = {
            k: renamed_keys(hints[k], v, f"{where}.{k}", True)
            if k in hints and dataclasses.is_dataclass(hints[k])
            else v
            for k, v in data.items()
        }
    return data


def _coerce(hint: Any, value: Any, source: str, key: str) -> Any:
    """Convert a YAML value to the field's annotated type, or fail naming the key."""
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        return from_mapping(hint, value, source, key)  # type: ignore[arg-type]
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if value is None:
            return None
        return _coerce(args[0], value, source, key)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{source}: {key} expects a list, got {value!r}")
        (item,) = typing.get_args(hint)[:1]
        return tuple(_coerce(item, v, source, key) for v in value)
    if origin is typing.Literal:
        allowed = typing.get_args(hint)
        if value not in allowed:
            raise ConfigError(f"{source}: {key} must be one of {list(allowed)}, got {value!r}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: {key} expects true or false, got {value!r}")
        return value
    if hint in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{source}: {key} expects a number, got {value!r}")
        if hint is int and not float(value).is_integer():  # also inf and NaN
            raise ConfigError(f"{source}: {key} expects a whole number, got {value!r}")
        return hint(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {key} expects a string, got {value!r}")
        return value
    return value


def read_yaml(path: Path) -> Any:
    """Parse a YAML file within `bounded_parse`'s limits, or raise a ConfigError naming it."""
    return read_yaml_file(path, ConfigError, "config file")


def to_mapping(obj: Any) -> Any:
    """Dataclass -> plain dict/list tree, ready for YAML or JSON."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_mapping(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [to_mapping(v) for v in obj]
    return obj


def save_yaml(obj: Any, path: Path) -> None:
    """Write a dataclass (a resolved config) as YAML (atomically, never through a link)."""
    write_text_atomic(path, yaml.safe_dump(to_mapping(obj), sort_keys=False))


# ------------------------------------------------------------------------------ layers


@dataclass(frozen=True)
class ConfigLayer:
    """One source of configuration values, overlaid key by key on what lies below it."""

    values: Mapping[str, Any]
    """The keys this layer sets, nested by section (as in a YAML file)."""
    source: str
    """Where the values come from, in full (a file path, 'override camera.fx=500'): error
    messages name it."""
    label: str
    """Short provenance shown beside each key it sets ('preset tum_fr1', 'file my.yaml',
    'camera.yaml', '--set')."""


_OVERRIDE = re.compile(r"\s*([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+)\s*=(.*)", re.DOTALL)
_FLOAT_E = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")
"""Numbers like 1e-3, which YAML 1.1 (PyYAML) reads as strings."""


def parse_override(text: str, label: str = "override") -> ConfigLayer:
    """A layer setting one key from 'section.key=value' (value in YAML syntax: 0, 1.5e-3,
    true, null, [0, 65535], msac); nested sections are dotted
    ('segmentation.organized.pixel_stride=1'). Types are checked when the layers are
    resolved (`resolve_layers`)."""
    match = _OVERRIDE.fullmatch(text)
    if match is None:
        raise ConfigError(
            f"{label} {text!r}: expected section.key=value (e.g. backend.lag_frames=0)"
        )
    key, raw = match.group(1), match.group(2).strip()
    if _FLOAT_E.fullmatch(raw):
        value: Any = float(raw)
    else:
        value = load_yaml(raw, f"{label} {text!r}", ConfigError, "a YAML value") if raw else None
    return override_layer(key, value, f"{label} {shown(text)}", label)


def override_layer(key: str, value: Any, source: str, label: str) -> ConfigLayer:
    """A layer setting the dotted `key` ('run.backend') to `value`."""
    nested: Any = value
    for part in reversed(key.split(".")):
        nested = {part: nested}
    return ConfigLayer(nested, source, label)


def _merge(base: Mapping[str, Any], layer: Mapping[str, Any]) -> dict[str, Any]:
    """Nested mappings overlaid key by key (new dicts; neither input changes)."""
    out = dict(base)
    for key, value in layer.items():
        below = out.get(key)
        if isinstance(value, Mapping):
            out[key] = _merge(below if isinstance(below, Mapping) else {}, value)
        else:
            out[key] = value
    return out


def leaf_keys(cls: type, prefix: str = "") -> list[str]:
    """Dotted names of every key of config dataclass `cls`, sections expanded, in field order."""
    hints = typing.get_type_hints(cls)
    keys: list[str] = []
    for f in dataclasses.fields(cls):
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(hints[f.name]):
            keys += leaf_keys(hints[f.name], f"{name}.")
        else:
            keys.append(name)
    return keys


def _keys_set(cls: type, data: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Dotted names of the keys of `cls` that the (validated) mapping `data` sets."""
    hints = typing.get_type_hints(cls)
    keys: list[str] = []
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint) and isinstance(value, Mapping):
            keys += _keys_set(hint, value, f"{prefix}{name}.")  # type: ignore[arg-type]
        else:
            keys.append(f"{prefix}{name}")
    return keys


def resolve_layers(cls: type[T], layers: Sequence[ConfigLayer]) -> tuple[T, dict[str, str]]:
    """Overlay `layers` in order, key by key, on the defaults of dataclass `cls`.

    Every layer is checked as it is added (unknown keys with the valid ones, types,
    ranges), and a failure names that layer's `source`. Returns the config and, for every
    key (dotted, `leaf_keys` order), the `label` of the last layer that set it or
    'default'.
    """
    merged: dict[str, Any] = {}
    sources = dict.fromkeys(leaf_keys(cls), "default")
    result = from_mapping(cls, merged, "defaults")
    for layer in layers:
        if not isinstance(layer.values, Mapping):
            raise ConfigError(
                f"{layer.source}: expected a mapping of keys, got {type(layer.values).__name__}"
            )
        values = renamed_keys(cls, layer.values, layer.source, deep=True)
        merged = _merge(merged, values)
        result = from_mapping(cls, merged, layer.source)
        for key in _keys_set(cls, values):
            sources[key] = layer.label
    return result, sources


def _yaml_entry(key: str, value: Any) -> str:
    """'key: value' in YAML flow style, one line."""
    text = yaml.safe_dump({key: value}, default_flow_style=True, width=2**31 - 1).strip()
    return text[1:-1]  # drop the braces of the one-entry flow mapping


def format_with_sources(
    obj: Any,
    sources: Mapping[str, str],
    comment_column: int = 44,
    keys: Collection[str] | None = None,
) -> str:
    """A resolved config (dataclass) as YAML, each key followed by `# <where it came from>`;
    the text loads back as a config file. `keys` (dotted): only those and their sections."""
    lines: list[str] = []

    def wanted(dotted: str) -> bool:
        return keys is None or any(k == dotted or k.startswith(f"{dotted}.") for k in keys)

    def walk(mapping: Mapping[str, Any], prefix: str, depth: int) -> None:
        for key, value in mapping.items():
            dotted = f"{prefix}{key}"
            indent = "  " * depth
            if not wanted(dotted):
                continue
            if isinstance(value, dict) and dotted not in sources:
                lines.append(f"{indent}{key}:")
                walk(value, f"{dotted}.", depth + 1)
            else:
                entry = f"{indent}{_yaml_entry(key, value)}"
                lines.append(f"{entry.ljust(comment_column)}  # {sources.get(dotted, '?')}")

    walk(to_mapping(obj), "", 0)
    return "\n".join(lines) + "\n"
