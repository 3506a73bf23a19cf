"""Files as a contract: map.json and metrics.json of real runs validate against the JSON
Schemas shipped in the package; map.json carries the keyframes (final poses, frame
indices) and the frames that saw each plane; a file that breaks the contract fails."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from conftest import shared_sequence

from planeslam.app.runner import run_sequence
from planeslam.eval.metrics import read_metrics
from planeslam.io.trajectory import read_tum
from planeslam.mapping.world_map import Map
from planeslam.schemas import SCHEMAS, load_schema

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module", params=["isam2", "merge"])
def real_run(request, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`planeslam run` on TUM fr1/desk (9 frames), with each backend."""
    out = tmp_path_factory.mktemp(f"desk_{request.param}")
    run_sequence(shared_sequence("tum_fr1_desk_9f"), out, backend=request.param)
    return out


def test_schemas_are_shipped_and_valid():
    for name in SCHEMAS:
        jsonschema.Draft202012Validator.check_schema(load_schema(name))
    with pytest.raises(KeyError, match="expected one of map, metrics"):
        load_schema("frames")


@pytest.mark.data
def test_real_outputs_validate(real_run: Path):
    metrics = json.loads((real_run / "metrics.json").read_text())
    jsonschema.validate(metrics, load_schema("metrics"))
    assert metrics["schema"] == "planeslam.metrics/1"
    read_metrics(real_run / "metrics.json")  # and reads back
    data = json.loads((real_run / "map.json").read_text())
    jsonschema.validate(data, load_schema("map"))
    Map.load(real_run / "map.json")  # the extra keys do not stop a reload


@pytest.mark.data
def test_map_json_has_the_keyframes_and_the_frames_that_saw_each_plane(real_run: Path):
    data = json.loads((real_run / "map.json").read_text())
    metrics = json.loads((real_run / "metrics.json").read_text())
    keyframes = data["keyframes"]
    assert len(keyframes) == metrics["keyframes"] >= 2
    trajectory = read_tum(real_run / "trajectory.txt")
    for kf in keyframes:
        row = int(np.argmin(np.abs(trajectory.timestamps - kf["timestamp"])))
        assert abs(trajectory.timestamps[row] - kf["timestamp"]) < 1e-6
        T = np.array(kf["T_world_cam"])  # the final pose, as trajectory.txt has it
        np.testing.assert_allclose(T, trajectory.T_world_cam[row], atol=1e-4)
    merged = {kf["merge"]: kf["index"] for kf in keyframes}
    for plane in data["planes"]:
        assert plane["seen_in_frames"] == sorted(merged[m] for m in plane["seen_in"])


def test_a_file_breaking_the_contract_fails():
    schema = load_schema("map")
    minimal = {
        "schema": "planeslam.map/1",
        "frame": "world",
        "gravity_up": None,
        "gravity_source": "",
        "frames_merged": 0,
        "next_plane_id": 0,
        "next_corner_id": 0,
        "config": {"map": {}, "objects": {}},
        "planes": [],
        "edges": [],
        "corners": [],
        "objects": [],
        "sparse_cloud": {},
    }
    jsonschema.validate(Map().to_dict(), schema)
    jsonschema.validate(minimal, schema)
    for key, value in (("frame", "camera"), ("planes", [{"id": 0}]), ("schema", "x/2")):
        broken = copy.deepcopy(minimal)
        broken[key] = value
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(broken, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**minimal, "keyframes": [{"index": 0}]}, schema)
