"""The package layering (README, Layout): every import, lazy ones included, points down.

    core <- io, frontend <- tracking, mapping <- factors <- backend <- config <- slam
         <- eval <- app        (sim: synthetic scenes, on core and io only)

A module may import its own layer and the layers its entry allows; nothing else.
"""

from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx
import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]

BELOW_FACTORS = {"core", "io", "frontend", "tracking", "mapping"}
BELOW_CONFIG = BELOW_FACTORS | {"factors", "backend"}
ALLOWED: dict[str, set[str]] = {
    "core": set(),
    "io": {"core"},
    "frontend": {"core"},
    "sim": {"core", "io"},
    "tracking": {"core", "io", "frontend"},
    "mapping": {"core", "io", "frontend"},
    "factors": BELOW_FACTORS,
    "backend": BELOW_FACTORS | {"factors"},
    "config": BELOW_CONFIG,
    "slam": BELOW_CONFIG | {"config"},
    "eval": BELOW_CONFIG | {"config", "slam", "sim"},
    "app": BELOW_CONFIG | {"config", "slam", "sim", "eval"},
}
"""Layer -> the layers it may import (besides itself and `planeslam.configs`, data only)."""


def _layer_of_file(path: Path) -> str:
    rel = path.relative_to(ROOT)
    if rel.parts[0] in ("factors", "eval"):
        return rel.parts[0]
    if len(rel.parts) == 2:  # planeslam/<module>.py
        return rel.stem
    return rel.parts[1]


def _layer_of_module(name: str) -> str | None:
    """'planeslam.frontend.objects' -> 'frontend'; None for the package root and data."""
    parts = name.split(".")
    if parts[0] != "planeslam" or len(parts) < 2 or parts[1] == "configs":
        return None
    return parts[1]


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in the file, relative ones resolved."""
    package = ".".join(("planeslam", *path.relative_to(ROOT).parts[:-1]))
    if path.relative_to(ROOT).parts[0] in ("factors", "eval"):
        package = "planeslam." + path.relative_to(ROOT).parts[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            found.append((node.lineno, module))
    return found


def _library_files() -> list[Path]:
    files = [p for p in (ROOT / "planeslam").rglob("*.py") if p.name != "__init__.py"]
    files += list((ROOT / "factors").glob("*.py")) + list((ROOT / "eval").glob("*.py"))
    return sorted(f for f in files if f.name != "__init__.py" or f.parent.name != "planeslam")


def test_every_layer_is_known():
    layers = {_layer_of_file(p) for p in _library_files()}
    assert layers <= set(ALLOWED), f"modules outside the layering: {layers - set(ALLOWED)}"


def test_imports_point_down():
    wrong = []
    for path in _library_files():
        layer = _layer_of_file(path)
        for line, module in _imports(path):
            target = _layer_of_module(module)
            if target is None or target == layer:
                continue
            if target not in ALLOWED[layer]:
                wrong.append(f"{path.relative_to(ROOT)}:{line} ({layer}) imports {module}")
    assert not wrong, "imports against the layering:\n" + "\n".join(wrong)


def test_the_check_sees_a_wrong_import(tmp_path):
    """The walker resolves relative imports and finds lazy ones inside functions."""
    path = ROOT / "planeslam" / "core" / "geometry.py"
    imports = dict((m, n) for n, m in _imports(path))
    assert "planeslam.core.errors" in imports
    fake = ast.parse("def f():\n    from planeslam.slam import SLAM\n")
    (node,) = [n for n in ast.walk(fake) if isinstance(n, ast.ImportFrom)]
    assert _layer_of_module(node.module) == "slam" and "slam" not in ALLOWED["core"]


def test_no_module_imports_the_cli():
    """`planeslam.app.cli` builds the parser from the command modules; none imports it back
    (lazy imports included), so there is no cycle to break at load time."""
    back = [
        f"{path.relative_to(ROOT)}:{line}"
        for path in _library_files()
        if path.name != "cli.py"
        for line, module in _imports(path)
        if module == "planeslam.app.cli"
    ]
    assert not back, "modules importing the CLI:\n" + "\n".join(back)


def _type_only_lines(path: Path) -> set[int]:
    """Lines of the imports inside `if TYPE_CHECKING:` blocks (no import at run time)."""
    lines: set[int] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            lines |= {
                n.lineno for n in ast.walk(node) if isinstance(n, ast.Import | ast.ImportFrom)
            }
    return lines


def test_no_import_cycles_at_run_time():
    """The library's modules import each other without a cycle (lazy imports inside
    functions included, type-only imports left out): each room depends one way."""
    graph = nx.DiGraph()
    for path in _library_files():
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        type_only = _type_only_lines(path)
        for line, imported in _imports(path):
            if imported.startswith("planeslam.") and line not in type_only:
                graph.add_edge(module, imported)
    cycles = sorted(sorted(cycle) for cycle in nx.simple_cycles(graph))
    assert not cycles, f"import cycles: {cycles}"


MAX_MODULE_LINES = 700


def test_modules_are_small_rooms():
    sizes = {
        str(path.relative_to(ROOT)): len(path.read_text(encoding="utf-8").splitlines())
        for path in _library_files()
    }
    large = sorted(name for name, lines in sizes.items() if lines > MAX_MODULE_LINES)
    assert not large, f"over {MAX_MODULE_LINES} lines: {large}"
