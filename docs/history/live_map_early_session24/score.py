"""score.py SESSIONS.json DIR TAG [TAG...]: live map-frame RMSE % of path per session (session 22's metric) and final."""
import json, sys
from pathlib import Path
import numpy as np
from metricslam.trajectory.io import read_kitti_poses
from metricslam.geometry.align import align_trajectory
import os
EXCL = bool(os.environ.get("EXCL"))
sj, D, tags = sys.argv[1], Path(sys.argv[2]), sys.argv[3:]
res = {t: [] for t in tags}
hdr = "| session | " + " | ".join(f"{t} live % (max) / final %" for t in tags) + " |"
print(hdr); print("|---" * (len(tags) + 1) + "|")
for s in json.loads(Path(sj).read_text()):
    s1 = read_kitti_poses(s["s1"]); cells = []
    for t in tags:
        f = D / f"{s['name']}.{t}.npz"
        if not f.is_file(): cells.append("—"); continue
        d = np.load(f); m = np.flatnonzero(d["is_map"])
        if s["kind"] == "real":
            idx = m[(s["offset"] + m < len(s1)) & (s["offset"] + m >= 0)]; ref = s1[s["offset"] + idx, :3, 3]
            path = float(np.sum(np.linalg.norm(np.diff(ref, axis=0), axis=1)))
        else:
            gt = read_kitti_poses(s["truth"]); a = np.arange(60)
            if EXCL:
                bad = set(json.loads(Path(s["s1"].replace(".txt", ".json")).read_text())["pose_invalid_frame_indices"]); a = np.array([i for i in a if i not in bad])
            T, _ = align_trajectory(gt[a], s1[a], with_scale=False)
            idx = m; ref = gt[s["offset"] + idx, :3, 3] @ T[:3, :3].T + T[:3, 3]
            path = float(np.sum(np.linalg.norm(np.diff(gt[s["offset"] + idx, :3, 3], axis=0), axis=1)))
        if len(idx) < 2: cells.append("not in map"); continue
        e = np.linalg.norm(d["live"][idx, :3, 3] - ref, axis=1)
        ef = np.linalg.norm(d["final_map"][idx, :3, 3] - ref, axis=1)
        live, mx, fin = 100*np.sqrt(np.mean(e**2))/path, 100*e.max()/path, 100*np.sqrt(np.nanmean(ef**2))/path
        res[t].append((s["name"], live, fin, int(d["first_map_frame"])))
        cells.append(f"{live:.2f} ({mx:.1f}) / {fin:.2f} [f{int(d['first_map_frame'])}]")
    print(f"| {s['name']} | " + " | ".join(cells) + " |")
for t in tags:
    r = res[t]
    print(f"{t}: n={len(r)} mean live {np.mean([x[1] for x in r]):.3f} % final {np.mean([x[2] for x in r]):.3f} %")
