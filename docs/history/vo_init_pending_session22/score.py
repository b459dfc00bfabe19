"""Score docs/history/rule_vo_init_pending_session22.md: python score.py /tmp/s22/vinit"""
import json, sys
from pathlib import Path
import numpy as np
from metricslam.geometry.align import align_trajectory
from metricslam.trajectory.io import read_kitti_poses

V = Path(sys.argv[1])
D = Path("/work/shared/data")
GT = {"kitti06": D / "kitti_odometry/poses/06.txt", "kitti01": D / "kitti_odometry/poses/01.txt",
      "raw0013": D / "kitti_raw_stereo/poses/2011_09_26_drive_0013.txt"}


def ang_deg(R):
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def step_err(est, gt, k):
    Re = est[k - 1, :3, :3].T @ est[k, :3, :3]
    Rg = gt[k - 1, :3, :3].T @ gt[k, :3, :3]
    return ang_deg(Rg.T @ Re)


def ate(est, gt, valid, scale):
    _, al = align_trajectory(est[valid], gt[valid], with_scale=scale)
    return float(np.sqrt(np.mean(np.sum((al[:, :3, 3] - gt[valid, :3, 3]) ** 2, axis=1))))


rows, steps_b, steps_c = [], [], []
names = sorted({p.name.split(".")[0] for p in V.glob("*.cand.txt")})
for n in names:
    gt = read_kitti_poses(GT.get(n, V / "worlds" / n / "poses" / "00.txt"))
    lb = (V / f"{n}.base.txt").read_text().splitlines()
    lc = (V / f"{n}.cand.txt").read_text().splitlines()
    jb, jc = (json.loads((V / f"{n}.{w}.json").read_text()) for w in ("base", "cand"))
    eb, ec = read_kitti_poses(V / f"{n}.base.txt"), read_kitti_poses(V / f"{n}.cand.txt")
    bad = set(jb["pose_invalid_frame_indices"]) | set(jc["pose_invalid_frame_indices"])
    changed = [k for k in range(len(lb)) if lb[k] != lc[k]]
    valid = [k for k in range(len(gt)) if k not in bad]
    kitti = n in GT
    touch = sorted({k for c in changed for k in (c, c + 1) if 1 <= k < len(gt) and k not in bad and k - 1 not in bad})
    sb = [step_err(eb, gt, k) for k in touch]
    sc = [step_err(ec, gt, k) for k in touch]
    steps_b += sb; steps_c += sc
    first = [k for k in range(1, 16) if k not in bad and k - 1 not in bad]
    wrong = max(step_err(ec, gt, k) for k in first) > 2.0 if first else False
    flagged = any(r[0] <= 15 for r in jc.get("vo_suspect_ranges", []))
    rows.append(dict(name=n, changed=len(changed), changed_frames=changed[:12], ate_b=ate(eb, gt, valid, not kitti),
                     ate_c=ate(ec, gt, valid, not kitti), step_b=float(np.mean(sb)) if sb else None,
                     step_c=float(np.mean(sc)) if sc else None, wrong_start=wrong, flagged=flagged,
                     invalid_b=len(jb["pose_invalid_frame_indices"]), invalid_c=len(jc["pose_invalid_frame_indices"]),
                     suspect_c=jc.get("vo_suspect_ranges"), suspect_b=jb.get("vo_suspect_ranges")))
print("| run | changed frames | ATE base m | ATE cand m | change % | step rot err base / cand deg | wrong start | flagged |")
print("|---|---|---|---|---|---|---|---|")
for r in rows:
    ch = 100 * (r["ate_c"] / r["ate_b"] - 1)
    st = "—" if r["step_b"] is None else f"{r['step_b']:.2f} / {r['step_c']:.2f}"
    print(f"| {r['name']} | {r['changed']} {r['changed_frames']} | {r['ate_b']:.4f} | {r['ate_c']:.4f} | {ch:+.2f} | {st} | "
          f"{r['wrong_start']} | {r['flagged']} {r['suspect_c'] if r['flagged'] else ''} |")
sim = [r for r in rows if r["name"] not in GT]
print()
print(f"(2) mean per-step rotation error over steps touching changed frames: base {np.mean(steps_b):.3f} deg, "
      f"cand {np.mean(steps_c):.3f} deg ({len(steps_b)} steps)")
print(f"(3) worst ATE change (rendered): {max(100 * (r['ate_c'] / r['ate_b'] - 1) for r in sim):+.2f} %; KITTI: "
      + ", ".join(f"{r['name']} {100 * (r['ate_c'] / r['ate_b'] - 1):+.2f} %" for r in rows if r['name'] in GT))
good = [r for r in sim if not r["wrong_start"]]
wrong = [r for r in sim if r["wrong_start"]]
print(f"(4) flagged among {len(good)} runs without a wrong start: {sum(r['flagged'] for r in good)}; KITTI flagged: "
      f"{sum(r['flagged'] for r in rows if r['name'] in GT)}")
print(f"(5) wrong starts: {len(wrong)}, flagged {sum(r['flagged'] for r in wrong)}: {[r['name'] for r in wrong]}")
print(f"frames without a pose: base {sum(r['invalid_b'] for r in sim)}, cand {sum(r['invalid_c'] for r in sim)}")
