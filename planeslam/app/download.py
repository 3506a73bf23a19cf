"""`planeslam download tum NAME [--dir DIR]`: a TUM RGB-D sequence from the benchmark's
site, unpacked and ready for `planeslam run`, its camera's calibration recorded in the
folder's camera.yaml (`--list` lists the sequences)."""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

import yaml

from planeslam.app.progress import byte_progress
from planeslam.app.subcommand import add_command
from planeslam.config import load_config
from planeslam.core.config import to_mapping
from planeslam.core.errors import ConfigError
from planeslam.core.safe_files import write_text_atomic
from planeslam.io.tum_download import (
    TUM_BASE_URL,
    TUM_SEQUENCES,
    DownloadResult,
    download_tum,
)

BASE_URL_ENV = "PLANESLAM_TUM_URL"
"""Environment variable overriding TUM's base URL (a mirror); `--base-url` wins over it."""


@dataclass(frozen=True)
class TumDownload:
    """What `download_tum_sequence` did."""

    result: DownloadResult
    camera_yaml: Path
    """The folder's camera.yaml with its camera's calibration (the preset's camera)."""

    def text(self) -> str:
        r = self.result
        if r.already_present:
            what = f"{r.sequence.name} already in {r.folder}"
        else:
            resumed = f", resumed at {r.resumed_from} bytes" if r.resumed_from else ""
            what = (
                f"{r.sequence.name}: {r.downloaded_bytes / 1e6:.1f} MB downloaded{resumed}, "
                f"unpacked into {r.folder}"
            )
        return (
            f"{what}\ncalibration of preset {r.sequence.preset} in {self.camera_yaml}\n"
            f"run it: planeslam run {r.folder}"
        )


def write_camera_yaml(result: DownloadResult) -> Path:
    """Record the sequence's camera calibration (its preset's camera section) in the
    folder's camera.yaml, which `resolve_config` reads whatever the folder is called.
    An existing camera.yaml is left as it is."""
    path = result.folder / "camera.yaml"
    if not os.path.lexists(path):  # a link there (even dangling) is not written through
        preset = result.sequence.preset
        camera = to_mapping(load_config(preset).camera)
        header = (
            f"# TUM RGB-D {result.sequence.name}: the calibration of preset {preset},\n"
            f"# written by `planeslam download`.\n"
        )
        write_text_atomic(path, header + yaml.safe_dump(camera, sort_keys=False))
    return path


def download_tum_sequence(
    name: str,
    dest_dir: str | Path = ".",
    base_url: str | None = None,
    progress: bool = False,
    keep_archive: bool = False,
) -> TumDownload:
    """Download, check and unpack TUM sequence `name` into `dest_dir` (see
    `planeslam.io.tum_download.download_tum`) and record its calibration in camera.yaml.
    `base_url` defaults to $PLANESLAM_TUM_URL, else TUM's site."""
    url = base_url or os.environ.get(BASE_URL_ENV) or TUM_BASE_URL
    with byte_progress(f"download {name}", enabled=progress) as on_progress:
        result = download_tum(name, dest_dir, url, on_progress, keep_archive)
    return TumDownload(result=result, camera_yaml=write_camera_yaml(result))


def tum_sequence_list() -> str:
    """The short names, one per line."""
    return "\n".join(TUM_SEQUENCES)


def add_download_command(sub: argparse._SubParsersAction) -> None:
    """The `download` sub-command (sources: `tum`)."""

    p = add_command(
        sub,
        "download",
        help="download a public dataset sequence (TUM RGB-D)",
        description="Download a dataset sequence, check it and unpack it into a folder that "
        "`planeslam run` reads.",
    )
    source = p.add_subparsers(dest="source", metavar="SOURCE", required=True)
    t = add_command(
        source,
        "tum",
        help="a TUM RGB-D sequence by its short name (fr1/desk, fr3/structure_texture_far)",
        description="Download the official archive of a TUM RGB-D sequence, resuming a partial "
        "download, check it, unpack it into DIR/rgbd_dataset_freiburgK_NAME and write the "
        "camera's calibration (preset tum_frK) into its camera.yaml.",
    )
    t.add_argument("name", nargs="?", default=None, help="short name, e.g. fr1/desk")
    t.add_argument("--list", action="store_true", help="list the sequences and exit")
    t.add_argument("--dir", type=Path, default=Path("."), help="where to unpack (default .)")
    t.add_argument(
        "--base-url",
        default=None,
        help=f"where the archives are (default ${BASE_URL_ENV}, else {TUM_BASE_URL})",
    )
    t.add_argument("--keep-archive", action="store_true", help="keep the .tgz after unpacking")
    t.set_defaults(func=_cmd_download_tum)


def _cmd_download_tum(args: argparse.Namespace) -> int:
    if args.list:
        print(tum_sequence_list())
        return 0
    if args.name is None:
        raise ConfigError("download tum: give a sequence name such as fr1/desk (--list lists them)")
    done = download_tum_sequence(
        args.name, args.dir, args.base_url, progress=not args.quiet, keep_archive=args.keep_archive
    )
    print(done.text())
    return 0
