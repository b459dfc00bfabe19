"""``metricslam depth IMAGE (--fx FX [--fy FY --cx CX --cy CY] | --calib FILE) --out OUT.npy
[--png OUT.png] [--model PATH]``.

One image (gray or colour, any size) through the depth model in onnxruntime; writes depth in
metres (float32, the network's L3 output resolution, covering the whole image; NaN where a
canonical-camera model — contract version 2 — did not see the image). Intrinsics are pixels of
IMAGE as given: ``--fx`` with optional ``--fy`` (default fx), ``--cx``/``--cy`` (default the
image centre, (W−1)/2 and (H−1)/2), or a ``--calib`` file (rescaled to the image's size if it has
the same aspect ratio; distortion is undone first). Version-1 models use only fx.
"""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("depth", help="metric depth of one image with the shipped network",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", help="image file (PNG/JPEG, gray or colour, any size)")
    p.add_argument("--fx", type=float, help="focal length of IMAGE in pixels (at its own width)")
    p.add_argument("--fy", type=float, help="focal length y in pixels; default = fx")
    p.add_argument("--cx", type=float, help="principal point x in pixels; default = image centre (W-1)/2")
    p.add_argument("--cy", type=float, help="principal point y in pixels; default = image centre (H-1)/2")
    p.add_argument("--calib", metavar="FILE.yaml",
                   help="camera calibration instead of --fx/--fy/--cx/--cy (metricslam, OpenCV FileStorage "
                        "or EuRoC sensor.yaml YAML; docs/calibration.md); distortion is undone first")
    p.add_argument("--out", required=True,
                   help="output .npy: (h, w) float32 depth in metres; an existing folder (or a path "
                        "ending in /): written inside it as <IMAGE stem>.depth.npy")
    p.add_argument("--png", help="optional coloured visualization (inverse depth, near = bright)")
    p.add_argument("--model", help="ONNX model (default: the shipped int8 depth_l3_int8.onnx; its float32 "
                                   "source depth_l3.onnx lies next to it in metricslam/models/)")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads (default 1)")
    p.set_defaults(func=run)
    return p


def image_camera(args: argparse.Namespace, width_px: int, height_px: int):
    """``(PinholeCamera, undistortion maps or None)`` of IMAGE from ``--calib`` or ``--fx`` [...].

    Raises:
        ConfigError: neither or both given; CameraError / CalibrationError: bad values.
    """
    from metricslam.errors import ConfigError
    from metricslam_cli.camera_cmd import intrinsics

    if args.calib and args.fx is not None:
        raise ConfigError("--calib and --fx both give intrinsics; pass one")
    if args.calib:
        from metricslam.calibration import camera_and_maps, load_calibration

        return camera_and_maps(load_calibration(args.calib), width_px, height_px)
    if args.fx is None:
        raise ConfigError("no intrinsics: pass --fx FX (focal length in pixels at IMAGE's width; "
                          "--fy/--cx/--cy optional) or --calib FILE.yaml")
    return intrinsics(width_px, height_px, args.fx, args.fy, args.cx, args.cy), None


def out_path(out: str, image: str):
    """Where ``--out`` writes: ``out`` itself, or ``out/<image stem>.depth.npy`` when ``out`` is
    an existing folder or ends with a path separator (never "a file named like the folder").

    Raises:
        ConfigError: ``out`` exists and is neither a file nor a folder.
    """
    import os
    from pathlib import Path

    from metricslam.errors import ConfigError

    path = Path(out)
    if path.is_dir() or out.endswith((os.sep, "/")):
        return path / f"{Path(image).stem}.depth.npy"
    if path.exists() and not path.is_file():
        raise ConfigError(f"--out {out} exists and is not a file: give a .npy path or a folder")
    return path


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    import cv2
    import numpy as np

    from metricslam.depth.model import DepthModel
    from metricslam.errors import ImageError

    out = out_path(args.out, args.image)  # before any work
    bgr = cv2.imread(str(args.image), cv2.IMREAD_UNCHANGED)
    if bgr is None:
        raise ImageError(f"cannot read image {args.image}: give a PNG or JPEG file")
    if bgr.dtype == np.uint16:
        bgr = (bgr >> 8).astype(np.uint8)
    if bgr.ndim == 3 and bgr.shape[2] == 4:
        bgr = bgr[:, :, :3]
    image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB) if bgr.ndim == 3 else bgr
    camera, maps = image_camera(args, image.shape[1], image.shape[0])
    if maps is not None:
        image = cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR)
    model = DepthModel.load(args.model, threads=args.threads)
    result = model.predict_inv_depth(image, camera=camera)
    depth_m = result.depth_m()
    out.parent.mkdir(parents=True, exist_ok=True)
    np.save(out, depth_m)
    if args.png:
        inv = np.nan_to_num(result.inv_depth_per_m, nan=0.0)  # unseen cells: black
        scale = float(np.percentile(inv, 99)) or 1.0
        u8 = np.clip(inv / scale * 255.0, 0, 255).astype(np.uint8)
        h, w = image.shape[:2]
        vis = cv2.applyColorMap(cv2.resize(u8, (w, h), interpolation=cv2.INTER_NEAREST), cv2.COLORMAP_MAGMA)
        Path(args.png).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.png), vis)
    finite = depth_m[np.isfinite(depth_m)]
    median = float(np.median(finite)) if finite.size else float("nan")
    print(f"{out}: depth {depth_m.shape[0]}x{depth_m.shape[1]} m, median {median:.2f} m "
          f"(model {model.contract.model_id}, {model.contract.weights_precision})")
    return 0
