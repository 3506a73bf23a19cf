"""Command-line options of the commands that read a dataset: which bag topics to read
(`--rgb-topic`, `--depth-topic`, `--camera-info-topic`), applied to the resolved config's
`dataset.bag` section so that the saved config.yaml reproduces the run."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass

from planeslam.config import PlaneSlamConfig
from planeslam.io.config import BagConfig


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
