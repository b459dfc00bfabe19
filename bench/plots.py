"""Figures for ``docs/results.md`` (matplotlib PNGs), from the outputs of ``bench/accuracy.py``.

* ``trajectories.png`` — top view per sequence: ground truth, metricslam as run (no alignment:
  both start at the identity), and ``--no-scale`` after a Sim(3) oracle alignment.
* ``scale_over_time.png`` — the trajectory's scale along the path. The pipeline does not log a
  per-keyframe scale, so it is *derived from trajectory vs ground truth*: for every frame ``i``,
  ``|p_est[j] − p_est[i]| / |p_gt[j] − p_gt[i]|`` with ``j`` the first frame at least ``W`` metres
  of ground-truth path later (chord ratio over a sliding window). 1.0 is metric.
* ``error_vs_length.png`` — translational (%) and rotational (°/100 m) error against segment
  length (the paper's Fig. 5), from ``metricslam eval``'s ``t_rel_by_length``.
* ``depth_example.png`` — ``metricslam depth`` on a ``kitti_raw_lidar`` frame (never trained on),
  beside its projected LiDAR depth, on the same colour scale.

Example::

    .venv/bin/python bench/plots.py --accuracy bench/results/accuracy.json \\
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

METRICSLAM = [sys.executable, "-m", "metricslam.cli.main"]
COLORS = {"gt": "k", "metric": "tab:blue", "noscale": "tab:gray", "noscale_sim3": "tab:orange"}
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


def chord_scale(T_gt: np.ndarray, T_est: np.ndarray, window_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Derived scale along the path: (distance along GT path m (K,), chord ratio est/gt (K,))."""
    p_gt, p_est = T_gt[:, :3, 3], T_est[:, :3, 3]
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p_gt, axis=0), axis=1))])
    j = np.searchsorted(dist, dist + window_m, side="left")
    ok = j < len(dist)
    i, j = np.nonzero(ok)[0], j[ok]
    chord_gt = np.linalg.norm(p_gt[j] - p_gt[i], axis=1)
    chord_est = np.linalg.norm(p_est[j] - p_est[i], axis=1)
    keep = chord_gt > 0.5 * window_m  # a window that turns back on itself says little about scale
    return dist[i][keep], chord_est[keep] / chord_gt[keep]


def plot_scale(seqs: list[dict], out: Path) -> Path:
    fig, axes = plt.subplots(len(seqs), 1, figsize=(9, 2.3 * len(seqs)), squeeze=False)
    for ax, seq in zip(axes[:, 0], seqs):
        gt = read_kitti_poses(seq["gt"])
        est = _estimates(seq)
        path_m = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
        window_m = 10.0 if path_m < 200 else 50.0
        for v in ("metric", "noscale"):
            if v in est:
                d, s = chord_scale(gt, est[v], window_m)
                ax.plot(d, s, "-", color=COLORS[v], lw=1.2, label=f"{LABELS[v]}")
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_ylim(0, max(1.6, ax.get_ylim()[1] if np.isfinite(ax.get_ylim()[1]) else 1.6))
        ax.set_ylabel("est / true distance")
        ax.set_title(f"{_title(seq, gt)} — window {window_m:.0f} m", fontsize=9)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("distance along the ground-truth path (m)")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle("Scale along the path, DERIVED from trajectory vs ground truth\n(chord ratio "
                 "over a sliding window; the pipeline does not log per-keyframe scale)", fontsize=9)
    fig.tight_layout()
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
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = json.loads(Path(args.accuracy).read_text())
    seqs = [s for s in report["sequences"] if s["name"] not in args.skip]
    written = [plot_trajectories(seqs, out / "trajectories.png"),
               plot_scale(seqs, out / "scale_over_time.png"),
               plot_error_vs_length(seqs, out / "error_vs_length.png")]
    if args.lidar_dir:
        png, cmd = plot_depth(Path(args.lidar_dir), args.lidar_frame, out / "depth_example.png")
        written.append(png)
        print(f"depth: {cmd}")
    for w in written:
        print(f"{w} {w.stat().st_size / 1024:.0f} KB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
