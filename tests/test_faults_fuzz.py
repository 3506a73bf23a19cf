"""Property-based fault corpus: every reader and parser, given generated input (random
bytes, and valid files with one value replaced by anything), either succeeds or raises a
PlaneSlamError with a one-line message (the CLI's exit 2): never another exception, a
traceback or a hang (hypothesis's deadline).

The suite runs few examples (profile 'suite'); `make fuzz` sets PLANESLAM_FUZZ=1 for the
'fuzz' profile: many more examples (PLANESLAM_FUZZ_EXAMPLES each, about ten minutes in all).
"""

from __future__ import annotations

import copy
import json
import os
import string
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from planeslam.config import PlaneSlamConfig, explain_config, load_camera_yaml
from planeslam.core.camera import CameraConfig
from planeslam.core.config import leaf_keys, parse_override, resolve_layers
from planeslam.core.errors import PlaneSlamError
from planeslam.eval.report import read_frame_records
from planeslam.io.dataset import read_list_file
from planeslam.io.rosbag import camera_from_info
from planeslam.io.trajectory import read_tum
from planeslam.mapping.world_map import Map
from tests.corpus.cases import SMALL_CAMERA, one_line
from tests.corpus.tally import Outcome, record

pytestmark = pytest.mark.unit

settings.register_profile(
    "suite",
    max_examples=20,
    deadline=timedelta(seconds=5),
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
settings.register_profile(
    "fuzz",
    max_examples=int(os.environ.get("PLANESLAM_FUZZ_EXAMPLES", "3000")),
    deadline=timedelta(seconds=10),
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
PROFILE = settings.get_profile("fuzz" if os.environ.get("PLANESLAM_FUZZ") else "suite")


def clean_or_success(case: str, call: Callable[[], Any]) -> None:
    """Run `call`: success, or a one-line PlaneSlamError; anything else fails the example."""
    try:
        call()
    except PlaneSlamError as exc:
        if not one_line(str(exc)):
            record(case, Outcome.CRASH)
            raise AssertionError(f"{case}: message not one line: {exc!r}") from exc
    except BaseException:
        record(case, Outcome.CRASH)
        raise
    record(case, Outcome.CLEAN_ERROR)


def _write(folder: Path, name: str, data: bytes) -> Path:
    path = folder / name
    path.write_bytes(data)
    return path


# ------------------------------------------------------------------ strategies

JSON_LEAF = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
JSON_VALUE = st.recursive(
    JSON_LEAF,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=12,
)
NUMBER_TEXT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers().map(str),
    st.sampled_from(["nan", "inf", "-inf", "1e999", "0x10", "", "1,5", "١٢", "1_000"]),
    st.text(alphabet=string.printable, max_size=8),
)
TOKENS = st.one_of(NUMBER_TEXT, st.text(max_size=10))


def rows(fields: int) -> st.SearchStrategy[bytes]:
    """Text files of rows of about `fields` tokens, comments and blank lines, or raw bytes."""
    row = st.lists(TOKENS, min_size=max(0, fields - 1), max_size=fields + 1).map(" ".join)
    line = st.one_of(row, st.just("# comment"), st.just(""))
    text = st.lists(line, max_size=8).map("\n".join).map(lambda t: t.encode("utf-8", "replace"))
    return st.one_of(text, st.binary(max_size=200))


def yaml_text(mapping: st.SearchStrategy[dict[str, Any]]) -> st.SearchStrategy[bytes]:
    """YAML of generated mappings, random text, or random bytes."""
    return st.one_of(
        mapping.map(lambda m: yaml.safe_dump(m).encode()),
        st.text(max_size=200).map(lambda t: t.encode("utf-8", "replace")),
        st.binary(max_size=200),
    )


CAMERA_KEYS = [*CameraConfig.__dataclass_fields__, "bogus"]
CAMERA_MAPPING = st.dictionaries(st.sampled_from(CAMERA_KEYS), JSON_VALUE, max_size=6)
CONFIG_KEYS = leaf_keys(PlaneSlamConfig)


def _nest(dotted: str, value: Any) -> dict[str, Any]:
    out: Any = value
    for part in reversed(dotted.split(".")):
        out = {part: out}
    return out


CONFIG_MAPPING = st.lists(
    st.tuples(st.sampled_from([*CONFIG_KEYS, "run.bogus", "base"]), JSON_VALUE), max_size=4
).map(lambda kv: {k: v for d in (_nest(*p) for p in kv) for k, v in d.items()})

_PLANE = {
    "id": 0,
    "normal": [0.0, 0.0, -1.0],
    "d": 1.0,
    "centroid": [0.0, 0.0, 1.0],
    "scatter": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 0.01],
    "num_points": 100,
    "area_m2": 1.0,
    "outline": [[0, 0, 1.0], [1, 0, 1.0], [0, 1, 1.0]],
    "observations": 1,
    "seen_in": [0],
}
_EDGE = {
    "planes": [0, 1],
    "segment": [[0, 0, 1.0], [1, 0, 1.0]],
    "length_m": 1.0,
    "angle_rad": 1.57,
    "convex": True,
    "observations": 1,
}
_CORNER = {"id": 0, "planes": [0, 1, 2], "point": [0, 0, 1.0], "convex_edges": 3, "observations": 1}
_OBJECT = {"id": 0, "class": "box", "planes": [0, 1, 2], "corners": [0], "size_m": [1, 1, 1]}


def _map_template() -> dict[str, Any]:
    data = Map().to_dict()
    plane1 = dict(_PLANE, id=1, normal=[0.0, -1.0, 0.0])
    plane2 = dict(_PLANE, id=2, normal=[-1.0, 0.0, 0.0])
    data.update(
        planes=[dict(_PLANE), plane1, plane2],
        edges=[dict(_EDGE)],
        corners=[dict(_CORNER)],
        objects=[dict(_OBJECT)],
        next_plane_id=3,
        next_corner_id=1,
    )
    return data


MAP_TEMPLATE = _map_template()


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path into a JSON tree."""
    found = [prefix]
    if isinstance(value, dict):
        for k, v in value.items():
            found += _paths(v, (*prefix, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            found += _paths(v, (*prefix, i))
    return found


MAP_PATHS = _paths(MAP_TEMPLATE)[1:]


def _replaced(path: tuple, value: Any) -> dict[str, Any]:
    data = copy.deepcopy(MAP_TEMPLATE)
    target = data
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return data


MAP_FILES = st.one_of(
    st.builds(_replaced, st.sampled_from(MAP_PATHS), JSON_VALUE).map(
        lambda d: json.dumps(d).encode()
    ),
    st.binary(max_size=200),
)


# ------------------------------------------------------------------ properties


@PROFILE
@given(data=rows(2))
def test_list_files(tmp_path: Path, data: bytes) -> None:
    path = _write(tmp_path, "rgb.txt", data)
    clean_or_success("fuzz: list file", lambda: read_list_file(path))


@PROFILE
@given(data=rows(8))
def test_trajectories(tmp_path: Path, data: bytes) -> None:
    path = _write(tmp_path, "trajectory.txt", data)
    clean_or_success("fuzz: TUM trajectory", lambda: read_tum(path))


@PROFILE
@given(data=yaml_text(CAMERA_MAPPING))
def test_camera_yaml(tmp_path: Path, data: bytes) -> None:
    path = _write(tmp_path, "camera.yaml", data)
    clean_or_success("fuzz: camera.yaml", lambda: load_camera_yaml(path))


@PROFILE
@given(data=yaml_text(CONFIG_MAPPING))
def test_config_files(tmp_path: Path, data: bytes) -> None:
    path = _write(tmp_path, "config.yaml", data)
    clean_or_success("fuzz: config file", lambda: explain_config(config=path))


@PROFILE
@given(key=st.sampled_from([*CONFIG_KEYS, "x.y"]), value=st.text(max_size=30))
def test_set_overrides(key: str, value: str) -> None:
    def resolve() -> None:
        resolve_layers(PlaneSlamConfig, [parse_override(f"{key}={value}", "--set")])

    clean_or_success("fuzz: --set", resolve)


@PROFILE
@given(data=MAP_FILES)
def test_map_json(tmp_path: Path, data: bytes) -> None:
    path = _write(tmp_path, "map.json", data)
    clean_or_success("fuzz: map.json", lambda: Map.load(path))


FRAME_RECORD = st.fixed_dictionaries(
    {},
    optional={
        "index": JSON_VALUE,
        "timestamp": JSON_VALUE,
        "path": st.one_of(st.sampled_from(["lost", "odometry", "first"]), JSON_VALUE),
        "keyframe": JSON_VALUE,
        "stage_ms": JSON_VALUE,
    },
)


@PROFILE
@given(
    data=st.one_of(
        st.lists(FRAME_RECORD.map(json.dumps), max_size=5).map(lambda r: "\n".join(r).encode()),
        st.binary(max_size=200),
    )
)
def test_frames_jsonl(tmp_path: Path, data: bytes) -> None:
    path = _write(tmp_path, "frames.jsonl", data)
    clean_or_success("fuzz: frames.jsonl", lambda: read_frame_records(path))


FLOATS = st.floats(allow_nan=True, allow_infinity=True)


@PROFILE
@given(
    k=st.lists(FLOATS, max_size=10),
    d=st.lists(FLOATS, max_size=9),
    width=st.integers(min_value=-(2**40), max_value=2**40),
    height=st.integers(min_value=-(2**40), max_value=2**40),
    model=st.sampled_from(["plumb_bob", "rational_polynomial", "equidistant", ""]),
)
def test_bag_camera_info(k, d, width, height, model) -> None:
    msg = SimpleNamespace(k=k, d=d, width=width, height=height, distortion_model=model)
    clean_or_success(
        "fuzz: camera_info", lambda: camera_from_info(msg, SMALL_CAMERA, "bag /camera_info")
    )
