"""`planeslam download tum`: a small TUM-style archive served from a loopback HTTP server
(127.0.0.1 only) is downloaded, checked, unpacked and given its camera.yaml; a broken-off
transfer resumes, a truncated archive and a 404 give one-line errors."""

from __future__ import annotations

import http.server
import io
import re
import tarfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest

from planeslam.app.cli import main
from planeslam.app.download import download_tum_sequence
from planeslam.config import load_camera_yaml, load_config, resolve_config
from planeslam.core.errors import DatasetFormatError, DownloadError
from planeslam.io.sequence import open_dataset
from planeslam.io.tum_download import TUM_SEQUENCES, download_tum, tum_sequence

pytestmark = pytest.mark.unit

FOLDER = "rgbd_dataset_freiburg1_xyz"
ARCHIVE_PATH = f"/freiburg1/{FOLDER}.tgz"


@pytest.fixture(scope="module")
def archive(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A TUM-layout folder of two 640x480 frames, as a .tgz (gzip level 1, so that its
    bytes are not all in the first few kilobytes)."""
    root = tmp_path_factory.mktemp("src") / FOLDER
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(7)
    lines_rgb, lines_depth, lines_gt = [], [], []
    for k, t in enumerate((1305031102.1758, 1305031102.2058)):
        name = f"{t:.4f}.png"
        cv2.imwrite(str(root / "rgb" / name), rng.integers(0, 255, (480, 640, 3), dtype=np.uint8))
        depth = np.full((480, 640), 5000 + 100 * k, dtype=np.uint16)
        cv2.imwrite(str(root / "depth" / name), depth)
        lines_rgb.append(f"{t:.4f} rgb/{name}")
        lines_depth.append(f"{t:.4f} depth/{name}")
        lines_gt.append(f"{t:.4f} 0 0 {0.01 * k} 0 0 0 1")
    (root / "rgb.txt").write_text("# color images\n" + "\n".join(lines_rgb) + "\n")
    (root / "depth.txt").write_text("# depth maps\n" + "\n".join(lines_depth) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(lines_gt) + "\n")
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=1) as tar:
        tar.add(root, arcname=FOLDER)
    return buffer.getvalue()


@dataclass
class Served:
    """What the loopback server holds and saw."""

    files: dict[str, bytes] = field(default_factory=dict)
    drop_after: int | None = None
    """Break the next response off after this many body bytes (then serve normally)."""
    honour_range: bool = True
    requests: list[tuple[str, str | None]] = field(default_factory=list)
    """(path, Range header) of every GET."""


def _handler(served: Served) -> type[http.server.BaseHTTPRequestHandler]:
    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - the http.server API
            served.requests.append((self.path, self.headers.get("Range")))
            body = served.files.get(self.path)
            if body is None:
                self.send_error(404, "Not Found")
                return
            start = 0
            match = re.fullmatch(r"bytes=(\d+)-", self.headers.get("Range") or "")
            if match and served.honour_range:
                start = int(match[1])
                if start >= len(body):
                    self.send_response(416)
                    self.send_header("Content-Range", f"bytes */{len(body)}")
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                self.send_response(206)
                self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
            else:
                self.send_response(200)
            self.send_header("Content-Length", str(len(body) - start))
            self.end_headers()
            chunk = body[start:]
            if served.drop_after is not None:
                chunk, served.drop_after = chunk[: served.drop_after], None
                self.wfile.write(chunk)
                self.wfile.flush()
                self.close_connection = True
                return
            self.wfile.write(chunk)

        def log_message(self, *args: object) -> None:
            pass

    return Handler


@pytest.fixture
def server() -> Iterator[tuple[str, Served]]:
    served = Served()
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _handler(served))
    thread = threading.Thread(target=httpd.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", served
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_names_and_urls() -> None:
    seq = tum_sequence("fr3/structure_texture_far")
    assert seq.folder == "rgbd_dataset_freiburg3_structure_texture_far"
    assert seq.preset == "tum_fr3"
    assert seq.url("https://example.org/rgbd/dataset/") == (
        "https://example.org/rgbd/dataset/freiburg3/rgbd_dataset_freiburg3_structure_texture_far.tgz"
    )
    for alias in ("freiburg1_desk", "rgbd_dataset_freiburg1_desk", "FR1_desk", "fr1/desk"):
        assert tum_sequence(alias).name == "fr1/desk"
    with pytest.raises(DatasetFormatError, match="did you mean fr1/desk"):
        tum_sequence("fr1/dsk")
    assert len(TUM_SEQUENCES) == len(set(TUM_SEQUENCES))
    assert all(re.fullmatch(r"fr[123]/[a-z0-9_]+", name) for name in TUM_SEQUENCES)


def test_download_unpacks_and_records_the_preset(
    server: tuple[str, Served], archive: bytes, tmp_path: Path
) -> None:
    url, served = server
    served.files[ARCHIVE_PATH] = archive
    seen: list[tuple[int, int | None]] = []
    done = download_tum_sequence("fr1/xyz", tmp_path / "data", base_url=url)
    folder = tmp_path / "data" / FOLDER
    assert done.result.folder == folder and done.result.downloaded_bytes == len(archive)
    assert not (tmp_path / "data" / f"{FOLDER}.tgz").exists()  # deleted after unpacking
    assert [p.name for p in (tmp_path / "data").iterdir()] == [FOLDER]  # no staging left
    # camera.yaml holds fr1's calibration, and it is what the config resolution reads
    assert load_camera_yaml(folder / "camera.yaml") == load_config("tum_fr1").camera
    renamed = folder.rename(tmp_path / "data" / "my_sequence")  # no preset in the name
    cfg = resolve_config(renamed)
    assert cfg.camera == load_config("tum_fr1").camera
    dataset = open_dataset(renamed, cfg.camera, cfg.dataset)
    assert len(dataset) == 2 and dataset.groundtruth is not None
    assert float(np.median(dataset[1].depth_m)) == pytest.approx(1.02)
    # progress goes to the callback, ending at the total
    result = download_tum(
        "fr1/xyz", tmp_path / "again", url, lambda done, total: seen.append((done, total))
    )
    assert result.resumed_from == 0 and seen[-1] == (len(archive), len(archive))
    assert [d for d, _ in seen] == sorted(d for d, _ in seen)
    # already there: no request
    before = len(served.requests)
    assert download_tum("fr1/xyz", tmp_path / "again", url).already_present
    assert len(served.requests) == before


def test_broken_off_transfer_resumes(
    server: tuple[str, Served], archive: bytes, tmp_path: Path
) -> None:
    url, served = server
    served.files[ARCHIVE_PATH] = archive
    half = len(archive) // 2
    served.drop_after = half
    part = tmp_path / f"{FOLDER}.tgz.part"
    with pytest.raises(DownloadError, match=f"broke off after {half} bytes of {len(archive)}"):
        download_tum("fr1/xyz", tmp_path, url)
    assert part.stat().st_size == half  # kept for the next call
    result = download_tum("fr1/xyz", tmp_path, url)
    assert served.requests[-1] == (ARCHIVE_PATH, f"bytes={half}-")
    assert result.resumed_from == half and result.downloaded_bytes == len(archive) - half
    assert (tmp_path / FOLDER / "rgb.txt").is_file() and not part.exists()


def test_complete_part_and_a_server_without_ranges(
    server: tuple[str, Served], archive: bytes, tmp_path: Path
) -> None:
    url, served = server
    served.files[ARCHIVE_PATH] = archive
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / f"{FOLDER}.tgz.part").write_bytes(archive)  # complete: the server says 416
    assert download_tum("fr1/xyz", tmp_path / "a", url).downloaded_bytes == 0
    assert (tmp_path / "a" / FOLDER / "depth.txt").is_file()
    served.honour_range = False  # sends the whole file again: the part is replaced
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / f"{FOLDER}.tgz.part").write_bytes(b"garbage")
    result = download_tum("fr1/xyz", tmp_path / "b", url)
    assert result.resumed_from == 0 and result.downloaded_bytes == len(archive)
    assert (tmp_path / "b" / FOLDER / "depth.txt").is_file()


def test_truncated_archive_is_reported_and_deleted(
    server: tuple[str, Served], archive: bytes, tmp_path: Path
) -> None:
    url, served = server
    served.files[ARCHIVE_PATH] = archive[:-4000]  # served whole, but cut
    with pytest.raises(DatasetFormatError, match="truncated or corrupt archive") as info:
        download_tum("fr1/xyz", tmp_path / "data", url)
    assert f"{FOLDER}.tgz" in str(info.value) and "\n" not in str(info.value)
    assert list((tmp_path / "data").iterdir()) == []  # nothing unpacked, archive deleted


def test_foreign_archive_is_refused(server: tuple[str, Served], tmp_path: Path) -> None:
    url, served = server
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        info = tarfile.TarInfo("../evil.txt")
        tar.addfile(info, io.BytesIO(b""))
    served.files[ARCHIVE_PATH] = buffer.getvalue()
    with pytest.raises(DatasetFormatError, match="lies outside rgbd_dataset_freiburg1_xyz/"):
        download_tum("fr1/xyz", tmp_path, url)
    assert not (tmp_path.parent / "evil.txt").exists()


def test_404_names_the_url(server: tuple[str, Served], tmp_path: Path) -> None:
    url, _ = server
    with pytest.raises(DownloadError, match=r"freiburg2/rgbd_dataset_freiburg2_desk.tgz: HTTP 404"):
        download_tum("fr2/desk", tmp_path, url)
    assert not any(tmp_path.iterdir())


def test_cli(
    server: tuple[str, Served], archive: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url, served = server
    served.files[ARCHIVE_PATH] = archive
    assert main(["download", "tum", "--list"]) == 0
    listed = capsys.readouterr().out.split()
    assert "fr3/structure_texture_far" in listed and len(listed) == len(TUM_SEQUENCES)
    argv = ["-q", "download", "tum", "fr1/xyz", "--dir", str(tmp_path / "d"), "--base-url", url]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"planeslam run {tmp_path / 'd' / FOLDER}" in out and "tum_fr1" in out
    assert main(["download", "tum", "fr2/desk", "--dir", str(tmp_path), "--base-url", url]) == 2
    assert "HTTP 404" in capsys.readouterr().err


def test_a_part_file_planted_as_a_link_is_not_written_through(
    server: tuple[str, Served], archive: bytes, tmp_path: Path
) -> None:
    """`open(part, 'ab')` followed a link planted at the .part name and appended the
    archive to whatever file it named."""
    url, served = server
    served.files[ARCHIVE_PATH] = archive
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / f"{FOLDER}.tgz.part").symlink_to(victim)
    with pytest.raises(OSError, match="symbolic link"):
        download_tum("fr1/xyz", tmp_path / "data", url)
    assert victim.read_text() == "precious\n"
