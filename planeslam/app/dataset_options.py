"""What the commands that read a dataset share: which bag topics to read (`--rgb-topic`,
`--depth-topic`, `--camera-info-topic`), applied to the resolved config's `dataset.bag`
section so that the saved config.yaml reproduces the run, and opening the dataset with
the config (`open_configured`)."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path

from planeslam.config import PlaneSlamConfig
from planeslam.io.config import BagConfig
from planeslam.io.sequence import RgbdDataset, open_dataset


@dataclass(frozen=True)
class TopicOverrides:
    """Bag topics given on the command line; None keeps the config's."""

    rgb_topic: str | None = None
    """Colour image topic."""
    depth_topic: str | None = None
    """Depth image topic."""
    camera_info_topic: str | None = None
    """camera_info topic of the colour camera."""

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> TopicOverrides:
        return cls(args.rgb_topic, args.depth_topic, args.camera_info_topic)

    def apply(self, config: PlaneSlamConfig) -> PlaneSlamConfig:
        """`config` with these topics in `dataset.bag`."""
        given = {k: v for k, v in dataclasses.asdict(self).items() if v is not None}
        if not given:
            return config
        bag: BagConfig = dataclasses.replace(config.dataset.bag, **given)
        return dataclasses.replace(config, dataset=dataclasses.replace(config.dataset, bag=bag))


def open_configured(
    path: str | Path, config: PlaneSlamConfig
) -> tuple[RgbdDataset, PlaneSlamConfig]:
    """The sequence at `path` read with `config`, and `config` with the sequence's camera
    (a bag's camera_info replaces the configured intrinsics)."""
    dataset = open_dataset(path, config.camera, config.dataset)
    return dataset, dataclasses.replace(config, camera=dataset.camera)


def add_topic_options(p: argparse.ArgumentParser) -> None:
    """--rgb-topic, --depth-topic, --camera-info-topic (ROS bags only)."""
    defaults = BagConfig()
    for flag, default, what in (
        ("--rgb-topic", defaults.rgb_topic, "colour image topic"),
        ("--depth-topic", defaults.depth_topic, "depth image topic (16UC1 or 32FC1)"),
        ("--camera-info-topic", defaults.camera_info_topic, "camera_info topic (intrinsics)"),
    ):
        p.add_argument(
            flag, default=None, metavar="TOPIC", help=f"ROS bags: {what} (default {default})"
        )
