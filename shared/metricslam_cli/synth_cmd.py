"""``metricslam synth OUT_DIR --frames N --seed S``: write a synthetic KITTI-layout sequence."""

from __future__ import annotations

import argparse

from metricslam.errors import SynthError
from metricslam_cli.extras import require


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 1241x376, got {text!r}") from None
    return w, h


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "synth", help="generate a synthetic stereo driving sequence (KITTI layout + depth)",
        description="Render a KITTI-like street sequence with exact metric depth and poses: "
                    "image_0/, image_1/, depth_0/ (uint16 metres x 256), calib.txt, times.txt, "
                    "poses/00.txt.")
    p.add_argument("out_dir", metavar="OUT_DIR", help="output folder (image_0/ must be empty)")
    p.add_argument("--frames", type=int, required=True, help="number of frames (10 Hz)")
    p.add_argument("--seed", type=int, default=0, help="seed of world, path and noise (default 0)")
    p.add_argument("--trajectory", metavar="POSES_TXT",
                   help="drive along a KITTI pose file instead of a procedural path")
    p.add_argument("--start", type=int, default=0, help="first pose of --trajectory to use")
    p.add_argument("--path", choices=("straight", "turns", "loop"), default="loop",
                   help="procedural path when no --trajectory is given (default loop)")
    p.add_argument("--size", type=_size, default=(1241, 376), metavar="WxH",
                   help="image size (default 1241x376)")
    p.add_argument("--motion-blur", type=int, default=0, metavar="N",
                   help="average N sub-frame renders per image (0 = off)")
    p.add_argument("--noise", type=float, default=None, metavar="SIGMA",
                   help="gaussian noise std in gray levels (default 1.5)")
    p.add_argument("--traffic", type=float, default=0.0, metavar="PER_100M",
                   help="vehicles standing on the road beside the path per 100 m (default 0)")
    p.add_argument("--bridges", type=float, default=0.0, metavar="PER_KM",
                   help="overpasses across the path per km (default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    require("synth", command="synth")

    from metricslam.synth import SynthConfig, generate_sequence
    from metricslam.synth.photometric import PhotometricConfig

    if args.frames < 1:
        raise SynthError(f"--frames must be >= 1, got {args.frames}")
    photo = {"motion_blur_samples": args.motion_blur}
    if args.noise is not None:
        photo["noise_sigma"] = args.noise
    from metricslam.synth.world import WorldConfig

    world = WorldConfig(traffic_per_100m=args.traffic, bridges_per_km=args.bridges)
    config = SynthConfig(photometric=PhotometricConfig(**photo), world=world)
    generate_sequence(args.out_dir, args.frames, args.seed, trajectory=args.trajectory,
                      size=args.size, start=args.start, path=args.path, config=config,
                      progress=not args.no_progress)
    print(f"wrote {args.frames} frames to {args.out_dir}")
    return 0
