"""JSON Schemas (draft 2020-12) of the files a run writes, shipped with the package:
`map.schema.json` (map.json, 'planeslam.map/1') and `metrics.schema.json` (metrics.json,
'planeslam.metrics/1'). Validate with any JSON Schema validator, e.g.
`jsonschema.validate(data, load_schema("map"))`."""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

SCHEMAS = ("map", "metrics")
"""Names of the shipped schemas."""


def load_schema(name: str) -> dict[str, Any]:
    """The JSON Schema of `name` ('map' or 'metrics') as a dict; KeyError naming the valid
    names for another."""
    if name not in SCHEMAS:
        raise KeyError(f"schema {name!r}: expected one of {', '.join(SCHEMAS)}")
    text = resources.files(__package__).joinpath(f"{name}.schema.json").read_text("utf-8")
    data: dict[str, Any] = json.loads(text)
    return data
