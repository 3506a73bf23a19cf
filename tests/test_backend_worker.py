"""The iSAM2 backend beside tracking (planeslam.backend.worker): the child process gives
what inline gives, errors and interruptions reach the caller, what crosses the pipe is
small, and Python factors see iSAM2's own linearisation point (no copy per call)."""

from __future__ import annotations

import dataclasses
import pickle
import subprocess
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest

from planeslam.backend.base import KeyframeInput
from planeslam.backend.config import BackendConfig
from planeslam.backend.worker import Isam2Worker
from planeslam.config import resolve_config
from planeslam.core.errors import ConfigError, PlaneSlamError
from planeslam.eval.metrics import slam_run_metrics
from planeslam.eval.trajectory_metrics import evaluate_trajectory
from planeslam.factors.config import LandmarkKeys
from planeslam.factors.landmarks import PlaneLandmarks
from planeslam.factors.recovery import new_isam2
from planeslam.frontend.pipeline import FrontEnd
from planeslam.io.dataset import TumDataset
from planeslam.sim.sequence import synthesize
from planeslam.slam import SLAM, run_frames

pytestmark = pytest.mark.integration  # the backend in a worker process


@pytest.fixture(scope="module")
def loop(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("loop") / "seq"
    return synthesize("room_boxes_loop", root, frames=45, seed=5).out_dir


def run_loop(root: Path, **backend_overrides):
    cfg = resolve_config(root)
    cfg = dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, **backend_overrides))
    dataset = TumDataset(root, cfg.camera, cfg.dataset)
    slam = SLAM(cfg, "isam2", T_world_first=dataset.groundtruth_pose(dataset.timestamps[0]))
    summary = run_frames(slam, dataset, range(len(dataset)))
    ev = evaluate_trajectory(dataset.groundtruth, slam.trajectory())
    return slam, summary, ev


@pytest.mark.slow
def test_the_process_gives_what_inline_gives_and_lag_keeps_accuracy(loop: Path) -> None:
    inline, s_inline, ev_inline = run_loop(loop, separate_process=False)
    child, s_child, ev_child = run_loop(loop, separate_process=True)
    assert s_child.keyframes == s_inline.keyframes
    np.testing.assert_allclose(
        child.trajectory().T_world_cam, inline.trajectory().T_world_cam, atol=1e-7
    )
    assert child.backend_result.failures == 0
    assert len(child.backend_result.keyframe_poses) == s_child.keyframes
    figures = slam_run_metrics(child, s_child).backend
    assert figures["factors"] > 0 and figures["update_ms_max"] >= figures["update_ms_median"] > 0
    _, s_sync, ev_sync = run_loop(loop, separate_process=False, lag_frames=0)
    for ev in (ev_inline, ev_child, ev_sync):
        assert ev.ate_rmse_m < 0.01


def first_observation(root: Path):
    cfg = resolve_config(root)
    frame = TumDataset(root, cfg.camera, cfg.dataset)[0]
    return FrontEnd(cfg).process(frame.depth_m, frame.timestamp)


def keyframe(index: int, measurements) -> KeyframeInput:
    return KeyframeInput(index, 0.1 * index, np.eye(4), measurements, {}, {}, None)


def test_errors_in_the_worker_reach_the_caller_and_finish_closes(loop: Path) -> None:
    measurements = first_observation(loop).measurements()
    worker = Isam2Worker(BackendConfig(final_iterations=0))
    worker.submit(keyframe(3, measurements))
    worker.submit(keyframe(2, measurements))  # index must increase: fails in the child
    assert worker.collect().index == 3
    with pytest.raises(ConfigError, match="expected > the previous keyframe 3"):
        worker.collect()
    result = worker.finish()  # the child carried on after the error
    assert list(result.keyframe_poses) == [3] and result.num_factors == 1
    with pytest.raises(PlaneSlamError, match="has finished"):
        worker.submit(keyframe(4, measurements))
    worker.close()  # idempotent


def test_a_dropped_or_closed_slam_stops_its_worker(loop: Path) -> None:
    cfg = resolve_config(loop)
    with SLAM(cfg, "isam2") as slam:
        process = slam.backend._process
        assert process.poll() is None
    assert process.wait(timeout=10) is not None  # leaving the block stopped it
    dropped = SLAM(cfg, "isam2")
    process = dropped.backend._process
    del dropped
    assert process.wait(timeout=10) is not None  # dropping the object stopped it


def test_process_after_finish_or_close_raises_before_changing_anything(loop: Path) -> None:
    cfg = resolve_config(loop)
    frame = TumDataset(loop, cfg.camera, cfg.dataset)[0]
    for end in ("finish", "close"):
        slam = SLAM(cfg, "merge")
        slam.process(frame.depth_m, frame.timestamp, frame.rgb)
        getattr(slam, end)()
        planes = dict(slam.map.planes)
        with pytest.raises(PlaneSlamError, match="has finished"):
            slam.process(frame.depth_m, frame.timestamp + 1.0, frame.rgb)
        assert slam.frames == 1 and dict(slam.map.planes) == planes


def test_an_interrupted_run_stops_the_worker(loop: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = resolve_config(loop)
    dataset = TumDataset(loop, cfg.camera, cfg.dataset)
    slam = SLAM(cfg, "isam2")
    original = SLAM.process

    def interrupt_at_four(self, *args, **kwargs):
        if self.frames == 4:
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(SLAM, "process", interrupt_at_four)
    with pytest.raises(KeyboardInterrupt):
        run_frames(slam, dataset, range(8))
    assert slam.backend._process.poll() is not None  # the child has exited
    assert len(slam.trajectory()) == 4


def test_what_crosses_the_pipe_is_small_and_gives_the_same_factors(loop: Path) -> None:
    obs = first_observation(loop)
    measurements = obs.measurements()
    sent = keyframe(0, measurements)
    assert len(pickle.dumps(sent)) < 50_000 < len(pickle.dumps(obs))
    received = pickle.loads(pickle.dumps(sent)).measurements
    assert len(received.planes) == len(obs.segmentation.planes) >= 3
    assert len(received.corners) == len(obs.structure.corners)
    T = np.eye(4)
    plane_ids = {p.id: p.id for p in obs.segmentation.planes}
    errors = []
    for frame_measurements in (measurements, received):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        keys = LandmarkKeys()
        values.insert(keys.pose(0), gtsam.Pose3(gtsam.Rot3.Yaw(0.01), np.array([0.01, 0, 0])))
        PlaneLandmarks(keys).add_observations(
            graph, values, keys.pose(0), T, frame_measurements, plane_ids
        )
        errors.append([graph.at(i).error(values) for i in range(graph.size())])
    assert len(errors[0]) >= 3
    assert errors[0] == errors[1]


def test_python_factors_get_isam2s_own_values_not_a_copy() -> None:
    """pybind11 copies a C++ Values into a new Python object for each call of a Python
    factor unless one exists for it: `new_isam2` keeps one, so no call copies the map."""
    isam, theta = new_isam2(gtsam.ISAM2Params())
    seen = []

    def error(this, values, H):
        seen.append(values is theta)
        if H is not None:
            H[0] = np.eye(3)
        return values.atPoint3(this.keys()[0]) - np.array([1.0, 2.0, 3.0])

    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    for step in range(3):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.CustomFactor(noise, [step], error))
        values.insert(step, np.zeros(3))
        isam.update(graph, values)
    assert seen and all(seen)
    np.testing.assert_allclose(isam.calculateEstimate().atPoint3(2), [1.0, 2.0, 3.0], atol=1e-9)


def test_the_backend_process_imports_no_front_end():
    """The worker's iSAM2 backend and the landmark table it fills from `FrameMeasurements`
    load neither the front end's stages nor numba, OpenCV or networkx: about half its
    start-up CPU and 85 MB of its memory (docs/speed.md)."""
    heavy = ["numba", "cv2", "networkx"]
    heavy += ["planeslam.frontend.pipeline", "planeslam.frontend.objects"]
    code = (
        "import sys; import planeslam.backend.isam2; "
        f"print([name for name in {heavy!r} if name in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
