"""The requested layout installs as one package: planeslam.factors and planeslam.eval
come from the top-level factors/ and eval/ folders, in an editable install and a wheel."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration  # builds and installs a wheel

REPO = Path(__file__).resolve().parents[1]
PROBE = (
    "import planeslam, planeslam.factors, planeslam.eval, planeslam.configs, pathlib;"
    "print(pathlib.Path(planeslam.factors.__file__).parent.name,"
    " pathlib.Path(planeslam.eval.__file__).parent.name,"
    " pathlib.Path(planeslam.__file__).resolve())"
)


def test_editable_install_imports_from_any_directory(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=tmp_path, capture_output=True, text=True, check=True
    ).stdout.split()
    assert out[:2] == ["factors", "eval"]
    assert Path(out[2]).is_relative_to(REPO)


@pytest.mark.slow
def test_wheel_contains_and_imports_the_subpackages(tmp_path: Path) -> None:
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(tmp_path),
            str(REPO),
        ],
        check=True,
        capture_output=True,
    )
    (wheel,) = tmp_path.glob("planeslam-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for required in (
        "planeslam/factors/__init__.py",
        "planeslam/eval/__init__.py",
        "planeslam/configs/tum_fr1.yaml",
        "planeslam/configs/sevenscenes.yaml",
        "planeslam/schemas/map.schema.json",
        "planeslam/schemas/metrics.schema.json",
    ):
        assert required in names
    for package in (REPO / "planeslam").rglob("__init__.py"):  # every sub-package listed
        assert package.relative_to(REPO).as_posix() in names
    assert not any(n.startswith(("factors/", "eval/", "tests/")) for n in names)
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}
    out = subprocess.run(
        [sys.executable, "-c", PROBE],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert out[:2] == ["factors", "eval"]
    assert Path(out[2]).is_relative_to(site)
