"""`planeslam synth`: render a synthetic RGB-D sequence with exact truth (arguments + one call)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from planeslam.app.arg_types import SEED, number, sigma_pair, whole
from planeslam.app.subcommand import add_command
from planeslam.core.errors import ConfigError


def _range(text: str) -> tuple[float, float]:
    """'LOW,HIGH' -> (low, high); argparse turns the error into a usage message."""
    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW,HIGH (two numbers), got {text!r}") from None
    return low, high


def add_synth_command(sub: argparse._SubParsersAction) -> None:
    """The `synth` sub-command."""
    from planeslam.sim.noise import NOISE_MODELS
    from planeslam.sim.procedural import FURNITURE_KINDS, TEXTURE_KINDS, TRAJECTORY_KINDS
    from planeslam.sim.scenes import SCENES

    p = add_command(
        sub,
        "synth",
        help="render a synthetic RGB-D sequence with exact truth",
        description="Render a synthetic RGB-D sequence in the TUM layout, with camera.yaml "
        "and truth.json (planes, edges, corners, objects and their sizes, trajectory, and how "
        "it was rendered). The options vary the depth noise model, the camera and the "
        "texture; the scene's geometry and truth stay the same. The scene 'procedural' is "
        "drawn from --seed as the robustness benchmark draws its sequences (room, furniture, "
        "texture, camera path); --trajectory, --texture, --room and --furniture set parts "
        "of it, --noise-model its depth model: a sequence of a kind the benchmark holds, "
        "that no one tuned on.",
    )
    p.add_argument("scene", choices=[*sorted(SCENES), "procedural"], help="scene to render")
    p.add_argument("outdir", type=Path, help="output folder (created; must be empty)")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="render into OUTDIR even when it is not empty (its files are replaced)",
    )
    p.add_argument(
        "--frames", type=whole(1, 100_000), default=None, help="number of frames (default: scene's)"
    )
    p.add_argument("--seed", type=SEED, default=0, help="noise seed (default 0)")
    p.add_argument(
        "--noise-model",
        choices=sorted(NOISE_MODELS),
        default=None,
        help="depth error model: kinect (the front end's own sigma(z), default; 'procedural' "
        "draws one), disparity (structured light: quantised disparity, flying pixels, "
        "dropouts, shadows) or tof",
    )
    p.add_argument(
        "--hfov",
        type=number(1, 179),
        default=None,
        metavar="DEG",
        help="horizontal field of view [deg] (default 62.7: fx 525 px at 640 px)",
    )
    p.add_argument(
        "--camera-height",
        type=number(-100, 100),
        default=None,
        metavar="M",
        help="camera height [m]",
    )
    p.add_argument(
        "--look-height",
        type=number(-100, 100),
        default=None,
        metavar="M",
        help="look-at height [m]",
    )
    p.add_argument(
        "--start-azimuth",
        type=number(-360, 360),
        default=None,
        metavar="DEG",
        help="first azimuth on the circle [deg] (box_room_circle)",
    )
    p.add_argument(
        "--texture-seed", type=SEED, default=None, metavar="N", help="seed of the planes' texture"
    )
    p.add_argument(
        "--texture-brightness",
        type=_range,
        default=None,
        metavar="LOW,HIGH",
        help="range of the planes' mean albedo in (0, 1] (default 0.6,0.6)",
    )
    procedural = p.add_argument_group("procedural scene")
    procedural.add_argument("--trajectory", choices=TRAJECTORY_KINDS, help="camera path kind")
    procedural.add_argument("--texture", choices=TEXTURE_KINDS, help="texture of the surfaces")
    procedural.add_argument(
        "--room", choices=("square", "oblong"), help="floor shape (square: symmetric)"
    )
    procedural.add_argument(
        "--furniture",
        type=_furniture(FURNITURE_KINDS),
        metavar="KIND,...",
        help=f"comma-separated furniture kinds ({', '.join(FURNITURE_KINDS)}; '' for none)",
    )
    p.add_argument(
        "--odometry-sigma",
        type=sigma_pair,
        default=None,
        metavar="M,DEG",
        help="also write odometry.txt: the camera's odometry as a robot's wheels give it, "
        "each step of the truth with Gaussian noise of M metres and DEG degrees per axis, "
        "drawn from --seed (for `planeslam run --odometry`)",
    )
    p.set_defaults(func=_cmd_synth)


def _furniture(kinds: tuple[str, ...]) -> Callable[[str], tuple[str, ...]]:
    """A parser of 'KIND,...' into the furniture kinds among `kinds` ('' for none)."""

    def parse(text: str) -> tuple[str, ...]:
        chosen = tuple(k for k in text.split(",") if k)
        bad = [k for k in chosen if k not in kinds]
        if bad:
            raise argparse.ArgumentTypeError(f"unknown furniture {bad}; kinds: {', '.join(kinds)}")
        return chosen

    return parse


def _cmd_synth(args: argparse.Namespace) -> int:
    from planeslam.app.run_folder import check_empty_folder
    from planeslam.sim.scenes import SceneOptions, Texture
    from planeslam.sim.sequence import SynthOptions, render_sequence

    check_empty_folder(args.outdir, args.overwrite)
    if args.scene == "procedural":
        _procedural(args)
        _write_odometry(args)
        return 0
    if any(getattr(args, k) is not None for k in ("trajectory", "texture", "room", "furniture")):
        raise ConfigError("--trajectory, --texture, --room and --furniture are for 'procedural'")

    texture = None
    if args.texture_seed is not None or args.texture_brightness is not None:
        if args.texture_seed is None:
            raise ConfigError("--texture-brightness needs --texture-seed")
        brightness = args.texture_brightness or Texture().brightness
        texture = Texture(seed=args.texture_seed, brightness=brightness)
    options = SynthOptions(
        noise_model=args.noise_model or "kinect",
        hfov_deg=args.hfov,
        scene=SceneOptions(
            camera_height_m=args.camera_height,
            target_height_m=args.look_height,
            start_azimuth_deg=args.start_azimuth,
            texture=texture,
        ),
    )
    result = render_sequence(args.scene, args.outdir, options, frames=args.frames, seed=args.seed)
    print(f"wrote {result.num_frames} frames of '{result.scene_name}' to {result.out_dir}")
    _write_odometry(args)
    return 0


def _write_odometry(args: argparse.Namespace) -> None:
    """odometry.txt from the rendered groundtruth.txt, with --odometry-sigma (if given)."""
    if args.odometry_sigma is None:
        return
    from planeslam.io.trajectory import read_tum, write_tum
    from planeslam.sim.odometry import noisy_odometry

    sigma_m, sigma_deg = args.odometry_sigma
    truth = read_tum(args.outdir / "groundtruth.txt")
    header = (
        f"planeslam synthetic odometry, {sigma_m} m and {sigma_deg} deg per step, seed {args.seed}"
    )
    write_tum(
        args.outdir / "odometry.txt", noisy_odometry(truth, sigma_m, sigma_deg, args.seed), header
    )
    print(f"wrote {args.outdir / 'odometry.txt'}")


def _procedural(args: argparse.Namespace) -> None:
    """Render the procedural recipe of --seed, with the parts the options set."""
    import dataclasses

    from planeslam.sim.procedural import draw_recipe, write_procedural

    recipe = draw_recipe(args.seed, args.trajectory, args.texture, args.noise_model)
    if args.room is not None:
        recipe = dataclasses.replace(recipe, square_room=args.room == "square")
    if args.furniture is not None:
        recipe = dataclasses.replace(recipe, furniture=args.furniture)
    result = write_procedural(recipe, args.outdir, max_frames=args.frames)
    print(f"wrote {result.num_frames} frames of '{recipe.name}' to {result.out_dir}")
