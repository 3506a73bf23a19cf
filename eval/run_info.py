"""run.json: what a run was made from (dataset, backend, command line, version, date), so
that its outputs can be reported, replayed (`planeslam view`) and meshed (`planeslam
mesh`) without retyping the command."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from planeslam import __version__
from planeslam.core.bounded_parse import read_json_file
from planeslam.core.errors import EvaluationError
from planeslam.core.safe_files import resolve_path, write_text_atomic

RUN_JSON = "run.json"
SCHEMA = "planeslam.run/1"


@dataclass(frozen=True)
class RunInfo:
    """The run.json of a run folder."""

    dataset: str
    """Absolute path of the dataset folder the run read."""
    backend: str
    """'isam2' or 'merge'."""
    command: str = ""
    """The command line that made the run ('' when called from Python)."""
    version: str = __version__
    """planeslam version."""
    started_utc: str = ""
    """ISO 8601 start time, UTC."""

    @classmethod
    def now(cls, dataset: str | Path, backend: str, command: str = "") -> RunInfo:
        """A record of a run starting now on `dataset` (made absolute)."""
        started = datetime.now(timezone.utc).isoformat(timespec="seconds")
        return cls(str(resolve_path(dataset)), backend, command, __version__, started)

    @property
    def dataset_name(self) -> str:
        return Path(self.dataset).name


MAX_RUN_JSON_BYTES = 1 << 20
"""A run.json is a few hundred bytes; a larger one is not ours."""


def write_run_info(info: RunInfo, out_dir: str | Path) -> Path:
    """Write `out_dir`/run.json; returns its path."""
    text = json.dumps({"schema": SCHEMA, **asdict(info)}, indent=2) + "\n"
    return write_text_atomic(Path(out_dir) / RUN_JSON, text)


def read_run_info(run_dir: str | Path) -> RunInfo:
    """Read `run_dir`/run.json. EvaluationError naming the file when it is missing or not
    a planeslam.run/1 record."""
    path = Path(run_dir) / RUN_JSON
    if not path.is_file():
        raise EvaluationError(
            f"{path}: not found; is {Path(run_dir)} the output folder of `planeslam run`?"
        )
    data: Any = read_json_file(path, EvaluationError, MAX_RUN_JSON_BYTES, "run.json")
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        raise EvaluationError(f"{path}: expected a JSON object with schema '{SCHEMA}'")
    names = {f.name for f in fields(RunInfo)}
    missing = {"dataset", "backend"} - data.keys()
    if missing:
        raise EvaluationError(f"{path}: missing {', '.join(sorted(missing))}")
    values = {k: str(v) for k, v in data.items() if k in names}
    if "\x00" in values["dataset"]:  # no path holds one; os calls raise ValueError on it
        raise EvaluationError(f"{path}: dataset path holds a NUL character")
    return RunInfo(**values)
