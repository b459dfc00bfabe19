"""Tracking-loss scenario: loop300 with a gap of frames dropped; ATE per part."""
import json, shutil, sys, numpy as np
from pathlib import Path
from metricslam.trajectory.io import read_kitti_poses
from metricslam.geometry.align import align_trajectory
from metricslam_cli.main import main as cli
import os
src = Path(os.environ.get("GAP_SRC", "/tmp/maps_bench17/loop300"))
a, b = int(sys.argv[1]), int(sys.argv[2])  # drop frames a..b-1
tag = sys.argv[3] if len(sys.argv) > 3 else "base"
dst = Path(f"/tmp/gap_{src.name}_{a}_{b}")
N = len((src / "times.txt").read_text().split())
keep = [i for i in range(N) if not a <= i < b]
if not (dst / "times.txt").is_file():
    dst.mkdir(exist_ok=True); shutil.copy(src / "calib.txt", dst / "calib.txt")
    for sub in ("image_0", "image_1", "depth_0"):
        if (src / sub).is_dir():
            (dst / sub).mkdir(exist_ok=True)
            for j, i in enumerate(keep): shutil.copy(src / sub / f"{i:06d}.png", dst / sub / f"{j:06d}.png")
    t = (src / "times.txt").read_text().split(); (dst / "times.txt").write_text("".join(t[i] + "\n" for i in keep))
    p = (src / "poses" / "00.txt").read_text().splitlines(); (dst / "poses").mkdir(exist_ok=True)
    (dst / "poses" / "00.txt").write_text("".join(p[i] + "\n" for i in keep))
out = Path(f"/tmp/gap_{src.name}_{a}_{b}_{tag}.txt")
cli(["run", str(dst), "--out", str(out), "--json", str(out.with_suffix(".json")), "--deterministic", "--no-progress", *sys.argv[4:]])
st = json.loads(out.with_suffix(".json").read_text())
est = read_kitti_poses(out); gt = read_kitti_poses(dst / "poses" / "00.txt")
bad = set(st.get("pose_invalid_frame_indices", []))
ok = np.array([i for i in range(len(gt)) if i not in bad and i < len(est)])
T, al = align_trajectory(est[ok], gt[ok], with_scale=False)
err = np.linalg.norm(al[:, :3, 3] - gt[ok, :3, 3], axis=1)
pre, post = ok < a, ok >= a
T2, _ = align_trajectory(est[ok[pre]], gt[ok[pre]], with_scale=False)
p2 = est[ok, :3, 3] @ T2[:3, :3].T + T2[:3, 3]
e2 = np.linalg.norm(p2 - gt[ok, :3, 3], axis=1)
print(f"aligned on before-gap frames: before {np.sqrt(np.mean(e2[pre]**2)):.2f} m, after {np.sqrt(np.mean(e2[post]**2)):.2f} m, last {e2[-1]:.2f} m")
print("backend", {k: st["backend"].get(k) for k in ("segment_links", "segment_loops", "loops_accepted", "loops_verified")} if "backend" in st else list(st))
print(f"frames {len(gt)} invalid {len(bad)}; ATE SE3 all {np.sqrt(np.mean(err**2)):.2f} m; before gap {np.sqrt(np.mean(err[pre]**2)):.2f}; after {np.sqrt(np.mean(err[post]**2)):.2f}; max {err.max():.2f}")
