"""Figures for ``docs/results.md`` (matplotlib PNGs), from the outputs of ``bench/accuracy.py``.

* ``trajectories.png`` — top view per sequence: ground truth, metricslam as run (no alignment:
  both start at the identity), and ``--no-scale`` after a Sim(3) oracle alignment.
* ``scale_over_time.png`` — the system's own scale estimate over time, from the
  ``scale_history`` / ``scale_corrections`` that ``metricslam run --json`` logs (read from the
  stats files ``bench/accuracy.py --keep`` kept), for metricslam and ``--no-scale``: the live
  estimate (running product of the warp scales applied to the VO), the final optimized Sim(3)
  scale per keyframe, the median learned measurement ξ/z per keyframe, all in world units per
  unit of the VO's initial frame; and, drawn apart as a reference the system never sees, the
  true value from ground truth (GT path / VO path over a trailing window). With ``--no-scale``
  the world unit is the VO's own, so its curves sit near 1 while the reference shows how far
  from metric that is.
* ``error_vs_length.png`` — translational (%) and rotational (°/100 m) error against segment
  length (the paper's Fig. 5), from ``metricslam eval``'s ``t_rel_by_length``.
* ``depth_example.png`` — ``metricslam depth`` on a ``kitti_raw_lidar`` frame (never trained on),
  beside its projected LiDAR depth, on the same colour scale.

Example::

    .venv/bin/python -m bench.plots --accuracy bench/results/accuracy.json \\
        --lidar-dir /work/shared/data/kitti_raw_lidar --lidar-frame 40 --out docs/img
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from metricslam.evaluation.plots import top_view_axes  # noqa: E402
from metricslam.trajectory.io import read_kitti_poses  # noqa: E402

METRICSLAM = [sys.executable, "-m", "metricslam_cli.main"]
COLORS = {"gt": "k", "metric": "tab:blue", "noscale": "tab:gray", "noscale_sim3": "tab:orange"}
FIGURES = ("trajectories", "scale", "error", "depth")
LABELS = {"metric": "metricslam (learned scale, as run)", "noscale": "--no-scale, as run",
          "noscale_sim3": "--no-scale, Sim(3)-aligned to GT (oracle scale)"}


def _estimates(seq: dict) -> dict[str, np.ndarray]:
    out = {}
    for v, path in (("metric", seq["runs"]["metric"].get("est")),
                    ("noscale", seq["runs"]["noscale"].get("est")),
                    ("noscale_sim3", seq.get("aligned_est"))):
        if path and Path(path).is_file() and "error" not in seq["runs"][v.split("_")[0]]:
            out[v] = read_kitti_poses(path)
    return out


def _title(seq: dict, gt: np.ndarray) -> str:
    dist = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
    trained = " (depth net trained on it)" if seq["trained_on"] == "yes" else " (held out)"
    return f"{seq['name']}: {len(gt)} frames, {dist:.0f} m{trained}"


def plot_trajectories(seqs: list[dict], out: Path) -> Path:
    fig, axes = plt.subplots(1, len(seqs), figsize=(4.4 * len(seqs), 4.6), squeeze=False)
    for ax, seq in zip(axes[0], seqs):
        gt = read_kitti_poses(seq["gt"])
        est = _estimates(seq)
        a, b = top_view_axes(gt[:, :3, 3])
        ax.plot(gt[:, :3, 3][:, a], gt[:, :3, 3][:, b], "-", color=COLORS["gt"], lw=2.2,
                label="ground truth")
        for v in ("noscale_sim3", "metric"):
            if v in est:
                p = est[v][:, :3, 3]
                ax.plot(p[:, a], p[:, b], "-", color=COLORS[v], lw=1.2, label=LABELS[v])
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{'xyz'[a]} (m)")
        ax.set_ylabel(f"{'xyz'[b]} (m)")
        ax.set_title(_title(seq, gt), fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, loc="best")
    fig.suptitle("Top view: metricslam as run (no ground truth used) vs --no-scale with oracle "
                 "Sim(3) alignment", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def _scale_history(run: dict) -> dict | None:
    """The ``metricslam run --json`` statistics of one run (kept by ``bench/accuracy.py``), if
    they hold the scale history."""
    path = run.get("stats_json") or (str(Path(run["est"]).with_suffix("")) + "_stats.json"
                                     if run.get("est") else None)
    if "error" in run or not path or not Path(path).is_file():
        return None
    stats = json.loads(Path(path).read_text())
    return stats if stats.get("scale_history") else None


def true_scale(history: list[dict], T_gt: np.ndarray, window_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth reference for the scale history (never used by the system).

    For every keyframe ``i``: the ground-truth path over the VO path, both between consecutive
    keyframes of one segment over the trailing ``window_m`` metres of ground truth, with the VO
    steps converted to the VO's initial units (``step_vo / scale_live``) — i.e. the true metres
    per ``VO₀`` unit there, comparable with ``scale_live`` and ``scale_optimized``.

    Returns:
        (keyframe positions in ``history`` (K,), true scale (K,)), keyframes whose window is full.
    """
    p_gt = T_gt[:, :3, 3]
    steps: list[tuple[float, float]] = []  # (gt m, VO₀ units) within the current segment
    idx, vals = [], []
    for i, (prev, rec) in enumerate(zip([None, *history[:-1]], history)):
        if prev is None or rec["step_vo"] is None or rec["segment_id"] != prev["segment_id"]:
            steps = []
            continue
        steps.append((float(np.linalg.norm(p_gt[rec["frame_index"]] - p_gt[prev["frame_index"]])),
                      rec["step_vo"] / rec["scale_live"]))
        gt_m = vo0 = 0.0
        for g, v in reversed(steps):
            gt_m, vo0 = gt_m + g, vo0 + v
            if gt_m >= window_m:
                break
        if gt_m >= window_m and vo0 > 0:
            idx.append(i)
            vals.append(gt_m / vo0)
    return np.array(idx, dtype=int), np.array(vals)


def _draw_scale(ax, stats: dict, T_gt: np.ndarray, window_m: float, t0_ns: int) -> str:
    """One run's scale history on ``ax``; returns a one-line summary (optimized vs reference)."""
    hist, corr = stats["scale_history"], stats.get("scale_corrections", [])
    t_kf = np.array([(r["t_ns"] - t0_ns) * 1e-9 for r in hist])
    if corr:  # live: 1 until the first warp, then the running product, as a step function
        t_c = np.array([0.0] + [(c["t_ns"] - t0_ns) * 1e-9 for c in corr] + [t_kf.max()])
        live = np.array([1.0] + [c["scale_live"] for c in corr] + [corr[-1]["scale_live"]])
        ax.step(t_c, live, where="post", color="tab:blue", lw=1.3,
                label="live: product of the warp scales applied (as it ran)")
    meas = [(t, r["scale_measured_median"] * r["scale_live"]) for t, r in zip(t_kf, hist)
            if r.get("scale_measured_median")]
    if meas:
        m = np.array(meas)
        ax.plot(m[:, 0], m[:, 1], "x", color="tab:gray", ms=3, alpha=0.6,
                label="per keyframe: median learned ξ/z (× live)")
    opt = np.array([(t, r["scale_optimized"]) for t, r in zip(t_kf, hist)
                    if r.get("scale_optimized") is not None])
    if opt.size:
        ax.plot(opt[:, 0], opt[:, 1], ".", color="tab:orange", ms=3.5,
                label="per keyframe: final optimized Sim(3) scale (× live)")
    idx, ref = true_scale(hist, T_gt, window_m)
    summary = "no ground-truth window fits"
    if idx.size:
        ax.plot(t_kf[idx], ref, "--", color="k", lw=1.2,
                label="ground truth, reference only: GT path / VO path over a trailing window")
        opt_at = np.array([hist[i]["scale_optimized"] if hist[i]["scale_optimized"] is not None
                           else np.nan for i in idx])
        r = opt_at / ref
        r = r[np.isfinite(r)]
        if r.size:
            p10, p50, p90 = np.percentile(r, [10, 50, 90])
            summary = (f"optimized / reference ({window_m:.0f} m window): median {p50:.2f} "
                       f"(10–90 %: {p10:.2f}–{p90:.2f})")
    ax.grid(alpha=0.3)
    return summary


def plot_scale(seqs: list[dict], out: Path) -> Path | None:
    """Rows: sequences; columns: metricslam, ``--no-scale``. The system's own scale history from
    ``metricslam run --json``, with the ground-truth reference drawn separately."""
    rows = [(seq, {m: _scale_history(seq["runs"].get(m, {})) for m in ("metric", "noscale")})
            for seq in seqs]
    rows = [(seq, h) for seq, h in rows if any(h.values())]
    if not rows:
        print("scale_over_time.png skipped: the runs' stats hold no scale_history "
              "(re-run bench/accuracy.py with the current metricslam)")
        return None
    height_in = 1.5 + 2.6 * len(rows)
    fig, axes = plt.subplots(len(rows), 2, figsize=(12, height_in), squeeze=False)
    for (seq, hists), ax_row in zip(rows, axes):
        gt = read_kitti_poses(seq["gt"])
        path_m = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
        window_m = 10.0 if path_m < 200 else 50.0
        t0 = min(r["t_ns"] for h in hists.values() if h for r in h["scale_history"])
        for ax, mode in zip(ax_row, ("metric", "noscale")):
            if not hists[mode]:
                ax.set_axis_off()
                continue
            summary = _draw_scale(ax, hists[mode], gt, window_m, t0)
            what = ("metricslam (learned scale)" if mode == "metric" else
                    "--no-scale (world unit = the first keyframe's VO unit)")
            ax.set_title(f"{_title(seq, gt)} — {what}\n{summary}", fontsize=8)
            ax.set_ylim(bottom=0)
        ax_row[0].set_ylabel("world units per VO₀ unit\n(metres in metric mode)", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    handles: dict = {}
    for ax in axes.ravel():
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.suptitle("Scale estimate over time, as the system logged it (metricslam run --json → "
                 "scale_history); VO₀ = the VO's initial, arbitrary unit.\nBlack dashed: ground "
                 "truth for reference only — the system never sees it.", fontsize=9)
    fig.tight_layout(rect=(0, 0.55 / height_in, 1, 1))
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=2, fontsize=7,
               frameon=False)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def plot_error_vs_length(seqs: list[dict], out: Path) -> Path:
    fig, (ax_t, ax_r) = plt.subplots(1, 2, figsize=(11, 4.2))
    styles = ["-o", "--s", ":^", "-.d", "-v"]
    for k, seq in enumerate(seqs):
        for v in ("metric", "noscale_sim3"):
            res = seq["eval"].get(v, {}).get("result")
            by_len = (res or {}).get("t_rel_by_length") or {}
            if not by_len:
                continue
            L = np.array([float(x) for x in by_len])
            t = np.array([by_len[x][0] for x in by_len])
            r = np.array([by_len[x][1] for x in by_len])
            lab = f"{seq['name']}: {'metricslam' if v == 'metric' else '--no-scale + Sim(3)'}"
            ax_t.plot(L, t, styles[k % len(styles)], color=COLORS[v], ms=4, lw=1, label=lab)
            ax_r.plot(L, r, styles[k % len(styles)], color=COLORS[v], ms=4, lw=1, label=lab)
    for ax, lab in ((ax_t, "translation error (%)"), (ax_r, "rotation error (deg / 100 m)")):
        ax.set_xscale("log")
        ticks = [10, 20, 50, 100, 200, 400, 800]
        ax.set_xticks(ticks, labels=[str(t) for t in ticks])
        ax.minorticks_off()
        ax.set_xlabel("segment length (m)")
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3, which="both")
    ax_t.legend(fontsize=7)
    fig.suptitle("Error vs segment length (KITTI devkit definition; short sequences use 10–50 m)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def plot_depth(lidar_dir: Path, frame: int, out: Path) -> tuple[Path, str]:
    """Image | predicted depth | LiDAR depth for one ``kitti_raw_lidar`` frame."""
    import cv2

    names = sorted((lidar_dir / "image_02").glob("*.png"))
    img_path = names[frame]
    lidar = cv2.imread(str(lidar_dir / "depth_02" / img_path.name), cv2.IMREAD_UNCHANGED)
    depth_lidar_m = lidar.astype(np.float32) / 256.0
    fx_px = float((lidar_dir / "calib.txt").read_text().split("K:")[1].split()[0])
    with tempfile.TemporaryDirectory() as tmp:
        npy = Path(tmp) / "depth.npy"
        cmd = METRICSLAM + ["depth", str(img_path), "--fx", f"{fx_px}", "--out", str(npy)]
        subprocess.run(cmd, check=True, capture_output=True, text=True)
        depth_pred_m = np.load(npy)
    shown = "metricslam " + " ".join(cmd[len(METRICSLAM):-2]) + " --out depth.npy"
    image = cv2.cvtColor(cv2.imread(str(img_path)), cv2.COLOR_BGR2RGB)
    h, w = image.shape[:2]
    # Compare where LiDAR measured: sample the coarse prediction at each LiDAR pixel.
    v, u = np.nonzero(depth_lidar_m > 0)
    hp, wp = depth_pred_m.shape
    pred_at = depth_pred_m[(v * hp // h).clip(0, hp - 1), (u * wp // w).clip(0, wp - 1)]
    ratio = float(np.median(pred_at / depth_lidar_m[v, u]))
    norm = matplotlib.colors.LogNorm(vmin=2.0, vmax=80.0)  # most LiDAR depths here are < 10 m
    fig, axes = plt.subplots(3, 1, figsize=(7.6, 7.0), layout="constrained")
    axes[0].imshow(image)
    axes[0].set_title(f"kitti_raw_lidar/image_02/{img_path.name} (validation only, never trained on)",
                      fontsize=9)
    im = axes[1].imshow(depth_pred_m, cmap="turbo_r", norm=norm,
                        extent=(0, w, h, 0), interpolation="nearest")
    axes[1].set_title(f"network depth ({hp}x{wp}, metres)", fontsize=9)
    axes[2].imshow(np.full((h, w), 0.92), cmap="gray", vmin=0, vmax=1)
    axes[2].scatter(u, v, c=depth_lidar_m[v, u], s=1.2, cmap="turbo_r", norm=norm,
                    linewidths=0)
    axes[2].set_xlim(0, w)
    axes[2].set_ylim(h, 0)
    axes[2].set_title(f"projected LiDAR depth ({len(u)} points); median predicted / LiDAR = "
                      f"{ratio:.2f}", fontsize=9)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    cbar = fig.colorbar(im, ax=axes, shrink=0.6, label="depth (m, log scale)")
    cbar.set_ticks([2, 5, 10, 20, 40, 80], labels=["2", "5", "10", "20", "40", "80"])
    fig.savefig(out, dpi=72)
    plt.close(fig)
    return out, shown


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--accuracy", required=True, help="JSON written by bench/accuracy.py")
    p.add_argument("--lidar-dir", help="kitti_raw_lidar folder (image_02/, depth_02/, calib.txt)")
    p.add_argument("--lidar-frame", type=int, default=40)
    p.add_argument("--skip", nargs="*", default=["kitti03"],
                   help="sequences left out of the figures (default: kitti03, 5 frames)")
    p.add_argument("--out", required=True, help="output folder for PNGs")
    p.add_argument("--figures", nargs="+", choices=FIGURES, default=list(FIGURES),
                   help="which figures to (re)draw (default: all; depth needs --lidar-dir)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = json.loads(Path(args.accuracy).read_text())
    seqs = [s for s in report["sequences"] if s["name"] not in args.skip]
    written = []
    if "trajectories" in args.figures:
        written.append(plot_trajectories(seqs, out / "trajectories.png"))
    if "scale" in args.figures:
        written.append(plot_scale(seqs, out / "scale_over_time.png"))
    if "error" in args.figures:
        written.append(plot_error_vs_length(seqs, out / "error_vs_length.png"))
    if "depth" in args.figures and args.lidar_dir:
        png, cmd = plot_depth(Path(args.lidar_dir), args.lidar_frame, out / "depth_example.png")
        written.append(png)
        print(f"depth: {cmd}")
    for w in written:
        if w is not None:
            print(f"{w} {w.stat().st_size / 1024:.0f} KB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
