"""TUM RGB-D sequences from the benchmark's site: the catalogue of short names, and the
download of one sequence's archive (resumed when a partial file is there), its check and
its unpacking into a TUM-layout folder.

The archive of `fr1/desk` is `<base>/freiburg1/rgbd_dataset_freiburg1_desk.tgz`; it holds
one folder `rgbd_dataset_freiburg1_desk/` with rgb.txt, depth.txt, groundtruth.txt, rgb/
and depth/. A download goes to `<name>.tgz.part` first, is renamed when complete (its
length equal to what the server announced), and is then read through once: a gzip stream
that ends early or fails its CRC, a member outside the sequence's folder or a missing
list file is an error, and nothing is unpacked. Unpacking goes to a hidden folder that is
renamed at the end, so an interrupted unpack never looks like a sequence.
"""

from __future__ import annotations

import difflib
import http.client
import logging
import os
import re
import shutil
import tarfile
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from planeslam.core.errors import DatasetFormatError, DownloadError
from planeslam.core.safe_files import open_output, regular_file_size

log = logging.getLogger(__name__)

TUM_BASE_URL = "https://cvg.cit.tum.de/rgbd/dataset"
"""Where TUM serves the archives (`<base>/freiburg<k>/<folder>.tgz`)."""

TUM_SEQUENCES = (
    # Testing and debugging
    "fr1/xyz",
    "fr1/rpy",
    "fr2/xyz",
    "fr2/rpy",
    # Handheld SLAM
    "fr1/360",
    "fr1/floor",
    "fr1/desk",
    "fr1/desk2",
    "fr1/room",
    "fr2/360_hemisphere",
    "fr2/360_kidnap",
    "fr2/desk",
    "fr2/large_no_loop",
    "fr2/large_with_loop",
    "fr3/long_office_household",
    # Robot SLAM
    "fr2/pioneer_360",
    "fr2/pioneer_slam",
    "fr2/pioneer_slam2",
    "fr2/pioneer_slam3",
    # Structure vs. texture
    "fr3/nostructure_notexture_far",
    "fr3/nostructure_notexture_near_withloop",
    "fr3/nostructure_texture_far",
    "fr3/nostructure_texture_near_withloop",
    "fr3/structure_notexture_far",
    "fr3/structure_notexture_near",
    "fr3/structure_texture_far",
    "fr3/structure_texture_near",
    # Dynamic objects
    "fr2/desk_with_person",
    "fr3/sitting_static",
    "fr3/sitting_xyz",
    "fr3/sitting_halfsphere",
    "fr3/sitting_rpy",
    "fr3/walking_static",
    "fr3/walking_xyz",
    "fr3/walking_halfsphere",
    "fr3/walking_rpy",
    # 3-D object reconstruction
    "fr1/plant",
    "fr1/teddy",
    "fr2/coke",
    "fr2/dishes",
    "fr2/flowerbouquet",
    "fr2/flowerbouquet_brownbackground",
    "fr2/metallic_sphere",
    "fr2/metallic_sphere2",
    "fr3/cabinet",
    "fr3/large_cabinet",
    "fr3/teddy",
)
"""Short names of the TUM RGB-D sequences with public ground truth, grouped as on TUM's
download page."""

LIST_FILES = ("rgb.txt", "depth.txt")
"""Files every sequence folder has (groundtruth.txt too, except the validation sequences)."""

CHUNK_BYTES = 1 << 20

ProgressCallback = Callable[[int, int | None], None]
"""on_progress(bytes so far, total bytes or None when the server does not say)."""


@dataclass(frozen=True)
class TumSequence:
    """One TUM RGB-D sequence."""

    name: str
    """Short name, 'fr1/desk'."""

    @property
    def camera(self) -> int:
        """Which Kinect recorded it: 1, 2 or 3 (freiburg1 ...), which sets its calibration."""
        return int(self.name[2])

    @property
    def folder(self) -> str:
        """The folder its archive unpacks to: 'rgbd_dataset_freiburg1_desk'."""
        return f"rgbd_dataset_freiburg{self.camera}_{self.name.split('/', 1)[1]}"

    @property
    def preset(self) -> str:
        """The config preset with its camera's calibration: 'tum_fr1'."""
        return f"tum_fr{self.camera}"

    def url(self, base_url: str = TUM_BASE_URL) -> str:
        """Where its archive is: `<base_url>/freiburg1/rgbd_dataset_freiburg1_desk.tgz`."""
        return f"{base_url.rstrip('/')}/freiburg{self.camera}/{self.folder}.tgz"


def tum_sequence(name: str) -> TumSequence:
    """The sequence called `name`: 'fr1/desk', 'fr1_desk', 'freiburg1_desk' or the folder
    name 'rgbd_dataset_freiburg1_desk'. DatasetFormatError for an unknown name, listing
    the closest known ones."""
    text = name.strip().lower().removeprefix("rgbd_dataset_")
    match = re.fullmatch(r"(?:fr|freiburg)([123])[/_](.+)", text)
    short = f"fr{match.group(1)}/{match.group(2)}" if match else text
    if short in TUM_SEQUENCES:
        return TumSequence(short)
    close = difflib.get_close_matches(short, TUM_SEQUENCES, n=3, cutoff=0.7)
    hint = f"; did you mean {', '.join(close)}?" if close else ""
    raise DatasetFormatError(
        f"unknown TUM RGB-D sequence {name!r}{hint} (expected a short name such as fr1/desk; "
        f"{len(TUM_SEQUENCES)} sequences, listed with --list)"
    )


@dataclass(frozen=True)
class DownloadResult:
    """What `download_tum` did."""

    sequence: TumSequence
    folder: Path
    """The unpacked TUM-layout folder."""
    downloaded_bytes: int
    """Bytes fetched by this call (0 when the folder was already there)."""
    resumed_from: int
    """Bytes of a partial download that this call continued (0: started afresh)."""
    already_present: bool
    """The folder existed with its list files: nothing was fetched or unpacked."""


def _content_total(response: object, offset: int) -> int | None:
    """Total size of the file [bytes] from a response's Content-Range or Content-Length."""
    headers = response.headers  # type: ignore[attr-defined]
    content_range = headers.get("Content-Range", "")
    match = re.fullmatch(r"bytes (?:\d+-\d+|\*)/(\d+)", content_range.strip())
    if match:  # 'bytes 100-199/200' of a 206, 'bytes */200' of a 416
        return int(match.group(1))
    length = headers.get("Content-Length")
    return offset + int(length) if length is not None and length.isdigit() else None


def download_file(
    url: str,
    dest: Path,
    on_progress: ProgressCallback | None = None,
    timeout_s: float = 60.0,
) -> tuple[int, int]:
    """Fetch `url` into `dest`, continuing `dest + '.part'` when it exists (HTTP Range);
    returns (bytes fetched now, bytes resumed from). The part file is kept when the
    transfer breaks off, so that calling again continues it. DownloadError naming the URL
    for an HTTP error, an unreachable server or a transfer that ends early."""
    part = dest.with_name(dest.name + ".part")
    offset = regular_file_size(part) or 0  # a link planted there is not continued
    request = urllib.request.Request(url, headers={"User-Agent": "planeslam"})
    if offset:
        request.add_header("Range", f"bytes={offset}-")
    try:
        response = urllib.request.urlopen(request, timeout=timeout_s)  # noqa: S310 - http(s) only
    except urllib.error.HTTPError as exc:
        if exc.code == 416 and offset:  # nothing left to fetch: the part may be complete
            total = _content_total(exc, 0)
            if total == offset:
                os.replace(part, dest)
                return 0, offset
            log.info("%s: the server refused to resume at %d bytes; starting again", url, offset)
            part.unlink()
            return download_file(url, dest, on_progress, timeout_s)
        raise DownloadError(f"{url}: HTTP {exc.code} {exc.reason}") from None
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise DownloadError(f"{url}: cannot download ({reason})") from None
    with response:
        if offset and response.status != 206:  # the server ignored the range: start again
            log.info("%s: the server does not resume downloads; starting again", url)
            offset = 0
        resumed_at = re.match(r"bytes (\d+)-", response.headers.get("Content-Range", ""))
        if offset and not (resumed_at and int(resumed_at[1]) == offset):
            raise DownloadError(
                f"{url}: asked to resume at byte {offset}, the server sent "
                f"{response.headers.get('Content-Range')!r}; delete {part} to start again"
            )
        total = _content_total(response, offset)
        fetched = 0
        broken: Exception | None = None
        with open_output(part, append=bool(offset)) as fh:  # never through a link
            if on_progress is not None:
                on_progress(offset, total)
            while broken is None:
                try:
                    chunk = response.read(CHUNK_BYTES)
                except (OSError, ValueError, http.client.HTTPException) as exc:  # reset, cut
                    chunk, broken = b"", exc
                if not chunk:
                    break
                fh.write(chunk)
                fetched += len(chunk)
                if on_progress is not None:
                    on_progress(offset + fetched, total)
    size = regular_file_size(part) or 0
    if broken is not None or (total is not None and size != total):
        expected = f"of {total} " if total is not None else ""
        raise DownloadError(
            f"{url}: transfer broke off after {size} bytes {expected}({broken or 'early end'}); "
            f"{part} is kept and the same command resumes it"
        )
    os.replace(part, dest)
    return fetched, offset


def check_archive(archive: Path, folder: str) -> list[tarfile.TarInfo]:
    """The members of TUM archive `archive`, read through once (gzip CRC included).
    DatasetFormatError naming the archive when it is truncated or corrupt, when a member
    lies outside `folder/` or is not a plain file or folder, or when the list files are
    missing."""
    try:
        with tarfile.open(archive, "r:gz") as tar:
            members = []
            for member in tar:
                members.append(member)
                if member.isfile():  # read the data: a truncated stream fails here
                    extracted = tar.extractfile(member)
                    assert extracted is not None
                    while extracted.read(CHUNK_BYTES):
                        pass
    except (tarfile.TarError, EOFError, OSError, ValueError) as exc:
        raise DatasetFormatError(
            f"{archive}: truncated or corrupt archive ({exc or type(exc).__name__})"
        ) from None
    names = set()
    for member in members:
        path = Path(member.name)
        if path.is_absolute() or ".." in path.parts or path.parts[:1] != (folder,):
            raise DatasetFormatError(
                f"{archive}: member {member.name!r} lies outside {folder}/ (not a TUM archive?)"
            )
        if not (member.isfile() or member.isdir()):
            raise DatasetFormatError(f"{archive}: member {member.name!r} is not a file or folder")
        names.add(member.name)
    missing = [f"{folder}/{name}" for name in LIST_FILES if f"{folder}/{name}" not in names]
    if missing:
        raise DatasetFormatError(f"{archive}: {', '.join(missing)} missing (not a TUM archive?)")
    return members


def unpack_archive(archive: Path, folder: str, dest_dir: Path) -> Path:
    """Unpack the checked TUM archive into `dest_dir/folder` through a hidden folder
    renamed at the end; returns the folder."""
    staging = dest_dir / f".{folder}.unpacking"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    with tarfile.open(archive, "r:gz") as tar:
        if hasattr(tarfile, "data_filter"):
            tar.extractall(staging, filter="data")
        else:  # Python < 3.10.12: the members were checked by `check_archive`
            tar.extractall(staging)  # noqa: S202
    target = dest_dir / folder
    os.replace(staging / folder, target)
    shutil.rmtree(staging)
    return target


def is_sequence_folder(path: Path) -> bool:
    """Whether `path` holds an unpacked sequence (its list files)."""
    return all((path / name).is_file() for name in LIST_FILES)


def download_tum(
    name: str,
    dest_dir: str | Path,
    base_url: str = TUM_BASE_URL,
    on_progress: ProgressCallback | None = None,
    keep_archive: bool = False,
) -> DownloadResult:
    """Download, check and unpack TUM RGB-D sequence `name` ('fr1/desk') into
    `dest_dir/<folder>`; nothing is fetched when that folder is already there. A partial
    download (`<folder>.tgz.part` in `dest_dir`) is resumed. A truncated or corrupt archive
    is deleted (DatasetFormatError): the next call fetches it afresh. The archive is
    deleted after unpacking unless `keep_archive`."""
    sequence = tum_sequence(name)
    dest = Path(dest_dir)
    target = dest / sequence.folder
    if is_sequence_folder(target):
        log.info("%s is already in %s", sequence.name, target)
        return DownloadResult(sequence, target, 0, 0, already_present=True)
    if target.exists():
        raise DatasetFormatError(
            f"{target}: exists but is not a TUM sequence folder (no rgb.txt / depth.txt); "
            f"move it away to download {sequence.name} there"
        )
    dest.mkdir(parents=True, exist_ok=True)
    archive = dest / f"{sequence.folder}.tgz"
    fetched, resumed = 0, 0
    if not archive.is_file():
        url = sequence.url(base_url)
        log.info("downloading %s from %s", sequence.name, url)
        fetched, resumed = download_file(url, archive, on_progress)
    try:
        check_archive(archive, sequence.folder)
    except DatasetFormatError as exc:
        archive.unlink()
        raise DatasetFormatError(
            f"{exc}; deleted it: the next download fetches it afresh"
        ) from None
    folder = unpack_archive(archive, sequence.folder, dest)
    if not keep_archive:
        archive.unlink()
    return DownloadResult(sequence, folder, fetched, resumed, already_present=False)
