"""Parsing that a small crafted file cannot turn into a hang, a huge allocation or a
traceback: UTF-8 text with a size limit, YAML with limits on aliases and on the size of
the tree they expand to, YAML and JSON with a nesting limit, and finite numbers in range.

Every function raises the error class its caller passes (a `PlaneSlamError` subclass:
ConfigError for configs, MapError for maps, ...) with a one-line message naming the file.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import yaml

from planeslam.core.errors import PlaneSlamError

MAX_DEPTH = 64
"""Deepest nesting of lists and mappings accepted in YAML or JSON (ours use under 10)."""
MAX_JSON_BYTES = 1 << 30
"""Largest JSON file read [bytes] (a long run's map.json holds tens of MB)."""
MAX_ABS_NUMBER = 1e15
"""Largest magnitude of a number read from our JSON files (metres, seconds, counts, ids)."""
MAX_YAML_BYTES = 1 << 20
"""Largest YAML file read [bytes] (configs and camera.yaml are a few kB)."""
MAX_YAML_ALIASES = 100
"""Most aliases (`*name`) in one YAML document."""
MAX_YAML_NODES = 200_000
"""Most nodes a YAML document may expand to, every alias counted with what it names (an
alias bomb of a few hundred bytes expands to billions)."""


def read_text(
    path: str | Path, error: type[PlaneSlamError], max_bytes: int, what: str = "file"
) -> str:
    """The text of `path` decoded as UTF-8 (a leading BOM dropped). `error` naming the file
    when it is missing, unreadable, larger than `max_bytes` or not UTF-8."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read(max_bytes + 1)
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise error(f"{path}: {what} larger than {max_bytes} bytes; not read")
    return decode_utf8(data, str(path), error)


def decode_utf8(data: bytes, source: str, error: type[PlaneSlamError]) -> str:
    """`data` as UTF-8 text (a BOM dropped), or `error` naming `source` and the offset."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(
            f"{source}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start})"
        ) from None


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe loader counting aliases, nesting depth and expanded nodes as it
    composes, so that a bomb is refused before anything walks the expanded tree."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.aliases = 0
        self.depth = 0
        self.sizes: dict[int, int] = {}
        """Expanded node count by id(node) (aliases return their anchor's node)."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > MAX_YAML_ALIASES:
                raise _Refused(f"more than {MAX_YAML_ALIASES} aliases")
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise _Refused(f"nested deeper than {MAX_DEPTH} levels")
        try:
            node = super().compose_node(parent, index)
        finally:
            self.depth -= 1
        if id(node) not in self.sizes:
            size = 1
            if isinstance(node, yaml.SequenceNode):
                size += sum(self.sizes.get(id(v), 1) for v in node.value)
            elif isinstance(node, yaml.MappingNode):
                size += sum(
                    self.sizes.get(id(k), 1) + self.sizes.get(id(v), 1) for k, v in node.value
                )
            if size > MAX_YAML_NODES:
                raise _Refused(f"expands to more than {MAX_YAML_NODES} values (an alias bomb?)")
            self.sizes[id(node)] = size
        return node


class _Refused(Exception):
    """A limit of `_BoundedLoader` was passed."""


def load_yaml(text: str, source: str, error: type[PlaneSlamError], what: str = "valid YAML") -> Any:
    """Parse one YAML document (safe types only) within the limits above; `error` naming
    `source` ('SOURCE: not WHAT (reason)') for a syntax error or a passed limit."""
    if len(text) > MAX_YAML_BYTES:
        raise error(f"{source}: YAML larger than {MAX_YAML_BYTES} bytes; not read")
    loader = None
    try:
        loader = _BoundedLoader(text)  # its reader already rejects control characters
        return loader.get_single_data()
    except _Refused as exc:
        raise error(f"{source}: YAML refused: {exc}") from None
    except (yaml.YAMLError, RecursionError, ValueError, OverflowError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise error(f"{source}: not {what} ({reason})") from None
    finally:
        if loader is not None:
            loader.dispose()


def read_yaml_file(path: str | Path, error: type[PlaneSlamError], what: str = "file") -> Any:
    """`load_yaml` of the UTF-8 text of `path` (at most MAX_YAML_BYTES)."""
    text = read_text(path, error, MAX_YAML_BYTES, what)
    return load_yaml(text, str(path), error, "a readable YAML file")


def load_json(text: str, source: str, error: type[PlaneSlamError]) -> Any:
    """Parse JSON nested at most MAX_DEPTH deep; NaN and Infinity literals are refused.
    `error` naming `source` otherwise."""

    def no_constant(name: str) -> Any:
        raise ValueError(f"{name} is not a JSON number")

    try:
        data = json.loads(text, parse_constant=no_constant)
    except RecursionError:
        raise error(f"{source}: JSON nested deeper than {MAX_DEPTH} levels") from None
    except json.JSONDecodeError as exc:
        raise error(f"{source}: not JSON ({exc.msg} at line {exc.lineno})") from None
    except ValueError as exc:  # a NaN / Infinity literal, a number too long to convert
        raise error(f"{source}: not JSON ({str(exc).splitlines()[0]})") from None
    check_tree(data, source, error)
    return data


def read_json_file(
    path: str | Path,
    error: type[PlaneSlamError],
    max_bytes: int = MAX_JSON_BYTES,
    what: str = "file",
    max_abs: float | None = MAX_ABS_NUMBER,
) -> Any:
    """`load_json` of the UTF-8 text of `path` (at most `max_bytes`), every number checked
    finite and within +-`max_abs` (None: not checked) by `check_tree`."""
    data = load_json(read_text(path, error, max_bytes, what), str(path), error)
    check_tree(data, str(path), error, max_abs)
    return data


def check_tree(
    data: Any, source: str, error: type[PlaneSlamError], max_abs: float | None = None
) -> None:
    """`error` naming `source` when lists and mappings in `data` nest deeper than MAX_DEPTH,
    or (with `max_abs`) when a number in it is not finite or beyond +-max_abs, naming its
    key ('planes[2].normal[0]'). Walked without recursion."""
    stack: list[tuple[Any, int, Any, Any]] = [(data, 1, None, None)]
    while stack:
        value, depth, parent, key = stack.pop()
        here = (parent, key)
        if isinstance(value, dict):
            items: Any = value.items()
        elif isinstance(value, (list, tuple)):
            items = enumerate(value)
        else:
            if (
                max_abs is not None
                and isinstance(value, (int, float))
                and not isinstance(value, bool)
            ):
                finite_number(value, f"{source}: {_key_path(here)}", error, -max_abs, max_abs)
            continue
        if depth > MAX_DEPTH:
            raise error(f"{source}: nested deeper than {MAX_DEPTH} levels")
        stack.extend((v, depth + 1, here, k) for k, v in items)


def _key_path(here: Any) -> str:
    """'a.b[2]' from the (parent, key) chain `check_tree` keeps."""
    parts: list[str] = []
    while here is not None and here[1] is not None:
        parent, key = here
        parts.append(f"[{key}]" if isinstance(key, int) else f".{shown(key)}")
        here = parent
    return "".join(reversed(parts)).lstrip(".") or "(top level)"


def finite_number(
    value: Any,
    where: str,
    error: type[PlaneSlamError],
    low: float = -math.inf,
    high: float = math.inf,
) -> float:
    """`value` as a float when it is a number (not a bool), finite and in [low, high];
    `error` naming `where` (file and key) otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(f"{where}: expected a number, got {_short(value)}")
    try:
        number = float(value)
    except OverflowError:  # an int beyond float's range
        number = math.inf
    if not math.isfinite(number) or not low <= number <= high:
        raise error(
            f"{where}: expected a finite number in [{low:g}, {high:g}], got {_short(value)}"
        )
    return number


def shown(text: Any) -> str:
    """`text` as a message shows it: as it is when printable, else quoted with escapes (a
    key or value read from a file keeps the message on one line)."""
    text = str(text)
    return text if text.isprintable() else repr(text)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."
