"""Upper bound of the learned-scale pipeline: the same SLAM with a *stereo* depth source.

Separates what the global graph and the warp can do from what the depth network delivers:
the depth source is replaced by OpenCV SGBM on the rectified stereo pair (metric inverse depth,
pooled to the network's 32x64 grid by the median of valid disparities per cell). Everything
else — VO, Sim(3) graph, per-keyframe scale factors, loops, warp — is ``metricslam run``'s
default. This is NOT the method (it uses the right camera); it is the ceiling the network can
approach.

Example::

    .venv/bin/python bench/scale_upper_bound.py --seq kitti06=/work/shared/data/kitti_odometry/sequences/06:/work/shared/data/kitti_odometry/poses/06.txt \\
        --out bench/results/scale_upper_bound
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from machine import describe, write_results
from metricslam.datasets.kitti import KittiOdometry
from metricslam.slam.backend_factory import make_backend
from metricslam.slam.pipeline import SlamPipeline
from metricslam.slam.vo.config import VOConfig
from metricslam.trajectory.io import write_kitti_poses


class StereoDepthSource:
    """``DepthSource`` from SGBM on the stereo pair (right images registered by image hash)."""

    def __init__(self, baseline_m: float, grid_hw: tuple[int, int] = (32, 64)) -> None:
        self.baseline_m = baseline_m
        self.grid_hw = grid_hw
        self.right: dict[str, np.ndarray] = {}

    @staticmethod
    def _key(image: np.ndarray) -> str:
        return hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=16).hexdigest()

    def register(self, left: np.ndarray, right: np.ndarray) -> None:
        self.right[self._key(left)] = right

    def inv_depth_map(self, image: np.ndarray, camera) -> np.ndarray:
        right = self.right[self._key(image)]
        sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=7, P1=8 * 49,
                                     P2=32 * 49, uniquenessRatio=10)
        disp = sgbm.compute(image, right).astype(np.float32) / 16.0
        h, w = self.grid_hw
        H, W = disp.shape
        out = np.zeros((h, w), np.float32)
        for i in range(h):
            for j in range(w):
                cell = disp[i * H // h:(i + 1) * H // h, j * W // w:(j + 1) * W // w]
                valid = cell[cell >= 1.0]
                out[i, j] = np.median(valid) if valid.size > 10 else 0.0
        return out / (camera.fx_px * self.baseline_m)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, metavar="NAME=SEQ_DIR:GT.txt")
    p.add_argument("--out", help="write OUT.md and OUT.json")
    args = p.parse_args(argv)
    rows = []
    work = Path(tempfile.mkdtemp(prefix="scale_bound_"))
    for spec in args.seq:
        name, rest = spec.split("=", 1)
        seq_dir, gt = rest.rsplit(":", 1)
        seq = KittiOdometry(seq_dir, gt)
        src = StereoDepthSource(seq.baseline_m)
        pipe = SlamPipeline(seq.camera, VOConfig.preset("kitti"),
                            backend=make_backend(seq.camera, use_scale=True, depth_source=src))
        t0 = time.perf_counter()
        for i in range(len(seq)):
            f = seq[i]
            src.register(f.image, f.image_right)
            pipe.process(f)
        pipe.close()
        wall = time.perf_counter() - t0
        est = work / f"{name}.txt"
        write_kitti_poses(est, np.array([e.T_world_cam for e in pipe.trajectory()]))
        out_json = work / f"{name}_eval.json"
        subprocess.run([sys.executable, "-m", "metricslam.cli.main", "eval", "--gt", gt, "--est", str(est),
                        "--json", str(out_json)], check=True, capture_output=True)
        m = json.loads(out_json.read_text())
        rows.append({"name": name, "metrics": m, "backend": pipe.stats().get("backend", {}),
                     "fps_incl_sgbm": len(seq) / wall})
        print(json.dumps({"name": name, "scale_error_pct": m["scale_error_pct"], "ate_rmse_m": m["ate_rmse_m"],
                          "t_rel_pct": m["t_rel_pct"]}), flush=True)
    if args.out:
        machine = describe()
        lines = ["# Upper bound: the same SLAM with stereo (SGBM) depth instead of the network", "",
                 f"Command: `.venv/bin/python {' '.join(sys.argv)}`  ", f"Machine: {machine}", "",
                 "| run | path m | scale err % | ATE SE(3) m | ATE % path | ATE Sim(3) m | t_rel % |",
                 "| --- | --- | --- | --- | --- | --- | --- |"]
        for r in rows:
            m = r["metrics"]
            lines.append(f"| {r['name']} (stereo depth) | {m['path_length_m']:.0f} | {m['scale_error_pct']:.2f} | "
                         f"{m['ate_rmse_m']:.2f} | {100 * m['ate_rmse_m'] / m['path_length_m']:.2f} | "
                         f"{m['ate_rmse_sim3_m']:.2f} | {m['t_rel_pct']:.2f} |")
        write_results(args.out, {"rows": rows, "machine": machine, "command": " ".join(sys.argv)},
                      "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
