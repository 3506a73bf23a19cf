"""Object size errors: estimated plane-based objects against a synthetic scene's truth.json."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from planeslam.core.bounded_parse import read_json_file
from planeslam.core.errors import EvaluationError

log = logging.getLogger(__name__)


def _sizes(obj: Mapping[str, Any], source: str) -> np.ndarray:
    """(K,) object sizes [m], largest first."""
    try:
        size = np.asarray(obj["size_m"], dtype=np.float64).ravel()
        cls = obj["class"]
    except (KeyError, TypeError, ValueError):
        raise EvaluationError(
            f"{source}: object {obj.get('id', '?') if isinstance(obj, Mapping) else obj!r} "
            "needs 'class' and a list of numbers 'size_m'"
        ) from None
    if size.size == 0 or not np.all(np.isfinite(size)) or not isinstance(cls, str):
        raise EvaluationError(
            f"{source}: object {obj.get('id', '?')} has an invalid class or size_m"
        )
    return np.sort(size)[::-1]


def _size_cost(est: np.ndarray, true: np.ndarray) -> float:
    k = min(est.size, true.size)
    return float(np.mean(np.abs(est[:k] - true[:k])))


def object_size_errors(
    estimated_objects: Sequence[Mapping[str, Any]],
    truth: Mapping[str, Any],
    truth_source: str = "truth",
    map_source: str = "estimated map",
) -> list[dict[str, Any]]:
    """Size error of each true object against its matched estimated object [m].

    `estimated_objects` are map objects ({"id", "class", "planes", "size_m"}), `truth` is the
    parsed truth.json with an "objects" list ({"id", "class", "size_m", ...}). Within each
    class, true objects are matched one-to-one to estimated ones by the Hungarian method on
    the mean absolute difference of their common leading (largest-first) dimensions.
    Returns one dict per true object, in truth order: class, true_id, estimated_id,
    true_size_m, estimated_size_m, abs_error_m (per common dimension), mean_abs_error_m;
    a true object with no estimate of its class has None for the estimated fields.
    EvaluationError naming `truth_source` / `map_source` for malformed content.
    """
    if not isinstance(truth, Mapping) or not isinstance(truth.get("objects"), list):
        raise EvaluationError(f"{truth_source}: expected a mapping with an 'objects' list")
    true_objs = list(truth["objects"])
    true_sizes = [_sizes(o, truth_source) for o in true_objs]
    est_sizes = [_sizes(o, map_source) for o in estimated_objects]
    matches: dict[int, int] = {}
    for cls in sorted({o["class"] for o in true_objs}):
        ti = [i for i, o in enumerate(true_objs) if o["class"] == cls]
        ei = [j for j, o in enumerate(estimated_objects) if o["class"] == cls]
        if not ei:
            continue
        cost = np.array([[_size_cost(est_sizes[j], true_sizes[i]) for j in ei] for i in ti])
        rows, cols = linear_sum_assignment(cost)
        matches.update({ti[r]: ei[c] for r, c in zip(rows, cols, strict=True)})

    results: list[dict[str, Any]] = []
    for i, obj in enumerate(true_objs):
        entry: dict[str, Any] = {
            "class": obj["class"],
            "true_id": obj.get("id"),
            "estimated_id": None,
            "true_size_m": true_sizes[i].tolist(),
            "estimated_size_m": None,
            "abs_error_m": None,
            "mean_abs_error_m": None,
        }
        if i in matches:
            est = estimated_objects[matches[i]]
            k = min(est_sizes[matches[i]].size, true_sizes[i].size)
            err = np.abs(est_sizes[matches[i]][:k] - true_sizes[i][:k])
            entry.update(
                estimated_id=est.get("id"),
                estimated_size_m=est_sizes[matches[i]].tolist(),
                abs_error_m=err.tolist(),
                mean_abs_error_m=float(err.mean()),
            )
        else:
            log.info("no estimated %s object for true object %s", obj["class"], obj.get("id"))
        results.append(entry)
    return results


def mean_object_size_error(errors: Sequence[Mapping[str, Any]]) -> float | None:
    """Mean of `mean_abs_error_m` over the matched objects [m]; None when none matched."""
    values = [e["mean_abs_error_m"] for e in errors if e.get("mean_abs_error_m") is not None]
    return float(np.mean(values)) if values else None


def read_json(path: Path, what: str = "file") -> Any:
    """Parse a JSON file, or raise an EvaluationError naming it and what it should be."""
    return read_json_file(path, EvaluationError, what=what)


def object_size_errors_from_files(
    map_json: str | Path, truth_json: str | Path
) -> list[dict[str, Any]]:
    """`object_size_errors` for a map JSON file (with an 'objects' list) and a truth.json."""
    map_data = read_json(Path(map_json), "map file")
    objects = map_data.get("objects") if isinstance(map_data, Mapping) else None
    if not isinstance(objects, list):
        raise EvaluationError(f"{map_json}: expected a JSON object with an 'objects' list")
    truth = read_json(Path(truth_json), "truth file")
    return object_size_errors(objects, truth, str(truth_json), str(map_json))
