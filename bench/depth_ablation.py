"""Ablation of the paper's two training claims, on held-out data.

Compares checkpoints trained with the same seed, data and learning rate for the same number of
steps: the full loss (D1..D6 + supervision), without the block-matching supervision term, and
without the fine-to-coarse terms (losses only at D3..D6). Each checkpoint is exported to ONNX and
scored by ``bench/depth_accuracy.py``'s metrics on kitti_raw_lidar (LiDAR) and on the held-out
KITTI stereo sequence (SGBM, textured pixels).

Example::

    .venv/bin/python -m bench.depth_ablation \\
        --run full=runs/depth_no06/step_000500.pt \\
        --run no_supervision=runs/ablation_no_sup/final.pt \\
        --run no_fine_to_coarse=runs/ablation_no_f2c/final.pt \\
        --out bench/results/depth_ablation
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from bench import depth_accuracy
from bench.machine import command_line
from metricslam.depth import DepthModel


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, help="LABEL=CHECKPOINT.pt (repeat)")
    p.add_argument("--data", default="../shared/data")
    p.add_argument("--stereo-seq", default="06")
    p.add_argument("--frame-step", type=int, default=1)
    p.add_argument("--out", help="write OUT.md and OUT.json")
    args = p.parse_args(argv)
    from metricslam_train.export import export_checkpoint

    ns = argparse.Namespace(frame_step=args.frame_step, min_depth_m=1.0, max_depth_m=80.0, camera_height_m=1.65,
                            texture_min=40.0, slam_min_depth_m=10.0)
    data = Path(args.data)
    results, rows = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.run:
            label, ckpt = spec.split("=", 1)
            onnx_path = Path(tmp) / f"{label}.onnx"
            export_checkpoint(ckpt, onnx_path)
            model = DepthModel.load(onnx_path)
            lidar = depth_accuracy.evaluate_lidar(model, data / "kitti_raw_lidar", ns)
            stereo = depth_accuracy.evaluate_stereo(model, data / "kitti_odometry" / "sequences" / args.stereo_seq, ns)
            results[label] = {"checkpoint": ckpt, "lidar": lidar["model"], "stereo": stereo["model"]}
            for name, m in (("kitti_raw_lidar", lidar["model"]), (f"KITTI {args.stereo_seq} SGBM", stereo["model"])):
                rows.append(f"| {label} | {name} | {m['median_ratio']:.3f} | {m['abs_rel']:.3f} | {m['rmse_m']:.2f} | "
                            f"{m['delta_1_25']:.3f} |")
    table = "\n".join(["| run | set | median pred/true | abs-rel | RMSE (m) | δ<1.25 |",
                       "| --- | --- | --- | --- | --- | --- |", *rows])
    print(table)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.with_suffix(".json").write_text(json.dumps(results, indent=2))
        out.with_suffix(".md").write_text(
            f"# Depth training ablation\n\nCommand: `{command_line('bench.depth_ablation', argv)}`\n\n"
            + "".join(f"- `{k}`: {v['checkpoint']}\n" for k, v in results.items()) + f"\n{table}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
