"""`planeslam calibrate DATASET`: the sensor's depth noise fitted from the planes of a
sequence (`planeslam.frontend.calibration`), written as a config file holding the
`sensor` section (use it with `--config`: the preset is still guessed from the folder),
so that the segmentation's gates and the plane factors' noise follow it."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import yaml

from planeslam.app.subcommand import add_command
from planeslam.config import open_configured, resolve_config
from planeslam.core.config import ConfigLayer
from planeslam.core.safe_files import atomic_output
from planeslam.frontend.calibration import DepthNoiseFit, fit_depth_noise
from planeslam.slam import frame_indices

SENSOR_YAML = "sensor.yaml"


@dataclass(frozen=True)
class CalibrationResult:
    """What `calibrate_sequence` fitted and wrote."""

    fit: DepthNoiseFit
    path: Path
    """The config file written (its `sensor` section)."""

    def text(self) -> str:
        s = self.fit.sensor
        rows = "\n".join(
            f"  {z:5.2f} m  {1e3 * sigma:6.2f} mm  (model {1e3 * s.sigma_m(z):6.2f})  {n} pixels"
            for z, sigma, n in zip(self.fit.depth_m, self.fit.sigma_m, self.fit.pixels, strict=True)
        )
        return (
            f"depth noise from {self.fit.planes} planes of {self.fit.frames} frames: "
            f"sigma(z) = {1e3 * s.sigma_a_m:.2f} mm + {1e3 * s.sigma_b_per_m:.2f} mm/m^2 z^2, "
            f"1/z step {s.inverse_depth_step_per_m:.5f} 1/m"
            f"{'' if self.fit.step_found else ' (the configured one: no lattice found)'}"
            f" -> {self.path}\n"
            f"residual sigma (1.4826 MAD) per depth, quantisation included:\n{rows}"
        )


def calibrate_sequence(
    dataset_dir: str | Path,
    out: str | Path | None = None,
    config: str | Path | None = None,
    camera: str | ConfigLayer | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
    every: int = 1,
    max_frames: int | None = 30,
) -> CalibrationResult:
    """Fit the depth noise of the sensor of a dataset (TUM folder or bag) on every
    `every`-th of its frames (at most `max_frames`) and write it to `out` (default
    sensor.yaml in the current folder: datasets are often read-only)."""
    root = Path(dataset_dir)
    cfg = resolve_config(root, config, camera, overrides)
    dataset, cfg = open_configured(root, cfg)
    indices = frame_indices(len(dataset), max_frames, every)
    fit = fit_depth_noise([dataset[i].depth_m for i in indices], cfg, seed=cfg.run.seed)
    path = Path(out) if out is not None else Path(SENSOR_YAML)
    text = (
        f"# planeslam calibrate {root}: depth noise from {fit.planes} planes of "
        f"{fit.frames} frames\n" + yaml.safe_dump({"sensor": asdict(fit.sensor)}, sort_keys=False)
    )
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return CalibrationResult(fit, path)


def add_calibrate_command(sub: argparse._SubParsersAction) -> None:
    """The `calibrate` sub-command."""
    from planeslam.app.config_command import add_config_options

    p = add_command(
        sub,
        "calibrate",
        help="fit the sensor's depth noise from the planes of a sequence",
        description="Segment the frames of a dataset, fit the depth noise sigma(z) = a + b "
        "z^2 of the pixels about their planes and the quantisation step of 1/z, and write "
        "them as a config file with the sensor section (use it with --config).",
    )
    p.add_argument("dataset", type=Path, help="TUM-layout folder, ROS 1 .bag or ROS 2 bag")
    p.add_argument("--out", type=Path, default=None, help="file to write (default ./sensor.yaml)")
    p.add_argument("--every", type=int, default=1, help="every n-th frame (default 1)")
    p.add_argument("--max-frames", type=int, default=30, help="at most this many (default 30)")
    add_config_options(p)
    p.set_defaults(func=_cmd_calibrate)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from planeslam.app.config_command import camera_option, override_layers

    result = calibrate_sequence(
        args.dataset,
        args.out,
        args.config,
        camera_option(args),
        override_layers(args),
        args.every,
        args.max_frames,
    )
    print(result.text())
    return 0
