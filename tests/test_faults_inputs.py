"""Fault corpus, inputs: bad images, depth in a wrong unit, bad colour images, bad
timestamps, malformed camera.yaml, configs and ground truth. Each case gives the exact
clean error or documented outcome; the tally is printed at the end of the session."""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from planeslam.config import load_config, resolve_config
from planeslam.core.errors import ConfigError, DatasetFormatError, FrameReadError, PlaneSlamError
from planeslam.io.dataset import TumDataset
from planeslam.io.trajectory import read_tum
from planeslam.slam import SLAM
from tests.corpus.cases import (
    corrupt,
    expect_error,
    expect_handled,
    frame_files,
    rewrite_rows,
    synth_sequence,
    truncate,
    write_png,
)

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synth_sequence(tmp_path_factory.mktemp("pristine") / "seq", frames=4).out_dir


@pytest.fixture
def seq(pristine: Path, tmp_path: Path) -> Path:
    """A fresh copy of the 4-frame sequence to break."""
    return Path(shutil.copytree(pristine, tmp_path / "seq"))


def open_seq(root: Path) -> TumDataset:
    cfg = resolve_config(root)
    return TumDataset(root, cfg.camera, cfg.dataset)


# ------------------------------------------------------------------ image files


def _jpeg_rgb(root: Path) -> Path:
    """Frame 1's colour image as a JPEG, listed in associations.txt."""
    rgb, _ = frame_files(root, 1)
    jpg = rgb.with_suffix(".jpg")
    cv2.imwrite(str(jpg), cv2.imread(str(rgb)))
    assoc = root / "associations.txt"
    assoc.write_text(assoc.read_text().replace(f"rgb/{rgb.name}", f"rgb/{jpg.name}"))
    return jpg


IMAGE_FAULTS = [
    ("truncated depth PNG", lambda r: truncate(frame_files(r, 1)[1]), r"truncated PNG"),
    ("truncated colour PNG", lambda r: truncate(frame_files(r, 1)[0], 0.9), r"truncated PNG"),
    ("truncated colour JPEG", lambda r: truncate(_jpeg_rgb(r), 0.7), r"truncated JPEG"),
    ("corrupt depth PNG", lambda r: corrupt(frame_files(r, 1)[1]), r"not a decodable image"),
    ("corrupt colour JPEG", lambda r: corrupt(_jpeg_rgb(r)), r"corrupt JPEG \(invalid marker"),
    (
        "text file named .png",
        lambda r: frame_files(r, 1)[1].write_text("not an image\n"),
        r"not a decodable image",
    ),
    ("empty image file", lambda r: frame_files(r, 1)[0].write_bytes(b""), "not a decodable"),
]


@pytest.mark.parametrize("case, damage, message", IMAGE_FAULTS, ids=[c[0] for c in IMAGE_FAULTS])
def test_unreadable_images_name_the_file(seq: Path, case: str, damage, message: str) -> None:
    damage(seq)
    dataset = open_seq(seq)
    exc = expect_error(case, FrameReadError, message, lambda: dataset[1])
    assert "1" in Path(str(exc).split(":")[0]).name or ".jpg" in str(exc)
    dataset[2]  # the other frames still read


DEPTH_FORMATS = [
    ("8-bit depth PNG", lambda d: (d // 256).astype(np.uint8), ".png", r"got uint8 with 1"),
    ("float depth image", lambda d: d.astype(np.float32) / 5000, ".tiff", r"got float32 with 1"),
    ("3-channel depth PNG", lambda d: np.dstack([d] * 3), ".png", r"got uint16 with 3 channel"),
]


@pytest.mark.parametrize("case, convert, suffix, message", DEPTH_FORMATS)
def test_depth_in_another_format(seq: Path, case, convert, suffix: str, message: str) -> None:
    _, depth = frame_files(seq, 0)
    raw = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
    depth.unlink()
    write_png(depth.with_suffix(suffix), convert(raw)).rename(depth)
    dataset = open_seq(seq)
    expect_error(
        case, DatasetFormatError, rf"{depth.name}: depth must be .*{message}", lambda: dataset[0]
    )


@pytest.mark.parametrize(
    "case, depth_scale, median",
    [
        ("raw depth values read as metres (depth_scale 1)", 1.0, r"far beyond"),
        ("depth_scale 1000x too large", 5e6, r"closer than any RGB-D camera"),
    ],
)
def test_dataset_depth_in_a_wrong_unit_names_depth_scale(
    seq: Path, case: str, depth_scale: float, median: str
) -> None:
    (seq / "camera.yaml").write_text(
        (seq / "camera.yaml")
        .read_text()
        .replace("depth_scale: 5000.0", f"depth_scale: {depth_scale}")
    )
    dataset = open_seq(seq)
    expect_error(
        case,
        DatasetFormatError,
        rf"depth/.*\.png: median depth .*{median}.*likely depth_scale 1000 or 5000 \(camera\.",
        lambda: dataset[0],
    )


def test_grey_and_rgba_colour_files_are_read_as_rgb(seq: Path) -> None:
    rgb0, _ = frame_files(seq, 0)
    rgb1, _ = frame_files(seq, 1)
    colour = cv2.imread(str(rgb0))
    write_png(rgb0, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))
    write_png(rgb1, cv2.cvtColor(cv2.imread(str(rgb1)), cv2.COLOR_BGR2BGRA))
    dataset = open_seq(seq)

    def read_both() -> None:
        grey, rgba = dataset[0].rgb, dataset[1].rgb
        assert grey.shape == rgba.shape == (240, 320, 3) and grey.dtype == np.uint8
        assert np.array_equal(grey[..., 0], grey[..., 2])

    expect_handled("greyscale and RGBA colour PNG files", read_both)


def test_colour_and_depth_of_different_sizes(seq: Path) -> None:
    rgb, _ = frame_files(seq, 2)
    write_png(rgb, cv2.resize(cv2.imread(str(rgb)), (160, 120)))
    dataset = open_seq(seq)
    expect_error(
        "colour and depth files of different sizes",
        DatasetFormatError,
        r"colour image is 160x120 but its depth image is 320x240",
        lambda: dataset[2],
    )


def test_missing_images_are_warned_about_and_all_missing_is_an_error(
    seq: Path, caplog: pytest.LogCaptureFixture
) -> None:
    frame_files(seq, 1)[0].unlink()

    def warns() -> None:
        with caplog.at_level(logging.WARNING):
            dataset = open_seq(seq)
        assert "image listed but not found; 1 of 4 frames will be skipped" in caplog.text
        with pytest.raises(FrameReadError, match=r"rgb/.*\.png: image listed but not found"):
            dataset[1]

    expect_handled("an image missing in the middle of a sequence", warns)
    for k in (0, 2, 3):
        frame_files(seq, k)[1].unlink()
    expect_error(
        "every frame misses an image",
        DatasetFormatError,
        r"image listed but not found; none of the 4 frames of .* has both its images",
        lambda: open_seq(seq),
    )


# ------------------------------------------------------------------ timestamps and lists


def _swap_first_two(rows: list[str]) -> list[str]:
    return [rows[1], rows[0], *rows[2:]]


def _repeat_first_time(rows: list[str]) -> list[str]:
    t0 = rows[0].split()[0]
    return [rows[0], " ".join([t0, *rows[1].split()[1:]]), *rows[2:]]


def _text_time(rows: list[str]) -> list[str]:
    return [rows[0], "soon " + rows[1].split(maxsplit=1)[1], *rows[2:]]


def _nan_time(rows: list[str]) -> list[str]:
    return [rows[0], "nan " + rows[1].split(maxsplit=1)[1], *rows[2:]]


TIMESTAMP_FAULTS = [
    ("decreasing timestamps", "associations.txt", _swap_first_two, r":2: timestamp .* goes back"),
    ("repeated timestamps", "associations.txt", _repeat_first_time, r":2: timestamp .* repeats"),
    ("text timestamp", "associations.txt", _text_time, r":2: expected 't_rgb rgb_path"),
    ("NaN timestamp", "associations.txt", _nan_time, r":2: expected 't_rgb rgb_path"),
    ("decreasing rgb.txt", "rgb.txt", _swap_first_two, r":2: timestamp .* goes back from"),
    ("repeated depth.txt", "depth.txt", _repeat_first_time, r":2: timestamp .* repeats the"),
    ("text time in rgb.txt", "rgb.txt", _text_time, r":2: expected 'timestamp path', got 'soon"),
]


@pytest.mark.parametrize("case, name, change, message", TIMESTAMP_FAULTS)
def test_bad_timestamps_name_the_line(
    seq: Path, case: str, name: str, change, message: str
) -> None:
    if name != "associations.txt":
        (seq / "associations.txt").unlink()
    rewrite_rows(seq / name, change)
    expect_error(case, DatasetFormatError, rf"{name}{message}", lambda: open_seq(seq))


@pytest.mark.parametrize(
    "case, text",
    [("empty list file", ""), ("list of comments only", "# timestamp filename\n# nothing\n")],
)
def test_empty_sequences(seq: Path, case: str, text: str) -> None:
    (seq / "associations.txt").unlink()
    (seq / "rgb.txt").write_text(text)
    expect_error(
        case, DatasetFormatError, r"rgb.txt: no entries \(expected rows", lambda: open_seq(seq)
    )


# ------------------------------------------------------------------ SLAM.process inputs


@pytest.fixture(scope="module")
def frames(pristine: Path):
    dataset = open_seq(pristine)
    return resolve_config(pristine), [dataset[i] for i in range(4)]


def _process_raises(frames, case, message, depth=None, rgb=None, stamp=None, before=0):
    cfg, fs = frames
    slam = SLAM(cfg, "merge")
    for f in fs[:before]:
        slam.process(f.depth_m, f.timestamp, f.rgb)
    planes = dict(slam.map.planes)
    f = fs[before]
    expect_error(
        case,
        DatasetFormatError,
        message,
        lambda: slam.process(
            f.depth_m if depth is None else depth,
            f.timestamp if stamp is None else stamp,
            f.rgb if rgb is None else rgb,
        ),
    )
    assert slam.frames == before and dict(slam.map.planes) == planes  # nothing changed
    slam.close()


def test_process_depth_in_a_wrong_unit_names_depth_scale(frames) -> None:
    _, fs = frames
    depth = fs[0].depth_m
    _process_raises(
        frames,
        "raw uint16 depth given to SLAM.process",
        r"depth_m is uint16: depth must be float metres.*depth_scale \(likely depth_scale 5000\)",
        depth=np.rint(depth * 5000).astype(np.uint16),
    )
    _process_raises(
        frames,
        "millimetres given to SLAM.process as metres",
        r"depth_m: median depth [\d.]+ m over the valid pixels, far beyond the camera's range "
        r"\(6 m\).*likely depth_scale 1000",
        depth=depth * 1000.0,
    )
    _process_raises(
        frames,
        "depth given to SLAM.process in kilometres",
        r"depth_m: median depth .* closer than any RGB-D camera sees.*about 1000x too small",
        depth=depth / 1000.0,
    )


def test_process_rejects_bad_colour_images(frames) -> None:
    _, fs = frames
    rgb = fs[0].rgb
    cases = [
        ("RGBA colour given to SLAM.process", np.dstack([rgb, rgb[..., :1]]), r"4 channels .*RGBA"),
        ("greyscale colour given to SLAM.process", rgb[..., 0], r"rgb is greyscale"),
        ("colour of another size", rgb[::2, ::2], r"rgb is 160x120 but the depth image is 320x240"),
        ("float colour", rgb / 255.0, r"rgb is float64: expected uint8"),
    ]
    for case, bad, message in cases:
        _process_raises(frames, case, message, rgb=bad)
    _process_raises(
        frames,
        "depth of another size than the camera",
        r"depth_m has shape \(120, 160\), expected \(H, W\) = \(240, 320\)",
        depth=fs[0].depth_m[::2, ::2],
    )


def test_process_rejects_timestamps_out_of_order(frames) -> None:
    _, fs = frames
    _process_raises(
        frames,
        "repeated timestamp given to SLAM.process",
        r"timestamp .* s is not after the previous frame's",
        stamp=fs[0].timestamp,
        before=1,
    )
    _process_raises(
        frames,
        "decreasing timestamp given to SLAM.process",
        r"is not after the previous frame's",
        stamp=fs[0].timestamp - 1.0,
        before=1,
    )
    _process_raises(frames, "NaN timestamp", r"timestamp nan is not a finite", stamp=float("nan"))
    _process_raises(frames, "text timestamp", r"timestamp 'now' is not a number", stamp="now")


@pytest.mark.integration
def test_nan_and_inf_depth_are_invalid_pixels(frames) -> None:
    cfg, fs = frames

    def same_as_zero() -> None:
        results = []
        for fills in ((0.0, 0.0, 0.0), (np.nan, np.inf, -np.inf)):
            slam = SLAM(cfg, "merge")
            out = []
            for f in fs[:3]:
                depth = f.depth_m.copy()
                for k, fill in enumerate(fills):  # the top sixth has no measurement
                    depth[13 * k : 13 * (k + 1) + 1] = fill
                out.append(slam.process(depth, f.timestamp, f.rgb))
            slam.close()
            results.append(out)
        for a, b in zip(*results, strict=True):
            assert a.path == b.path and np.allclose(a.T_world_cam, b.T_world_cam, atol=1e-9)

    expect_handled("NaN and infinity in depth given to SLAM.process", same_as_zero)


def _parallel_planes_only(cfg, frame) -> np.ndarray:
    """The frame's depth on the planes parallel to its largest plane (floor, box top), 0
    elsewhere: planes that leave the pose undetermined along and about their normal."""
    from planeslam.frontend.pipeline import FrontEnd

    seg = FrontEnd(cfg).process(frame.depth_m).segmentation
    largest = max(seg.planes, key=lambda p: np.count_nonzero(seg.labels == p.id))
    parallel = [p.id for p in seg.planes if abs(float(p.normal @ largest.normal)) > 0.99]
    assert len(parallel) >= 2 and len(parallel) < len(seg.planes)
    return np.where(np.isin(seg.labels, parallel), frame.depth_m, 0).astype(np.float32)


@pytest.mark.integration
@pytest.mark.parametrize("backend", ["merge", "isam2"])
def test_frames_without_depth_or_planes_are_lost_with_a_reason(frames, backend: str) -> None:
    cfg, fs = frames
    cfg = dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, separate_process=False))
    h, w = fs[0].depth_m.shape
    no_planes = np.random.default_rng(0).uniform(0.8, 3.0, (h, w)).astype(np.float32)
    for case, depth, frontend_reason, reason in [
        ("all-zero depth frame", np.zeros((h, w), np.float32), "no valid depth", "no plane"),
        ("frame with no plane", no_planes, "no plane with at least", "no plane"),
        (
            "frame whose planes are all parallel",
            _parallel_planes_only(cfg, fs[1]),
            "",
            "plane pose degenerate",
        ),
    ]:

        def lost_then_tracked(depth=depth, frontend_reason=frontend_reason, reason=reason) -> None:
            slam = SLAM(cfg, backend)
            slam.process(fs[0].depth_m, fs[0].timestamp, fs[0].rgb)
            result = slam.process(depth, fs[1].timestamp, fs[1].rgb)
            assert result.lost and not result.keyframe
            assert reason in result.reason and frontend_reason in result.observation.reason
            after = slam.process(fs[2].depth_m, fs[2].timestamp, fs[2].rgb)
            assert not after.lost, after.reason
            slam.finish()

        expect_handled(f"{case} ({backend})", lost_then_tracked)


def test_a_sequence_without_depth_from_its_first_frame_is_lost_not_tracked(frames) -> None:
    """A blind sensor (every depth pixel 0 from the first frame) gave 100 % tracked with
    identical poses; every such frame is lost, and the first frame with depth starts."""
    cfg, fs = frames

    def all_lost() -> None:
        slam = SLAM(cfg, "merge")
        blind = [slam.process(np.zeros_like(f.depth_m), f.timestamp, f.rgb) for f in fs[:3]]
        assert all(r.lost and "no valid depth" in r.reason for r in blind)
        assert slam.tracked_frames == 0 and not slam.map.planes
        seen = slam.process(fs[3].depth_m, fs[3].timestamp, fs[3].rgb)
        assert seen.path.value == "first" and seen.keyframe
        slam.finish()
        assert len(slam.trajectory()) == 1

    expect_handled("sequence with no valid depth from the first frame", all_lost)


@pytest.mark.integration
def test_a_parallel_planes_frame_after_tracked_ones_is_lost_not_slid(frames) -> None:
    """Frame 2 with depth only on parallel planes, after two tracked frames: RGB-D odometry
    from the prediction found no pose near the truth (143 cm off a 140 cm motion) and the
    depth-overlap check passed it, as any slide along those planes passes; the frame's
    keypoints must now confirm such a pose, and here they do not, so it is lost. The next
    frame is tracked again."""
    cfg, fs = frames

    def lost_not_slid() -> None:
        slam = SLAM(cfg, "merge")
        for f in fs[:2]:
            assert not slam.process(f.depth_m, f.timestamp, f.rgb).lost
        result = slam.process(_parallel_planes_only(cfg, fs[2]), fs[2].timestamp, fs[2].rgb)
        assert result.lost, (result.path, result.reason)
        assert "keypoints do not agree" in result.reason or "colours contradict" in result.reason
        assert not slam.process(fs[3].depth_m, fs[3].timestamp, fs[3].rgb).lost
        slam.finish()

    expect_handled("frame of parallel planes after tracked frames", lost_not_slid)


def test_finished_or_closed_slam_refuses_frames(frames) -> None:
    cfg, fs = frames
    for end in ("finish", "close"):
        slam = SLAM(cfg, "merge")
        slam.process(fs[0].depth_m, fs[0].timestamp, fs[0].rgb)
        getattr(slam, end)()
        expect_error(
            f"SLAM.process after {end}()",
            PlaneSlamError,
            r"this SLAM has finished",
            lambda slam=slam: slam.process(fs[1].depth_m, fs[1].timestamp, fs[1].rgb),
        )
        assert slam.frames == 1


# ------------------------------------------------------------------ camera.yaml, configs, truth


CAMERA_FAULTS = [
    ("camera.yaml not YAML", "fx: [525\n", ConfigError, r"camera.yaml: not a readable YAML file"),
    ("camera.yaml a list", "- 525\n- 525\n", ConfigError, r"expected a mapping of keys, got list"),
    (
        "camera.yaml unknown key",
        "focal: 525\n",
        ConfigError,
        r"unknown key\(s\) focal; valid keys: fx",
    ),
    ("camera.yaml text fx", "fx: wide\n", ConfigError, r"fx expects a number, got 'wide'"),
    ("camera.yaml zero width", "width: 0\n", ConfigError, r"image size 0x480 outside"),
    ("camera.yaml NaN centre", "cx: .nan\n", ConfigError, r"camera.cx must be a finite number"),
    ("camera.yaml infinite width", "width: .inf\n", ConfigError, r"width expects a whole number"),
    (
        "camera.yaml negative depth_scale",
        "depth_scale: -1\n",
        ConfigError,
        r"depth_scale must be > 0",
    ),
]


@pytest.mark.parametrize(
    "case, text, error, message", CAMERA_FAULTS, ids=[c[0] for c in CAMERA_FAULTS]
)
def test_malformed_camera_yaml(seq: Path, case: str, text: str, error, message: str) -> None:
    (seq / "camera.yaml").write_text(text)
    expect_error(case, error, message, lambda: resolve_config(seq))


CONFIG_FAULTS = [
    ("unknown preset", None, r"config 'tum_fr9': neither a preset \(defaults, tum_fr1"),
    ("config unknown section", "trackign:\n  icp: true\n", r"unknown key\(s\) trackign; valid"),
    ("config wrong type", "backend:\n  lag_frames: two\n", r"backend.lag_frames expects a number"),
    ("config NaN integer", "backend:\n  lag_frames: .nan\n", r"lag_frames expects a whole number"),
    ("config not YAML", "backend: {lag_frames: 2\n", r"not a readable YAML file"),
]


@pytest.mark.parametrize("case, text, message", CONFIG_FAULTS, ids=[c[0] for c in CONFIG_FAULTS])
def test_malformed_configs(tmp_path: Path, case: str, text: str | None, message: str) -> None:
    target = "tum_fr9"
    if text is not None:
        target = str(tmp_path / "bad.yaml")
        Path(target).write_text(text)
    expect_error(case, ConfigError, message, lambda: load_config(target))


TRUTH_FAULTS = [
    ("ground truth with too few columns", "1.0 0 0 0 0 0 1\n", r":1: expected 8 numbers"),
    ("ground truth with a bad quaternion", "1.0 0 0 0 0 0 0 2\n", r":1: quaternion .* norm 2"),
    ("ground truth with a zero quaternion", "1.0 0 0 0 0 0 0 0\n", r":1: quaternion .* norm 0"),
    ("ground truth with text", "1.0 0 0 x 0 0 0 1\n", r":1: expected 8 numbers"),
    ("ground truth with infinity", "1.0 0 0 inf 0 0 0 1\n", r":1: expected 8 numbers"),
]


@pytest.mark.parametrize("case, text, message", TRUTH_FAULTS, ids=[c[0] for c in TRUTH_FAULTS])
def test_malformed_ground_truth(
    seq: Path, case: str, text: str, message: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Read alone: a clean error. Beside a dataset: a warning, and no ground truth."""
    gt = seq / "groundtruth.txt"
    gt.write_text(text)
    expect_error(case, DatasetFormatError, rf"groundtruth.txt{message}", lambda: read_tum(gt))

    def read_without() -> None:
        with caplog.at_level(logging.WARNING):
            dataset = open_seq(seq)
        assert dataset.groundtruth is None and dataset.groundtruth_path is None
        assert "reading the sequence without ground truth" in caplog.text
        assert "groundtruth.txt" in dataset.groundtruth_error

    expect_handled(f"{case}, beside a dataset", read_without)
