"""The two levels of the configuration (the basic keys, `config show` and `--advanced`)
and docs/configuration.md, generated from the config dataclasses' docstrings."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from planeslam.app.cli import main
from planeslam.app.config_command import DOCS_COMMAND
from planeslam.config import BASIC_KEYS, PlaneSlamConfig, configuration_markdown, load_config
from planeslam.core.config import leaf_keys
from planeslam.core.config_docs import field_docs, key_docs, type_text

pytestmark = pytest.mark.unit

DOCS = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


def test_configuration_page_is_current() -> None:
    assert DOCS.read_text(encoding="utf-8") == configuration_markdown(DOCS_COMMAND), (
        f"docs/configuration.md is stale: run `{DOCS_COMMAND}` and commit it"
    )


def test_basic_keys_are_few_real_and_documented() -> None:
    keys = leaf_keys(PlaneSlamConfig)
    assert len(BASIC_KEYS) <= 30 and len(set(BASIC_KEYS)) == len(BASIC_KEYS)
    assert not set(BASIC_KEYS) - set(keys), "a basic key that no config has"
    docs = {k.key: k for k in key_docs(PlaneSlamConfig)}
    assert [k for k in keys if not docs[k].doc] == [], "every key needs a docstring"
    floats = [k for k in BASIC_KEYS if docs[k].type_text == "float"]
    without_unit = [k for k in floats if not re.search(r"\[[^\]]+\]|_m$|_s$", docs[k].doc + k)]
    assert without_unit == [], "a basic number without its unit"


def test_no_dataset_figures_in_config_docstrings() -> None:
    """Measured results go stale in docstrings (they belong in docs/experiments.md, with
    the command that reproduces them), and so do references to README sections: every
    key of every section says what it does, not what it measured."""
    figures = re.compile(
        r"\bATE\b|\bfps\b|README|\breplay\b|\d{4}-\d\d-\d\d"  # results, dates
        r"|\d\s*(?:cm|mm)?\s*(?:->|against)\s*\d"  # before -> after, x against y
        r"|ICL-NUIM|\bfr[123]/"  # sequences named for their results
    )
    stale = {k.key: m.group() for k in key_docs(PlaneSlamConfig) if (m := figures.search(k.doc))}
    assert stale == {}


def test_field_docs_reads_the_docstring_under_each_field() -> None:
    docs = field_docs(PlaneSlamConfig)
    assert docs["camera"] == "Intrinsics and depth encoding."
    assert type_text(PlaneSlamConfig.__annotations__["run"]) == "RunConfig"
    run = {k.key: k for k in key_docs(PlaneSlamConfig)}
    assert run["run.backend"].type_text == "'isam2' or 'merge'"
    assert run["run.max_frames"].type_text == "int or null"
    assert run["camera.distortion"].type_text == "list of float"


def shown(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[str, dict[str, str]]:
    """`planeslam config show ARGS`: its text and {dotted key: source} of the keys shown."""
    assert main(["config", "show", *args]) == 0
    text = capsys.readouterr().out
    keys: dict[str, str] = {}
    path: list[str] = []
    for line in text.splitlines():
        if line.startswith("#"):
            continue
        depth = (len(line) - len(line.lstrip())) // 2
        name = line.strip().split(":")[0]
        path = path[:depth] + [name]
        if "#" in line:
            keys[".".join(path)] = line.rsplit("# ", 1)[1]
    return text, keys


def test_config_show_basic_and_advanced(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    user = tmp_path / "user.yaml"
    user.write_text("base: tum_fr1\nbackend:\n  lag_frames: 0\n")
    _, basic = shown(capsys, str(user), "--set", "map.voxel_m=0.02")
    assert set(BASIC_KEYS) <= set(basic)
    # the basic keys and what a layer set, nothing else
    assert set(basic) - set(BASIC_KEYS) == {"backend.lag_frames", "map.voxel_m"}
    assert basic["backend.lag_frames"] == f"file {user}" and basic["map.voxel_m"] == "--set"
    text, advanced = shown(capsys, str(user), "--set", "map.voxel_m=0.02", "--advanced")
    assert list(advanced) == leaf_keys(PlaneSlamConfig)
    saved = tmp_path / "shown.yaml"
    saved.write_text(text)
    expected = load_config(user)
    expected = replace(expected, map=replace(expected.map, voxel_m=0.02))
    assert load_config(saved) == expected  # --advanced loads back as the same config
    assert yaml.safe_load(text)["backend"]["lag_frames"] == 0


def test_config_docs_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "configuration.md"
    assert main(["config", "docs", "--markdown", str(out)]) == 0
    assert out.read_text(encoding="utf-8") == DOCS.read_text(encoding="utf-8")
    capsys.readouterr()
    assert main(["config", "docs"]) == 0
    assert capsys.readouterr().out.startswith("# Configuration\n")
