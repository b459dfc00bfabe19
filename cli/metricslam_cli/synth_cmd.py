"""``metricslam synth OUT_DIR --frames N --seed S``: write a synthetic KITTI-layout sequence.

The rig defaults to KITTI's (focal length scaled to ``--size``, 0.54 m baseline, 1.65 m high);
``--fx``, ``--baseline-m`` and ``--height-m`` render another one (docs/own_camera.md).
"""

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
    p.add_argument("--fx", type=float, default=None, metavar="PX",
                   help="focal length in pixels at --size (fx = fy; default KITTI 00's 718.856 px "
                        "scaled to the width, e.g. 718.856 at 1241 wide)")
    p.add_argument("--baseline-m", type=float, default=0.54, metavar="M",
                   help="stereo baseline: the right camera sits this far to the +x side (default 0.54)")
    p.add_argument("--height-m", type=float, default=1.65, metavar="M",
                   help="camera mounting height above the road (default 1.65, KITTI's)")
    p.add_argument("--board-photos", type=int, default=0, metavar="N",
                   help="also write N photos of a printed chessboard (9x6 inner corners, 25 mm "
                        "squares) seen by the left camera into OUT_DIR/board_photos/, for "
                        "`metricslam calibrate` (default 0)")
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


def synth_config(args: argparse.Namespace):
    """The :class:`~metricslam.synth.SynthConfig` of the arguments; without options it equals
    ``SynthConfig()`` (so the defaults render the same bytes as before the rig options)."""
    from metricslam.synth import SynthConfig
    from metricslam.synth.photometric import PhotometricConfig
    from metricslam.synth.world import WorldConfig

    photo = {"motion_blur_samples": args.motion_blur}
    if args.noise is not None:
        photo["noise_sigma"] = args.noise
    try:
        world = WorldConfig(traffic_per_100m=args.traffic, bridges_per_km=args.bridges,
                            camera_height_m=args.height_m)
        return SynthConfig(photometric=PhotometricConfig(**photo), world=world, fx_px=args.fx,
                           baseline_m=args.baseline_m)
    except ValueError as exc:  # pydantic's ValidationError names the field and its bound
        raise SynthError(f"bad option (--fx > 0, --baseline-m > 0, --height-m > 0.3, "
                         f"--traffic/--bridges 0..50): {exc}") from None


def run(args: argparse.Namespace) -> int:
    require("synth", command="synth")

    from metricslam.synth import generate_sequence

    if args.frames < 1:
        raise SynthError(f"--frames must be >= 1, got {args.frames}")
    if args.board_photos < 0:
        raise SynthError(f"--board-photos must be >= 0, got {args.board_photos}")
    config = synth_config(args)
    world = config.world
    scene = generate_sequence(args.out_dir, args.frames, args.seed, trajectory=args.trajectory,
                              size=args.size, start=args.start, path=args.path, config=config,
                              progress=not args.no_progress)
    cam = scene.camera
    print(f"wrote {args.frames} frames to {args.out_dir} ({cam.width_px}x{cam.height_px}, "
          f"fx {cam.fx_px:.3f} px, baseline {config.baseline_m:g} m, height {world.camera_height_m:g} m)")
    if args.board_photos:
        from metricslam.synth.board import write_board_photos

        folder = write_board_photos(args.out_dir, cam, args.board_photos, args.seed)
        print(f"wrote {args.board_photos} chessboard photos to {folder}")
    return 0
