"""Shared fixtures: the real data folder (skipped with a reason when absent); and the
`unit` / `integration` split of the suite (`make test-fast` runs `-m "unit and not slow"`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.corpus.tally import pytest_terminal_summary  # noqa: F401  (the fault corpus's figures)

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEQUENCES = ("7scenes_redkitchen_1000f", "tum_fr1_desk_9f", "tum_fr1_xyz_10f")

# Modules whose tests run across stages: the whole pipeline or SLAM runs, the CLI,
# subprocesses (the backend worker, the suite, packaging, benchmarks). Chosen by measuring
# `pytest --durations=0`: together they took ~75 s of the ~115 s suite. Tests on the real
# data (`data` mark) are integration tests too, wherever they are.
INTEGRATION_MODULES = frozenset(
    {
        "test_backend_worker.py",  # the backend in a worker process
        "test_baselines.py",  # open3d odometry on real data, the baseline suite in workers
        "test_bench.py",  # `planeslam bench`: front end over rendered sequences
        "test_cli.py",  # the CLI, in subprocesses, demo included
        "test_examples.py",  # examples/ run as scripts: rendering, front end, SLAM
        "test_faults_cli.py",  # the fault corpus through the CLI: signals, kills, full disks
        "test_faults_runs.py",  # the fault corpus on whole runs
        "test_packaging.py",  # builds and installs a wheel
        "test_run_config.py",  # `planeslam run` twice: the saved config repeats the run
        "test_run_views.py",  # a short run, then its report, rerun recordings and mesh
        "test_slam.py",  # full SLAM runs, `planeslam run`
        "test_tracking_runs.py",  # tracking on rendered and real sequences, whole runs
        "test_suite_command.py",  # `planeslam suite`
        "test_suite_executors.py",  # the suite on a Dask LocalCluster of worker processes
    }
)

# Single tests of otherwise unit modules that cross stages or call subprocesses
# ("module::function", every parametrisation included). Measured at 0.4-5.5 s per function
# (all parametrisations); what is left as `unit` runs in ~10 s of test time plus ~4 s of
# collection, the imports of open3d, gtsam and evo.
INTEGRATION_TESTS = frozenset(
    {
        # the evo CLI in subprocesses; whole evaluation folder with plots and report
        "test_eval.py::test_ate_equals_evo_ape_cli",
        "test_eval.py::test_rpe_equals_evo_rpe_cli",
        "test_eval.py::test_write_evaluation_and_report",
        "test_eval.py::test_evaluate_to_folder_adds_object_sizes",
        # renderer -> segmenter / front end, on whole rendered frames or sequences
        "test_frontend.py::test_truth_frames_see_three_box_faces",
        "test_frontend.py::test_box_and_room_with_the_real_segmenter",
        "test_segmentation.py::test_organized_matches_truth",
        "test_segmentation.py::test_msac_matches_truth",
        # a whole loop through iSAM2; rendered frames -> front end -> factor graph
        "test_backend.py::test_isam2_beats_odometry_below_1cm",
        "test_backend.py::test_real_front_end_observations_on_rendered_frames",
        # the fault corpus: whole SLAM runs on frames without depth or planes
        "test_faults_inputs.py::test_frames_without_depth_or_planes_are_lost_with_a_reason",
        # slow: the demo's figure; the paper's 24-frame run through front end and map
        "test_frontend.py::test_demo_figure_box_found_and_sized",
        "test_map.py::test_true_pose_merge_of_box_room_circle_sizes_box_and_room",
        # rendered frames -> front end -> the landmark layer's objects
        "test_outside_stack.py::test_objects_from_the_landmark_layer_on_rendered_frames",
        # the second depth model: the CLI, the front end and full SLAM on its renderings
        "test_depth_models.py::test_synth_command_writes_the_rendering_it_was_asked_for",
        "test_depth_models.py::test_front_end_finds_box_and_room_in_disparity_frames",
        "test_depth_models.py::test_slam_on_the_disparity_rendering",
        "test_depth_models.py::test_slam_on_the_independent_rendering_reaches_the_issue_target",
    }
)


def _is_integration(item: pytest.Item) -> bool:
    if item.get_closest_marker("data") is not None:  # real data: the whole reader, undistortion
        return True
    module = item.path.name
    name = getattr(item, "originalname", item.name)
    return module in INTEGRATION_MODULES or f"{module}::{name}" in INTEGRATION_TESTS


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test is `unit` or `integration`; an explicit mark on the test wins."""
    for item in items:
        if item.get_closest_marker("unit") or item.get_closest_marker("integration"):
            continue
        item.add_marker(pytest.mark.integration if _is_integration(item) else pytest.mark.unit)


def shared_sequence(name: str) -> Path:
    """Path of a sequence in ../shared/data, or skip the test saying why."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"real data not available: {path} is absent (CI and developers have it)")
    return path


@pytest.fixture
def rng():
    import numpy as np

    return np.random.default_rng(12345)
