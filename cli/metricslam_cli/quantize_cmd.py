"""``metricslam quantize MODEL.onnx --calib-images DIR_OR_GLOB [--calib-images ...] --out OUT.onnx``.

Static int8 quantization of a float32 depth model (onnxruntime; per-channel int8 weights, uint8
activations calibrated on images preprocessed as at inference). The output keeps the model's
contract and adds ``weights_precision = int8-static`` and ``calibration_data``; load it anywhere
a model is taken (``--model OUT.onnx``). See docs/depth_quantization.md.

Calibration images must be TRAINING images of the model (for the shipped models: KITTI odometry
01/03 and runs/synth_train worlds). Never calibrate on an evaluation set (KITTI 06,
kitti_raw_lidar): that leaks the test images into the model.

Example (the shipped depth_l3_int8.onnx, the default model since it runs ~2x faster)::

    metricslam quantize shared/metricslam/models/depth_l3.onnx \\
        --calib-images ../shared/data/kitti_odometry/sequences/01 \\
        --calib-images 'runs/synth_train/w20[0-4]*/image_0/000000.png' --stride 3 \\
        --out shared/metricslam/models/depth_l3_int8.onnx

``--calib`` was this option's former name; everywhere else ``--calib`` is a camera calibration
YAML, so it was renamed. ``--calib`` still works in this release, with a warning.
"""

from __future__ import annotations

import argparse
import logging
import warnings

log = logging.getLogger("metricslam.quantize")

#: path parts of the evaluation sets that must never calibrate a model.
EVALUATION_MARKERS = ("kitti_raw_lidar", "sequences/06")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("quantize", help="static int8 copy of a depth model (~2x faster on CPU)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="float32 metricslam depth model (ONNX; the shipped one is "
                                 "metricslam/models/depth_l3.onnx, not the int8 default)")
    p.add_argument("--calib-images", action="append", metavar="DIR_OR_GLOB",
                   help="calibration images (required), TRAINING data only (never KITTI 06 or kitti_raw_lidar): a "
                        "KITTI-layout sequence folder (its image_0/), a folder of images, an image file or a "
                        "quoted glob of them; repeat for more sources")
    p.add_argument("--calib", dest="calib_deprecated", action="append", metavar="DIR_OR_GLOB",
                   help="deprecated name of --calib-images (warns; removed in the next release)")
    p.add_argument("--stride", type=int, default=1, help="every N-th image of each folder (default 1)")
    p.add_argument("--max-images", type=int, help="at most N calibration images, evenly spaced")
    p.add_argument("--format", choices=["QDQ", "QOperator"], default="QDQ",
                   help="QDQ (standard ONNX ops, default) or QOperator (onnxruntime-only ops)")
    p.add_argument("--reduce-range", action="store_true",
                   help="7-bit weights: for x86 CPUs without VNNI (AVX2 only), where 8-bit products can saturate")
    p.add_argument("--out", required=True, help="output ONNX file")
    p.add_argument("--check", action="append", metavar="DIR_OR_GLOB",
                   help="held-out images (any data, e.g. KITTI 06) on which to report the int8 output's "
                        "difference from float32: |log(int8/fp32)| median, p95, max; repeatable")
    p.set_defaults(func=run)
    return p


def calibration_sources(args: argparse.Namespace) -> list[str]:
    """The ``--calib-images`` sources, and those of the deprecated ``--calib`` (with a
    :class:`FutureWarning`, which Python shows by default).

    Raises:
        ConfigError: neither was given.
    """
    from metricslam.errors import ConfigError

    sources = list(args.calib_images or [])
    if args.calib_deprecated:
        warnings.warn("metricslam quantize --calib is deprecated (everywhere else --calib is a camera "
                      "calibration YAML): use --calib-images; --calib will be removed in the next release",
                      FutureWarning, stacklevel=2)
        sources += args.calib_deprecated
    if not sources:
        raise ConfigError("no calibration images: pass --calib-images DIR_OR_GLOB (training images of the model)")
    return sources


def run(args: argparse.Namespace) -> int:
    from metricslam.depth.model import DepthModel
    from metricslam.depth.quantize import (
        QuantizeConfig,
        compare_models,
        find_images,
        quantize_model,
    )

    images = find_images(calibration_sources(args), stride=args.stride, max_images=args.max_images)
    suspicious = sorted({str(p.parent) for p in images
                         if any(m in p.resolve().as_posix() for m in EVALUATION_MARKERS)})
    if suspicious:
        log.warning("calibration images from %s look like an evaluation set: calibrate on training "
                    "images only, or the evaluation of this model is no longer held out", suspicious)
    config = QuantizeConfig(quant_format=args.format, reduce_range=args.reduce_range)
    result = quantize_model(args.model, args.out, images, config)
    size_mb = result.out_path.stat().st_size / 1e6
    print(f"{result.out_path}: {result.contract.weights_precision} model {result.contract.model_id}, "
          f"{size_mb:.1f} MB, calibrated on {result.n_images} images")
    if args.check:
        held_out = find_images(args.check)
        agreement = compare_models(DepthModel.load(args.model), DepthModel.load(result.out_path), held_out)
        print(f"int8 vs float32 on {agreement.n_images} images: |log(d_int8 / d_fp32)| median "
              f"{agreement.median:.4f}, p95 {agreement.p95:.4f}, max {agreement.max:.4f}")
    return 0
