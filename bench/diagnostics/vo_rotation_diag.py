"""Where does the VO's rotational drift come from? Per-frame relative rotations on KITTI extracts.

For each consecutive frame pair (i, i+1) of a sequence this compares the relative rotation
``R_i_{i+1}`` of

* the ground truth (``T_world_cam0`` of image_0),
* the local VO (``SlamPipeline`` without back end, inline BA: deterministic),
* a two-view essential matrix (``cv2.findEssentialMat`` + ``recoverPose`` on fresh LK tracks of
  the pair, normalized coordinates) — independent of the VO's map and BA,
* stereo PnP (left/right LK matches of frame i triangulated with the calibrated baseline, then
  ``solvePnPRansac`` + LM refinement on the LK tracks in frame i+1) — a diagnostic reference
  only; the VO never sees the right image.

Errors are ``log(R_gt⁻¹ R_x)`` in the camera frame of frame i, split into pitch (about x,
right), yaw (about y, down) and roll (about z, forward), in millidegrees. It also prints the
KITTI r_rel segment table of the VO and the references (which segments dominate the 10..50 m
fallback) and the yaw "scale" (sum of estimated yaw increments / sum of GT yaw increments).

Example::

    .venv/bin/python -m bench.diagnostics.vo_rotation_diag --seq ../shared/data/kitti_odometry/sequences/06 \\
        --seq ../shared/data/kitti_odometry/sequences/01 --out bench/results/vo_rotation.json

Ground truth is read only by the evaluation part.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
from bench.machine import command_line
from metricslam.datasets import open_sequence
from metricslam.evaluation.kitti_metric import SHORT_LENGTHS_M, segment_errors
from metricslam.geometry import so3
from metricslam.slam.session_builder import build_session
from metricslam.slam.system_config import SystemConfig

LK = {"winSize": (21, 21), "maxLevel": 3,
      "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}


def corners(gray: np.ndarray, n: int = 2000) -> np.ndarray:
    pts = cv2.goodFeaturesToTrack(gray, maxCorners=n, qualityLevel=0.003, minDistance=7, blockSize=5)
    return pts.reshape(-1, 2).astype(np.float32)


def lk_fb(a: np.ndarray, b: np.ndarray, p: np.ndarray, max_fb_px: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """LK from ``a`` to ``b`` with a forward-backward check; returns (q (N,2), ok (N,))."""
    q, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p.reshape(-1, 1, 2), None, **LK)
    pb, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, q, None, **LK)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(pb.reshape(-1, 2) - p, axis=1) < max_fb_px)
    return q.reshape(-1, 2), ok


def essential_rotation(K: np.ndarray, a_px: np.ndarray, b_px: np.ndarray) -> tuple[np.ndarray, int]:
    """``R_a_b`` (the pose of b in a) from the essential matrix on pixel pairs; (R, inliers)."""
    Ki = np.linalg.inv(K)
    na = (a_px @ Ki[:2, :2].T + Ki[:2, 2]).astype(np.float64)
    nb = (b_px @ Ki[:2, :2].T + Ki[:2, 2]).astype(np.float64)
    thr = 0.5 / K[0, 0]
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), method=cv2.RANSAC, prob=0.9999, threshold=thr)
    n, R_b_a, _, _ = cv2.recoverPose(E[:3], na, nb, np.eye(3), mask=mask)
    return R_b_a.T, int(n)


def stereo_pnp_rotation(K: np.ndarray, baseline_m: float, left: np.ndarray, right: np.ndarray,
                        nxt: np.ndarray, p_px: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """``T_i_{i+1}`` from stereo points of frame i and their LK tracks in frame i+1."""
    q_r, ok_r = lk_fb(left, right, p_px)
    disp = p_px[:, 0] - q_r[:, 0]
    ok_r &= (np.abs(p_px[:, 1] - q_r[:, 1]) < 1.0) & (disp > 1.0)
    q_n, ok_n = lk_fb(left, nxt, p_px)
    ok = ok_r & ok_n
    z = K[0, 0] * baseline_m / disp[ok]
    x = (p_px[ok, 0] - K[0, 2]) / K[0, 0] * z
    y = (p_px[ok, 1] - K[1, 2]) / K[1, 1] * z
    P = np.stack([x, y, z], axis=1).astype(np.float64)
    uv = q_n[ok].astype(np.float64)
    _okp, rvec, tvec, inl = cv2.solvePnPRansac(P, uv, K, None, reprojectionError=1.0,
                                               iterationsCount=500, flags=cv2.SOLVEPNP_ITERATIVE)
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(P[inl], uv[inl], K, None, rvec, tvec)
    R_n_i = cv2.Rodrigues(rvec)[0]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_n_i.T, -R_n_i.T @ tvec.ravel()
    return T[:3, :3], T, len(inl)


def run_vo(seq, n: int, preset: str) -> np.ndarray:
    pipe = build_session(seq.camera, SystemConfig(vo={"preset": preset}, vo_only=True, deterministic=True))
    for i in range(n):
        pipe.process(seq[i])
    pipe.close()
    return np.array([e.T_world_cam for e in pipe.trajectory()])


def chain(rel: list[np.ndarray]) -> np.ndarray:
    out = [np.eye(4)]
    for T in rel:
        out.append(out[-1] @ T)
    return np.array(out)


def rel_rot(T: np.ndarray) -> np.ndarray:
    return np.array([T[i, :3, :3].T @ T[i + 1, :3, :3] for i in range(len(T) - 1)])


def err_pyr_mdeg(R_gt: np.ndarray, R_x: np.ndarray) -> np.ndarray:
    """(N, 3) [pitch, yaw, roll] of log(R_gt⁻¹ R_x), millidegrees."""
    return np.degrees(np.array([so3.log(a.T @ b) for a, b in zip(R_gt, R_x)])) * 1e3


def segments_table(gt: np.ndarray, est: np.ndarray) -> list[dict]:
    seg = segment_errors(gt, est, SHORT_LENGTHS_M)
    rows = []
    for k in range(len(seg)):
        first, last = int(seg.first_frame[k]), int(seg.last_frame[k])
        E = np.linalg.inv(np.linalg.inv(est[first]) @ est[last]) @ (np.linalg.inv(gt[first]) @ gt[last])
        w = np.degrees(so3.log(E[:3, :3]))
        rows.append({"first": first, "last": last, "L": float(seg.length_m[k]),
                     "r_deg_per_100m": float(np.degrees(seg.r_err_rad_per_m[k]) * 100),
                     "err_pitch_yaw_roll_deg": [round(float(v), 4) for v in w]})
    return rows


def constant_gt_prefix(R_gt: np.ndarray, tol_mdeg: float = 1.0) -> int:
    """First pair index after a leading run of (near) constant GT rotation increments (0 if none).

    Interpolated ground truth shows as increments that change by < ``tol_mdeg`` per frame; real
    OXTS increments change by tens of millidegrees from frame to frame.
    """
    w = np.degrees(np.array([so3.log(R) for R in R_gt])) * 1e3
    k = 0
    while k + 1 < len(w) and np.all(np.abs(w[k + 1] - w[k]) < tol_mdeg):
        k += 1
    return k + 1 if k >= 3 else 0


def three_cornered_hat(e_a: np.ndarray, e_b: np.ndarray) -> dict:
    """Per-axis noise sigmas (mdeg per frame pair) of GT, A and B from A−GT and B−GT errors (N, 3),
    assuming independent errors (Allan/Gray three-cornered hat on the mean-removed series)."""
    va, vb, vab = np.var(e_a, axis=0), np.var(e_b, axis=0), np.var(e_a - e_b, axis=0)

    def sig(v):
        return [round(float(np.sqrt(max(x, 0.0))), 1) for x in v]

    return {"gt": sig((va + vb - vab) / 2), "a": sig((va + vab - vb) / 2), "b": sig((vb + vab - va) / 2)}


def shared_bias(e_a: np.ndarray, e_b: np.ndarray) -> np.ndarray:
    """Per-axis rotation-rate bias (3,) mdeg/frame that two references (N, 3) errors agree on:
    the mean of their means where both are significant (> 2 standard errors) with the same
    sign, else 0 for that axis."""
    m_a, m_b = e_a.mean(axis=0), e_b.mean(axis=0)
    se_a, se_b = e_a.std(axis=0) / np.sqrt(len(e_a)), e_b.std(axis=0) / np.sqrt(len(e_b))
    agree = (np.abs(m_a) > 2 * se_a) & (np.abs(m_b) > 2 * se_b) & (np.sign(m_a) == np.sign(m_b))
    return np.where(agree, 0.5 * (m_a + m_b), 0.0)


def with_rotation_bias(gt: np.ndarray, bias_mdeg: np.ndarray, first_pairs_mdeg: np.ndarray | None = None) -> np.ndarray:
    """GT with every per-frame rotation increment followed by ``Exp(bias)`` (translations kept);
    ``first_pairs_mdeg`` (k, 3) replaces the bias of the first k pairs (per-pair errors)."""
    out = [gt[0].copy()]
    for i in range(len(gt) - 1):
        T = np.linalg.inv(gt[i]) @ gt[i + 1]
        b = first_pairs_mdeg[i] if first_pairs_mdeg is not None and i < len(first_pairs_mdeg) else bias_mdeg
        T[:3, :3] = T[:3, :3] @ so3.exp(np.radians(b / 1e3))
        out.append(out[-1] @ T)
    return np.array(out)


def r_rel_stats(gt: np.ndarray, est: np.ndarray, first_from: int) -> dict:
    seg = segment_errors(gt, est, SHORT_LENGTHS_M)
    r = np.degrees(seg.r_err_rad_per_m) * 100
    late = seg.first_frame >= first_from
    return {"all": float(r.mean()), "before": float(r[~late].mean()) if (~late).any() else float("nan"),
            "from": float(r[late].mean()) if late.any() else float("nan"),
            "L10": float(r[seg.length_m == 10].mean()), "L50": float(r[seg.length_m == 50].mean())}


def gt_noise_floor(gt: np.ndarray, sigma_pair_mdeg: np.ndarray, first_from: int, n_draws: int,
                   seed: int = 0) -> dict:
    """r_rel of a perfect estimator scored against GT with white per-pose rotation noise whose
    frame-pair sigma is ``sigma_pair_mdeg`` (3,) (pose sigma = pair sigma / √2); mean of draws."""
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(n_draws):
        noisy = gt.copy()
        for i in range(len(gt)):
            noisy[i, :3, :3] = gt[i, :3, :3] @ so3.exp(np.radians(rng.normal(0, sigma_pair_mdeg / np.sqrt(2)) / 1e3))
        rows.append(r_rel_stats(noisy, gt, first_from))
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def analyse(path: Path, n_max: int | None, n_draws: int = 50) -> dict:
    seq = open_sequence(path)
    n = len(seq) if n_max is None else min(n_max, len(seq))
    K = seq.camera.K
    gt = np.asarray(seq.T_world_cam_gt[:n], dtype=float)
    imgs = [seq[i] for i in range(n)]
    vo = run_vo(seq, n, "synth" if (path / "depth_0").is_dir() else "kitti")
    R_ess, T_st, n_ess, n_st = [], [], [], []
    for i in range(n - 1):
        a, b = imgs[i].image, imgs[i + 1].image
        p = corners(a)
        q, ok = lk_fb(a, b, p)
        R, k = essential_rotation(K, p[ok], q[ok])
        R_ess.append(R)
        n_ess.append(k)
        _, T, k2 = stereo_pnp_rotation(K, seq.baseline_m, a, imgs[i].image_right, b, p)
        T_st.append(T)
        n_st.append(k2)
    R_gt, R_vo = rel_rot(gt), rel_rot(vo)
    R_ess = np.array(R_ess)
    stereo = chain(T_st)
    R_st = rel_rot(stereo)
    e_vo, e_ess, e_st = err_pyr_mdeg(R_gt, R_vo), err_pyr_mdeg(R_gt, R_ess), err_pyr_mdeg(R_gt, R_st)
    w_gt = np.degrees(np.array([so3.log(R) for R in R_gt]))

    def yaw(R):
        return np.degrees(np.array([so3.log(r) for r in R]))[:, 1]

    # essential-matrix chain with GT translation lengths (rotation only matters for r_rel)
    ess_chain = [np.eye(4)]
    for i, R in enumerate(R_ess):
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = (np.linalg.inv(gt[i]) @ gt[i + 1])[:3, 3]
        ess_chain.append(ess_chain[-1] @ T)
    ess_chain = np.array(ess_chain)
    s0 = constant_gt_prefix(R_gt)
    # first devkit start frame (every 10th) whose segments hold at most one interpolated pair
    first_from = int(np.ceil(max(s0 - 1, 0) / 10.0) * 10)
    sl = slice(s0, None)
    out = {"sequence": str(path), "frames": n, "fx_px": float(K[0, 0]), "cx_px": float(K[0, 2]),
           "cy_px": float(K[1, 2]), "size": [seq.camera.width_px, seq.camera.height_px],
           "gt_constant_increments_until_pair": s0, "segments_counted_from_frame": first_from,
           "per_frame": []}
    for i in range(n - 1):
        out["per_frame"].append({
            "pair": [i, i + 1], "gt_rot_pyr_deg": [round(float(v), 4) for v in w_gt[i]],
            "vo_err_mdeg": [round(float(v), 1) for v in e_vo[i]],
            "ess_err_mdeg": [round(float(v), 1) for v in e_ess[i]],
            "stereo_err_mdeg": [round(float(v), 1) for v in e_st[i]],
            "ess_inliers": n_ess[i], "stereo_inliers": n_st[i]})
    summary = {}
    for name, e, R in (("vo", e_vo, R_vo), ("essential", e_ess, R_ess), ("stereo_pnp", e_st, R_st)):
        summary[name] = {
            "rms_err_pitch_yaw_roll_mdeg": [round(float(v), 1) for v in np.sqrt(np.mean(e[sl]**2, axis=0))],
            "mean_err_pitch_yaw_roll_mdeg": [round(float(v), 1) for v in np.mean(e[sl], axis=0)],
            "yaw_sum_over_gt": float(np.sum(yaw(R)[sl]) / np.sum(w_gt[sl, 1])),
        }
    summary["gt_total_yaw_deg"] = float(np.sum(w_gt[sl, 1]))
    hat = three_cornered_hat(e_vo[sl], e_st[sl])
    summary["sigma_pair_mdeg_pyr"] = {"gt": hat["gt"], "vo": hat["a"], "stereo_pnp": hat["b"]}
    # the rotation-rate bias that both independent references (stereo PnP, essential matrix)
    # see against the GT: not something the VO can be blamed for
    bias = shared_bias(e_st[sl], e_ess[sl])
    summary["reference_bias_mdeg_per_frame_pyr"] = [round(float(v), 1) for v in bias]
    sig_gt = np.array(hat["gt"])
    r = {"vo": r_rel_stats(gt, vo, first_from),
         "stereo_pnp_chain": r_rel_stats(gt, stereo, first_from),
         "essential_chain_gt_t": r_rel_stats(gt, ess_chain, first_from),
         "gt_plus_reference_bias": r_rel_stats(gt, with_rotation_bias(gt, bias), first_from),
         "gt_noise_floor": gt_noise_floor(gt, sig_gt, first_from, n_draws),
         "vo_vs_bias_corrected_gt": r_rel_stats(with_rotation_bias(gt, bias), vo, first_from)}
    if s0 > 0:  # a perfect estimator that follows the images (stereo) where the GT is interpolated
        r["gt_with_stereo_on_interpolated_pairs"] = r_rel_stats(
            gt, with_rotation_bias(gt, np.zeros(3), e_st[:s0]), first_from)
    out["r_rel"] = r
    for name, traj in (("vo", vo), ("stereo_pnp_chain", stereo), ("essential_chain_gt_t", ess_chain)):
        out[name + "_segments"] = segments_table(gt, traj)
    out["summary"] = summary
    return out


def to_markdown(res: list[dict], command: str) -> str:
    lines = ["# Rotational error of the local VO on the KITTI extracts: where it comes from", "",
             f"Command: `{command}`", "",
             ("Errors are log(R_gt⁻¹ R_est) of each frame pair's relative rotation in the camera "
             "frame: pitch (x, right), yaw (y, down), roll (z, forward), millidegrees. Estimators: "
             "`vo` = the local VO (inline BA); `essential` = findEssentialMat + recoverPose on "
             "fresh LK tracks of the pair; `stereo_pnp` = image_1 stereo points of frame i, PnP in "
             "frame i+1 (a diagnostic reference; the VO never sees image_1). r_rel rows: the KITTI "
             "devkit formula over the 10..50 m fallback lengths; `*_chain` = the references' "
             "frame-to-frame chains (essential with GT step lengths); `gt_plus_reference_bias` = "
             "the GT with the references' shared rotation-rate bias added (what a perfect "
             "image-based estimator would score); `gt_noise_floor` = a perfect estimator against "
             "the GT with white per-pose noise of the three-cornered-hat size (Monte Carlo); "
             "`vo_vs_bias_corrected_gt` = the VO against the GT with that bias added; "
             "`gt_with_stereo_on_interpolated_pairs` = the GT except that the interpolated pairs "
             "rotate as the stereo reference says (the score of an estimator that is perfect "
             "elsewhere and follows the images there). 'starts "
             "before/from' split the devkit start frames at the first one after the interpolated "
             "GT."), ""]
    for r in res:
        s = r["summary"]
        lines += [f"## {r['sequence']}", "",
                  (f"K: fx {r['fx_px']:.3f}, cx {r['cx_px']:.3f}, cy {r['cy_px']:.3f} px, image "
                  f"{r['size'][0]}x{r['size'][1]}. GT rotation increments constant (interpolated) "
                  f"up to pair {r['gt_constant_increments_until_pair']}; per-frame statistics "
                  f"below start there, 'from' columns use devkit start frames ≥ "
                  f"{r['segments_counted_from_frame']}."), "",
                  "| estimator | mean err pitch/yaw/roll mdeg/frame | rms err p/y/r | yaw sum / GT |",
                  "| --- | --- | --- | --- |"]
        for k in ("vo", "essential", "stereo_pnp"):
            v = s[k]
            lines.append(f"| {k} | {v['mean_err_pitch_yaw_roll_mdeg']} | "
                         f"{v['rms_err_pitch_yaw_roll_mdeg']} | {v['yaw_sum_over_gt']:.4f} |")
        h = s["sigma_pair_mdeg_pyr"]
        lines += ["", (f"Three-cornered hat (independent noise per frame pair, mdeg, p/y/r): GT "
                  f"{h['gt']}, VO {h['vo']}, stereo PnP {h['stereo_pnp']}. Rotation-rate bias seen "
                  f"by both references against GT (axes where both are significant and agree, else 0): "
                  f"{s['reference_bias_mdeg_per_frame_pyr']} "
                  f"mdeg/frame (GT total yaw {s['gt_total_yaw_deg']:.2f}°)."), "",
                  "| r_rel deg/100 m | all segments | starts before | starts from | L = 10 m | L = 50 m |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for k, v in r["r_rel"].items():
            lines.append(f"| {k} | {v['all']:.2f} | {v['before']:.2f} | {v['from']:.2f} | "
                         f"{v['L10']:.2f} | {v['L50']:.2f} |")
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", action="append", required=True, type=Path)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--out", type=Path, default=None, help="JSON with every frame pair")
    ap.add_argument("--md", type=Path, default=None, help="markdown summary")
    ap.add_argument("--draws", type=int, default=50, help="Monte Carlo draws of the GT-noise floor")
    args = ap.parse_args(argv)
    res = []
    for s in args.seq:
        r = analyse(s, args.max_frames, args.draws)
        res.append(r)
        print(f"== {s}  fx={r['fx_px']:.2f} cx={r['cx_px']:.2f} cy={r['cy_px']:.2f} size={r['size']}")
        print("pair   gt p/y/r deg            vo err p/y/r mdeg     ess err p/y/r mdeg    stereo err p/y/r mdeg")
        for p in r["per_frame"]:
            print(f"{p['pair'][0]:2d}-{p['pair'][1]:2d} {p['gt_rot_pyr_deg']!s:28} {p['vo_err_mdeg']!s:22} "
                  f"{p['ess_err_mdeg']!s:22} {p['stereo_err_mdeg']!s:22}")
        print(json.dumps(r["summary"]), json.dumps(r["r_rel"]))
        for name in ("vo", "stereo_pnp_chain", "essential_chain_gt_t"):
            print(name, "segments:", " ".join(f"{s['first']}-{s['last']}:{s['r_deg_per_100m']:.2f}"
                                              for s in r[name + "_segments"]))
    if args.out:
        args.out.write_text(json.dumps(res, indent=1) + "\n")
    if args.md:
        command = command_line("bench.diagnostics.vo_rotation_diag", argv)
        args.md.write_text(to_markdown(res, command))
    return 0


if __name__ == "__main__":
    sys.exit(main())
