"""Score rule_live_map_scale_session22.md: live map-frame RMSE % per session, baseline vs candidate."""
import json
from pathlib import Path
import numpy as np
from metricslam.trajectory.io import read_kitti_poses
from metricslam.geometry.align import align_trajectory
V = Path("/tmp/s22/vlive")
rows = []
for s in json.loads((V / "sessions.json").read_text()):
    s1 = read_kitti_poses(s["s1"]); r = {"name": s["name"]}
    for tag in ("base", "cand"):
        f = V / f"{s['name']}.{tag}.npz"
        if not f.is_file():
            r[tag] = None; continue
        d = np.load(f); L = d["live"]; m = np.flatnonzero(d["is_map"])
        if s["kind"] == "real":
            idx = m[s["offset"] + m < len(s1)]
            ref = s1[s["offset"] + idx, :3, 3]
            path = float(np.sum(np.linalg.norm(np.diff(ref, axis=0), axis=1)))
        else:
            gt = read_kitti_poses(s["truth"])
            T, _ = align_trajectory(gt[:60], s1[:60], with_scale=False)  # truth -> map (session 1), rigid
            idx = m
            ref = gt[s["offset"] + idx, :3, 3] @ T[:3, :3].T + T[:3, 3]
            path = float(np.sum(np.linalg.norm(np.diff(gt[s["offset"] + idx, :3, 3], axis=0), axis=1)))
        e = np.linalg.norm(L[idx, :3, 3] - ref, axis=1)
        r[tag] = dict(pct=100 * float(np.sqrt(np.mean(e ** 2))) / path, max_pct=100 * float(e.max()) / path,
                      first=int(d["first_map_frame"]), n=len(idx), S_final=d["S_final"].tolist())
    rows.append(r)
print("| session | first map frame base/cand | frames | live RMSE % base | cand | diff | max % base / cand | same final S |")
print("|---|---|---|---|---|---|---|---|")
both = []
for r in rows:
    b, c = r["base"], r["cand"]
    if not (b and c):
        print(f"| {r['name']} | {b and b['first']} / {c and c['first']} | — | — | — | — | — | — |"); continue
    both.append((b["pct"], c["pct"]))
    same = np.allclose(b["S_final"], c["S_final"], atol=1e-9)
    print(f"| {r['name']} | {b['first']} / {c['first']} | {b['n']} | {b['pct']:.3f} | {c['pct']:.3f} | {c['pct'] - b['pct']:+.3f} | "
          f"{b['max_pct']:.2f} / {c['max_pct']:.2f} | {same} |")
b, c = np.array(both).T
print(f"\nmean over {len(both)} sessions: base {b.mean():.3f} %, cand {c.mean():.3f} %; worst increase {max(c - b):+.3f} points")
