"""Saved maps (docs/maps.md): size and save/load time per 1,000 keyframes; relocalization success,
latency and map-frame accuracy on a rendered revisit and on KITTI odometry 06.

* **Size and I/O**: the rendered revisit's session-1 map, its keyframes tiled (new ids, same
  content) to 1,000 keyframes, saved and loaded ``--repeats`` times (median wall time; bytes).
* **Rendered revisit** (``tests/test_map_relocalize.py``'s setup): loop render (300 frames, seed 3,
  620x188); session 1 = frames 0-149 ``--save-map``; session 2 = frames 190-299 ``--map`` (starts
  outside the map). The frame it relocalized at vs. the first within 10 m of the mapped path; map-frame
  RMSE against the truth rigidly aligned to session 1 on the revisited stretch, session 1's own RMSE
  there, each session's shape (``_sim3``: Sim(3)-aligned) and scale (truth per estimate); the scale of
  ``S_map_world``; a map of another world (seed 5) must not relocalize. Run twice: learned scale
  (default), and learned + road-height scale (``--scale-sources learned,ground --mount-height 1.65``,
  the renderer's camera height; docs/ground_scale.md), a vehicle's configuration.
* **KITTI raw 0013** (issue #34's real target, :func:`kitti_raw_0013`): sessions 0-99 / 40-143,
  overlap error against session 1 and ATE against the GPS/INS truth, a map of raw 0001 that
  must not relocalize it (``--data``: the shared data folder).
* **KITTI 06** (51 frames): session 1 = all frames ``--save-map``; session 2 = frames 10-50 and
  20-50 as their own folder ``--map`` (the same images from another start: a fair relocalization check,
  not a revisit). Reports the relocalized frame and, without any alignment, session 2's map-frame
  positions against session 1's for the same frames, in % of that stretch's path length.

Example::

    .venv/bin/python -m bench.maps --work /tmp/maps_bench --out bench/results/maps
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from bench.machine import command_line, publish
from metricslam.depth import RENDERED_MODEL_PATH
from metricslam.geometry import sim3
from metricslam.geometry.align import align_trajectory, apply_to_poses as sim3_apply
from metricslam.slam.map.format import SavedMap, load_map, save_map
from metricslam.trajectory.io import read_kitti_poses
from metricslam_cli.main import main as cli

KITTI06 = Path("../shared/data/kitti_odometry/sequences/06")
KITTI06_POSES = Path("../shared/data/kitti_odometry/poses/06.txt")


def cut(src: Path, dst: Path, start: int, stop: int, poses: Path | None = None, skip: range = range(0)) -> Path:
    """Frames ``start .. stop-1`` but ``skip`` of a KITTI-layout folder (PNG or JPEG) as a new folder,
    renumbered from 0 (``poses/00.txt`` cut from ``poses`` or from the source's own)."""
    dst.mkdir(parents=True, exist_ok=True)
    ext = "jpg" if (src / "image_0" / f"{start:06d}.jpg").is_file() else "png"
    frames = [i for i in range(start, stop) if i not in skip]
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    for sub in ("image_0", "image_1", "depth_0"):
        if (src / sub).is_dir():
            (dst / sub).mkdir(exist_ok=True)
            for j, i in enumerate(frames):
                shutil.copy(src / sub / f"{i:06d}.{ext}", dst / sub / f"{j:06d}.{ext}")
    times = (src / "times.txt").read_text().split()
    (dst / "times.txt").write_text("".join(f"{times[i]}\n" for i in frames))
    poses = poses or src / "poses" / "00.txt"
    if poses.is_file():
        (dst / "poses").mkdir(exist_ok=True)
        lines = poses.read_text().splitlines()
        (dst / "poses" / "00.txt").write_text("".join(f"{lines[i]}\n" for i in frames))
    return dst


#: rendered worlds run with the depth model for rendered worlds (the default is real streets only)
RENDERED = str(RENDERED_MODEL_PATH)


def run(seq: Path, out: Path, *flags: str) -> tuple[int, dict | None]:
    """``metricslam run``'s exit code and ``--json`` (None: it refused before writing one)."""
    js = out.with_suffix(".json")
    js.unlink(missing_ok=True)
    code = cli(["run", str(seq), "--out", str(out), "--json", str(js), "--deterministic", "--no-progress", *flags])
    return code, json.loads(js.read_text()) if js.is_file() else None


def tiled(saved: SavedMap, n_kf: int) -> SavedMap:
    """``saved`` with its keyframes (and their rows and features) repeated to ``n_kf``."""
    kf, lm, db = (saved.arrays[g] for g in ("keyframes", "landmarks", "loop_db"))
    n = len(kf["kf_id"])
    reps = -(-n_kf // n)
    step = int(kf["kf_id"].max()) + 1
    take = np.arange(n_kf)
    src = take % n
    shift = (take // n) * step
    keyframes = {k: v[src] for k, v in kf.items()}
    keyframes["kf_id"] = kf["kf_id"][src] + shift
    row_reps = [r for r in range(reps) if r * n < n_kf]
    counts = np.diff(db["feature_offsets"])
    per = {k: np.concatenate([v] * len(row_reps)) for k, v in db.items() if k.startswith("feature_") and k != "feature_offsets"}
    loop_db = {"vocabulary_words": db["vocabulary_words"], "vocabulary_idf": db["vocabulary_idf"],
               "bow_kf_id": np.concatenate([db["bow_kf_id"] + r * step for r in row_reps]),
               "bow_rows": np.concatenate([db["bow_rows"]] * len(row_reps)),
               "feature_offsets": np.concatenate([[0], np.cumsum(np.tile(counts, len(row_reps)))]).astype(np.int64),
               **per}
    landmarks = {"p_map_m": np.concatenate([lm["p_map_m"]] * len(row_reps)),
                 "obs_kf_id": np.concatenate([lm["obs_kf_id"] + r * step for r in row_reps]),
                 "obs_uv_px": np.concatenate([lm["obs_uv_px"]] * len(row_reps))}
    return SavedMap(saved.camera, saved.depth_model_id, saved.metric,
                    {"keyframes": keyframes, "landmarks": landmarks, "loop_db": loop_db}, saved.source)


def size_and_io(map_dir: Path, work: Path, repeats: int) -> dict:
    big = tiled(load_map(map_dir), 1000)
    save_s, load_s = [], []
    for _ in range(repeats):
        target = work / "map1000"
        t0 = time.perf_counter()
        save_map(big, target)
        save_s.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        load_map(target)
        load_s.append(time.perf_counter() - t0)
    size = sum(p.stat().st_size for p in target.rglob("*") if p.is_file())
    return {"keyframes": big.n_keyframes, "bow_rows": int(len(big.arrays["loop_db"]["bow_kf_id"])),
            "features": int(len(big.arrays["loop_db"]["feature_uv_px"])), "bytes": size,
            "mb": size / 1e6, "save_s_median": statistics.median(save_s),
            "load_s_median": statistics.median(load_s), "repeats": repeats}


#: the rendered revisit's second configuration: the road-height scale beside the learned one
GROUND = ("--scale-sources", "learned,ground", "--mount-height", "1.65")


def rendered_revisit(work: Path, model: str = RENDERED, flags: tuple[str, ...] = (), tag: str = "") -> dict:
    from metricslam.synth.scene import generate_sequence

    src, w = work / "loop300", work / f"r{tag}"  # the worlds are shared, each run's files in ``w``
    if not (src / "poses" / "00.txt").is_file():
        generate_sequence(src, 300, seed=3, size=(620, 188), path="loop")
    flags = ("--model", model, *flags)
    s1, s2 = cut(src, w / "r1", 0, 150), cut(src, w / "r2", 190, 300)
    _, st1 = run(s1, w / "r1.txt", "--save-map", str(w / "r_map"), *flags)
    code, st2 = run(s2, w / "r2.txt", "--map", str(w / "r_map"), *flags)
    m = st2["map"]
    gt = read_kitti_poses(src / "poses" / "00.txt")
    skip = set(st1["pose_invalid_frame_indices"]) | set(st1["interpolated_frame_indices"])
    mapped = gt[[i for i in range(150) if i not in skip], :3, 3]  # entry: within 10 m of what the map holds
    entry = next(j for j in range(110) if np.min(np.linalg.norm(mapped - gt[190 + j, :3, 3], axis=1)) < 10)
    e1 = read_kitti_poses(w / "r1.txt")
    rev = [i for i in range(60) if i not in skip]
    (T, al), (S1, al1) = (align_trajectory(e1[rev], gt[rev], with_scale=w) for w in (False, True))  # map; shape
    out = {"exit_code": code, "relocalized": m["relocalized"], "first_localized_frame": m["first_localized_frame"],
           "entry_frame": entry, "matches": m["relocalization_matches"], "matches_used": m["matches_used"],
           "query_ms_mean": m["relocalization_query_ms_mean"], "session1_rmse_m": _rmse(al, gt[rev]),
           "session1_rmse_sim3_m": _rmse(al1, gt[rev]), "session1_truth_per_est": sim3.scale(S1)}
    if m["relocalized"]:
        e2 = read_kitti_poses(w / "r2.txt")
        f0 = m["first_localized_frame"]
        g2 = gt[190 + f0: 190 + f0 + len(e2)]
        S2, al2 = align_trajectory(e2, g2)  # session 2 against its own truth: shape, own scale
        path, rmse2 = float(np.sum(np.linalg.norm(np.diff(g2[:, :3, 3], axis=0), axis=1))), _rmse(sim3_apply(T, e2), g2)
        out.update({"session2_rmse_m": rmse2, "session2_path_m": path, "session2_rmse_pct_of_path": 100 * rmse2 / path,
                    "scale_map_per_session": sim3.scale(np.array(m["S_map_world"])),
                    "session2_rmse_sim3_own_m": _rmse(al2, g2), "session2_truth_per_est": sim3.scale(S2)})
    other = work / "other150"
    if not (other / "poses" / "00.txt").is_file():
        generate_sequence(other, 150, seed=5, size=(620, 188), path="loop")
    run(other, w / "o1.txt", "--save-map", str(w / "o_map"), *flags)
    code_o, st_o = run(s2, w / "r2o.txt", "--map", str(w / "o_map"), *flags)
    out["foreign_map"] = {"exit_code": code_o, "relocalized": st_o["map"]["relocalized"],
                          "matches": st_o["map"]["relocalization_matches"]}
    return out


def kitti06(work: Path, starts: tuple[int, ...] = (10, 20)) -> dict | None:
    """Session 1 on all 51 frames saves; session 2 on frames ``start``-50 of each start."""
    if not KITTI06.is_dir():
        return None
    run(KITTI06, work / "k1.txt", "--save-map", str(work / "k_map"))
    e1 = read_kitti_poses(work / "k1.txt")
    out = {}
    for start in starts:
        k2 = cut(KITTI06, work / f"k2_{start}", start, 51, KITTI06_POSES)
        code, st2 = run(k2, work / f"k2_{start}.txt", "--map", str(work / "k_map"))
        m = st2["map"]
        r = {"frames": 51 - start, "exit_code": code, "relocalized": m["relocalized"],
             "first_localized_frame": m["first_localized_frame"], "matches": m["relocalization_matches"],
             "matches_used": m["matches_used"], "query_ms_mean": m["relocalization_query_ms_mean"]}
        if m["relocalized"]:
            e2 = read_kitti_poses(work / f"k2_{start}.txt")
            f0 = m["first_localized_frame"]
            ref = e1[start + f0: start + f0 + len(e2), :3, 3]
            d = np.linalg.norm(e2[:, :3, 3] - ref, axis=1)
            path = float(np.sum(np.linalg.norm(np.diff(ref, axis=0), axis=1)))
            r.update({"localized_frames": len(e2), "vs_session1_mean_m": float(d.mean()),
                      "vs_session1_max_m": float(d.max()), "stretch_path_m": path,
                      "vs_session1_max_pct_of_path": 100 * float(d.max()) / path,
                      "scale_map_per_session": sim3.scale(np.array(m["S_map_world"]))})
        out[f"frames_{start}_50"] = r
    return out


def _rmse(est: np.ndarray, gt: np.ndarray) -> float:
    """Position RMSE (m) of two (N, 4, 4) pose arrays."""
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))


def _ate_se3_m(est: np.ndarray, gt: np.ndarray) -> float:
    """Position RMSE (m) after the best rigid (SE(3)) alignment of ``est`` to ``gt`` (N, 4, 4)."""
    return _rmse(align_trajectory(est, gt, with_scale=False)[1], gt)


def kitti_raw_0013(work: Path, data: Path) -> dict | None:
    """Issue #34's real revisit: KITTI raw 0013, session 1 = frames 0-99 ``--save-map``; session 2
    = frames 40-143 (renumbered from 0) ``--map`` (and ``--save-map``: the map extended by it).
    Session 2's map-frame positions on the overlap (frames 40-99) against session 1's, no
    alignment, in % of the overlap's GPS/INS path; ATE SE(3) against the GPS/INS truth of session
    2 and of a single run over 0-143 on the same frames; a map of raw 0001 must not relocalize it."""
    src = data / "kitti_raw_stereo" / "sequences" / "2011_09_26_drive_0013"
    poses = data / "kitti_raw_stereo" / "poses" / "2011_09_26_drive_0013.txt"
    other = data / "kitti_raw_stereo" / "sequences" / "2011_09_26_drive_0001"
    if not (src.is_dir() and poses.is_file()):
        return None
    gt = read_kitti_poses(poses)
    s1, s2 = cut(src, work / "k13_s1", 0, 100, poses), cut(src, work / "k13_s2", 40, 144, poses)
    kitti = ("--preset", "kitti")  # a cut folder has depth_0/ and poses/ beside its images: not a render
    run(s1, work / "k13_s1.txt", *kitti, "--save-map", str(work / "k13_map"))
    code, st2 = run(s2, work / "k13_s2.txt", *kitti, "--map", str(work / "k13_map"), "--save-map",
                    str(work / "k13_map_ext"))
    _, st_all = run(src, work / "k13_all.txt", *kitti)
    m = st2["map"]
    out = {"exit_code": code, "relocalized": m["relocalized"], "first_localized_frame": m["first_localized_frame"],
           "matches": m["relocalization_matches"], "matches_used": m["matches_used"],
           "query_ms_mean": m["relocalization_query_ms_mean"], "map_keyframes": m["map_keyframes"]}
    if m["relocalized"]:
        f0 = m["first_localized_frame"]
        e1, e2, e_all = (read_kitti_poses(work / f"k13_{n}.txt") for n in ("s1", "s2", "all"))
        frames = np.arange(40 + f0, 144)  # original frame of each line of session 2's file
        overlap = frames[frames < 100]
        d = np.linalg.norm(e2[:len(overlap), :3, 3] - e1[overlap, :3, 3], axis=1)
        path = float(np.sum(np.linalg.norm(np.diff(gt[overlap, :3, 3], axis=0), axis=1)))
        rmse, saved = float(np.sqrt(np.mean(d ** 2))), st2.get("map_saved", {})
        out.update({
            "overlap_frames": f"{int(overlap[0])}-{int(overlap[-1])}", "overlap_path_m": path,
            "overlap_vs_session1_rmse_m": rmse, "overlap_vs_session1_max_m": float(d.max()),
            "overlap_vs_session1_rmse_pct_of_path": 100 * rmse / path,
            "overlap_vs_session1_max_pct_of_path": 100 * float(d.max()) / path,
            "ate_se3_session2_m": _ate_se3_m(e2, gt[frames]),
            "ate_se3_single_run_same_frames_m": _ate_se3_m(e_all[frames], gt[frames]),
            "ate_se3_single_run_0_143_m": _ate_se3_m(e_all, gt), "ate_frames": f"{int(frames[0])}-143",
            "scale_map_per_session": sim3.scale(np.array(m["S_map_world"])),
            "extended_map_keyframes": saved.get("keyframes"),
            "extended_cross_session_factors": saved.get("extended", {}).get("cross_session_factors"),
            "single_run_frames": st_all.get("frames")})
    if other.is_dir():
        run(other, work / "k01.txt", *kitti, "--save-map", str(work / "k01_map"))
        code_o, st_o = run(s2, work / "k13_s2_on01.txt", *kitti, "--map", str(work / "k01_map"))
        out["foreign_map_0001"] = {"exit_code": code_o, "refused_before_run": st_o is None,
                                   "relocalized": bool(st_o and st_o["map"]["relocalized"]),
                                   "matches": st_o["map"]["relocalization_matches"] if st_o else None}
    return out


def _table(d: dict) -> list[str]:
    cols = list(d)
    keys = list(dict.fromkeys(k for c in cols for k in d[c]))
    return (["| | " + " | ".join(cols) + " |", "| --- |" + " --- |" * len(cols)]
            + [f"| {k} | " + " | ".join(_fmt(d[c].get(k, "")) for c in cols) + " |" for k in keys])


def _fmt(v) -> str:
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def _kv(d: dict) -> list[str]:
    return ["| | value |", "| --- | --- |"] + [f"| {k} | {_fmt(v)} |" for k, v in d.items()]


def render(r: dict, command: str, machine: str) -> str:
    io, rv, k = r["io"], r["rendered"], r["kitti06"]
    lines = ["# Saved maps: size, save/load time, relocalization", "",
             f"Command: `{command}`  ", f"Machine: {machine} (the load average says whether other jobs "
             "shared the CPU while it ran).", "", "## Size and I/O per 1,000 keyframes", "",
             f"{io['keyframes']} keyframes ({io['bow_rows']} loop-database rows, {io['features']} features): "
             f"**{io['mb']:.1f} MB**, save **{io['save_s_median']:.2f} s**, load **{io['load_s_median']:.2f} s** "
             f"(median of {io['repeats']}; checksums included).", "",
             "## Rendered revisit (session 2 starts outside the map)", "", *_kv(rv)]
    if "rendered_ground" in r:
        lines += ["", "## Rendered revisit, learned + road-height scale (`" + " ".join(GROUND) + "`)", "",
                  *_kv(r["rendered_ground"])]
    lines += ["", "## KITTI odometry 06 (session 1: all 51 frames; session 2: frames START-50 of the same "
              "drive, renumbered; its map-frame positions against session 1's, no alignment)", ""]
    lines += ["KITTI 06 not found; skipped."] if k is None else _table(k)
    k13 = r.get("kitti_raw_0013")
    lines += ["", "## KITTI raw 0013 (session 1: frames 0-99 saves; session 2: frames 40-143, renumbered, "
              "`--map` and `--save-map`; GPS/INS truth)", ""]
    lines += ["KITTI raw 0013 not found under --data; skipped."] if k13 is None else _kv(k13)
    live = r.get("live_0013")
    if live is not None:
        lines += ["", "## KITTI raw 0013 session 2 through the live stack (`up --map`, `replay --rate 10 "
                  "--max-in-flight 3`, `poses --trajectory`; bench/maps_live.py)", "", *_kv(live)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--out", default=None, help="results path stem (writes .json and .md)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rendered-model", default=RENDERED, help="depth model of the rendered worlds (default: RENDERED_MODEL_PATH)")
    ap.add_argument("--data", default="../shared/data", help="the shared data folder (kitti_raw_stereo/)")
    ap.add_argument("--only", choices=("kitti_raw_0013", "live_0013"), default=None,
                    help="run only this part and merge it into the existing --out JSON")
    ap.add_argument("--live", action="store_true",
                    help="also 0013 session 2 through `up --map` + `replay` + `poses --trajectory` (bench/maps_live.py)")
    args = ap.parse_args(argv)
    work = Path(args.work or tempfile.mkdtemp(prefix="maps_bench_"))
    work.mkdir(parents=True, exist_ok=True)
    earlier = None
    if args.only is not None:
        if not args.out or not Path(f"{args.out}.json").is_file():
            raise SystemExit("--only needs --out naming an existing result to merge into")
        result = json.loads(Path(f"{args.out}.json").read_text())
        result.pop("machine", None)
        earlier = result.pop("command", None)
    else:
        result = {"rendered": rendered_revisit(work, args.rendered_model),
                  "rendered_ground": rendered_revisit(work, args.rendered_model, GROUND, "_ground")}
        result["io"] = size_and_io(work / "r" / "r_map", work, args.repeats)
        result["kitti06"] = kitti06(work)
    if args.only != "live_0013":
        result["kitti_raw_0013"] = kitti_raw_0013(work, Path(args.data))
    if args.live or args.only == "live_0013":
        from bench.maps_live import live_0013

        poses = Path(args.data) / "kitti_raw_stereo" / "poses" / "2011_09_26_drive_0013.txt"
        result["live_0013"] = live_0013(work, work / "k13_map", work / "k13_s2", work / "k13_s1.txt",
                                        read_kitti_poses(poses), _ate_se3_m)
    command = command_line("bench.maps", argv)
    if args.only is not None and earlier:
        command = f"{earlier} && {command}"  # the other parts are the earlier command's
    publish(args.out, result, command, render)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
