"""``metricslam depth IMAGE --fx FX --out OUT.npy [--png OUT.png] [--model PATH]``.

One image (gray or colour, any size) through the depth model in onnxruntime; writes depth in
metres (float32, the network's L3 output resolution, covering the whole image).
"""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("depth", help="metric depth of one image with the shipped network",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", help="image file (PNG/JPEG, gray or colour, any size)")
    p.add_argument("--fx", type=float, required=True, help="focal length of IMAGE in pixels (at its own width)")
    p.add_argument("--out", required=True, help="output .npy: (h, w) float32 depth in metres")
    p.add_argument("--png", help="optional coloured visualization (inverse depth, near = bright)")
    p.add_argument("--model", help="ONNX model (default: the shipped int8 depth_l3_int8.onnx; its float32 "
                                   "source depth_l3.onnx lies next to it in metricslam/models/)")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads (default 1)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    import cv2
    import numpy as np

    from metricslam.depth.model import DepthModel
    from metricslam.errors import ImageError

    bgr = cv2.imread(str(args.image), cv2.IMREAD_UNCHANGED)
    if bgr is None:
        raise ImageError(f"cannot read image {args.image}: give a PNG or JPEG file")
    if bgr.dtype == np.uint16:
        bgr = (bgr >> 8).astype(np.uint8)
    if bgr.ndim == 3 and bgr.shape[2] == 4:
        bgr = bgr[:, :, :3]
    image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB) if bgr.ndim == 3 else bgr
    model = DepthModel.load(args.model, threads=args.threads)
    result = model.predict_inv_depth(image, args.fx)
    depth_m = result.depth_m()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.save(out, depth_m)
    if args.png:
        inv = result.inv_depth_per_m
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
