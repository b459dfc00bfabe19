"""Held-out validation of own-map relocalization after tracking loss (rule_segment_reloc_session23.md).

Usage: PYTHONPATH=<tree>/shared:<tree>/cli:<tree>:<tree>/services/slam python val.py TAG OUT.jsonl
"""
import json, shutil, sys
from pathlib import Path
import numpy as np
from bench.maps import run, RENDERED, _ate_se3_m
from metricslam.synth.scene import generate_sequence
from metricslam.trajectory.io import read_kitti_poses
from metricslam.geometry.align import align_trajectory, apply_to_poses

SRC, WORK = Path("/tmp/s23/val/src"), Path("/tmp/s23/val/run")
RAW = Path("/work/shared/data/kitti_raw_stereo")
K13, K01, K1405 = (RAW / "sequences" / n for n in ("2011_09_26_drive_0013", "2011_09_26_drive_0001", "2011_09_26_residential_1405"))
K13_POSES = RAW / "poses" / "2011_09_26_drive_0013.txt"
SEEDS = list(range(155, 165))


def world(seed, n=300):
    d = SRC / f"loop{n}_{seed}"
    if not (d / "poses" / "00.txt").is_file():
        generate_sequence(d, n, seed=seed, size=(620, 188), path="loop")
    return d


def compose(name, parts):
    """parts: [(folder, frames, poses file or None)] -> one KITTI-layout folder, re-timed at 10 Hz."""
    dst = WORK / name
    if (dst / "times.txt").is_file():
        return dst
    shutil.rmtree(dst, ignore_errors=True)
    for sub in ("image_0", "image_1"):
        (dst / sub).mkdir(parents=True)
    shutil.copy(parts[0][0] / "calib.txt", dst / "calib.txt")
    j, lines, have, times, t = 0, [], True, [], -0.1
    for part in parts:  # (folder, frames, poses[, seconds that pass before the part's first frame])
        folder, frames, poses = part[:3]
        t += part[3] if len(part) > 3 else 0.0
        pl = poses.read_text().splitlines() if poses is not None and poses.is_file() else None
        have &= pl is not None
        for i in frames:
            for sub in ("image_0", "image_1"):
                shutil.copy(folder / sub / f"{i:06d}.png", dst / sub / f"{j:06d}.png")
            if pl is not None:
                lines.append(pl[i])
            j, t = j + 1, t + 0.1
            times.append(t)
    (dst / "times.txt").write_text("".join(f"{x:.6f}\n" for x in times))
    if have:
        (dst / "poses").mkdir()
        (dst / "poses" / "00.txt").write_text("".join(f"{x}\n" for x in lines))
    return dst


def per_seed(seeds, gap_s=None, short_s=None):
    """Kidnap, short-gap and foreign scenarios on the 300-frame loops of ``seeds`` (the last one's
    foreign world is the first's); ``gap_s`` / ``short_s``: seconds that pass over the gaps (None:
    the frames are re-timed at 10 Hz, the gap takes no time)."""
    g, gs = (() if gap_s is None else (gap_s,)), (() if short_s is None else (short_s,))
    out = []
    for s in seeds:
        w = world(s)
        p = w / "poses" / "00.txt"
        nxt = s + 1 if s < seeds[-1] else seeds[0]
        out.append((f"kidnap {s}", "kidnap", [(w, range(0, 120), p), (w, range(265, 300), p, *g)], 120, False))
        out.append((f"short gap {s}", "short", [(w, range(0, 100), p), (w, range(108, 300), p, *gs)], 100, False))
        out.append((f"foreign {s}->{nxt}", "foreign", [(w, range(0, 150), None), (world(nxt), range(150, 300), None, *g)],
                    150, False))
    return out


def loops150(seeds, timed=False):
    """150-frame loops of ``seeds`` with frames 40-46 and, separately, 90-98 dropped (``timed``:
    the dropped frames' time passes)."""
    out = []
    for s in seeds:
        w = world(s, 150)
        p = w / "poses" / "00.txt"
        for a, b in ((40, 47), (90, 99)):
            t = (0.1 * (b - a),) if timed else ()
            out.append((f"loop150 {s} drop {a}-{b - 1}", "short", [(w, range(0, a), p), (w, range(b, 150), p, *t)], a, False))
    return out


def scenarios():
    out = per_seed(SEEDS)
    out.append(("real revisit 0013", "kidnap", [(K13, range(0, 100, 2), K13_POSES), (K13, range(21, 80, 2), K13_POSES)], 50, True))
    out.append(("real foreign 0013->0001", "foreign", [(K13, range(0, 100, 2), None), (K01, range(0, 54), None)], 50, True))
    out.append(("real foreign 0013->1405", "foreign", [(K13, range(0, 100, 2), None), (K1405, range(0, 80), None)], 50, True))  # not runnable: 1405 is JPEG, 1242x375
    return out


def main(tag, out_path, make_scenarios=None):
    done = set()
    if Path(out_path).is_file():
        done = {json.loads(x)["name"] for x in Path(out_path).read_text().splitlines()}
    for name, kind, parts, n1, kitti in (make_scenarios or scenarios)():
        if name in done:
            continue
        seq = compose(name.replace(" ", "_").replace(">", ""), parts)
        out = WORK / f"{seq.name}_{tag}.txt"
        flags = ("--preset", "kitti") if kitti else ("--model", RENDERED)
        code, st = run(seq, out, *flags)
        b = st.get("backend", {}) if st else {}
        r = {"name": name, "kind": kind, "tag": tag, "code": code, "losses": st and st["tracking_losses"],
             "relocalized_segments": b.get("relocalized_segments"), "loops": b.get("loops")}
        if (seq / "poses" / "00.txt").is_file() and st:
            gt, est = read_kitti_poses(seq / "poses" / "00.txt"), read_kitti_poses(out)
            bad = set(st["pose_invalid_frame_indices"])
            ok = [i for i in range(len(gt)) if i not in bad]
            pre, post = [i for i in ok if i < n1], [i for i in ok if i >= n1]
            S, _ = align_trajectory(est[pre], gt[pre])
            d = np.linalg.norm(apply_to_poses(S, est)[post, :3, 3] - gt[post, :3, 3], axis=1)
            r.update({"ate_all_m": _ate_se3_m(est[ok], gt[ok]), "post_err_mean_m": float(d.mean()),
                      "post_err_max_m": float(d.max()), "n_post": len(post)})
        print(json.dumps(r), flush=True)
        with open(out_path, "a") as f:
            f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
