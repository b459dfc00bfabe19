"""Evaluation plots (matplotlib, Agg backend, imported only when a plot is asked for).

One figure per call: the top view of ground truth and estimate (SE(3)- and Sim(3)-aligned),
and translational / rotational error against segment length (the devkit's plots).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metricslam.geometry import align


def top_view_axes(p_world: np.ndarray) -> tuple[int, int]:
    """The two world axes spanning the ground plane: drop the axis with the least spread.

    KITTI (y down) gives (x, z); TUM/EuRoC worlds (z up) give (x, y).
    """
    spread = np.ptp(np.asarray(p_world, dtype=float), axis=0)
    keep = sorted(int(i) for i in np.argsort(spread)[1:])
    return keep[0], keep[1]


def save_plot(evaluations: list, out_path: str | Path) -> Path:
    """Write a PNG with one row per sequence: top view | t_err vs length | r_err vs length."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(evaluations)
    fig, axes = plt.subplots(n, 3, figsize=(15, 4.6 * n), squeeze=False)
    names = "xyz"
    for row, ev in zip(axes, evaluations):
        gt, est = ev.T_world_cam_gt, ev.T_world_cam_est
        a, b = top_view_axes(gt[:, :3, 3])
        ax = row[0]
        ax.plot(gt[:, a, 3], gt[:, b, 3], "k-", lw=1.5, label="ground truth")
        if ev.ate.S_gt_est is not None:
            _, est_se3 = align.align_trajectory(est, gt, with_scale=False)
            est_sim3 = align.apply_to_poses(ev.ate.S_gt_est, est)
            ax.plot(est_se3[:, a, 3], est_se3[:, b, 3], "r-", lw=1.0, label="estimate (SE(3)-aligned)")
            ax.plot(est_sim3[:, a, 3], est_sim3[:, b, 3], "b--", lw=0.8,
                    label=f"estimate (Sim(3), scale ratio {ev.result.scale_ratio:.3f})")
        else:
            ax.plot(est[:, a, 3], est[:, b, 3], "r-", lw=1.0, label="estimate (not aligned)")
        ax.plot(gt[0, a, 3], gt[0, b, 3], "ks", ms=6, label="start")
        ax.set_xlabel(f"{names[a]} [m]")
        ax.set_ylabel(f"{names[b]} [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"{ev.result.name}: top view")
        ax.legend(fontsize=7, loc="best")
        by_len = ev.segments.by_length()
        lengths = list(by_len)
        t = [by_len[L][0] for L in lengths]
        r = [by_len[L][1] for L in lengths]
        row[1].plot(lengths, t, "bo-")
        row[1].set_xlabel("segment length [m]")
        row[1].set_ylabel("translation error [%]")
        row[1].set_title(f"t_rel {_fmt(ev.result.t_rel_pct)} %")
        row[2].plot(lengths, r, "bo-")
        row[2].set_xlabel("segment length [m]")
        row[2].set_ylabel("rotation error [deg/100 m]")
        row[2].set_title(f"r_rel {_fmt(ev.result.r_rel_deg_per_100m)} deg/100 m")
        for ax in row[1:]:
            ax.grid(True, alpha=0.3)
            ax.set_ylim(bottom=0)
    fig.tight_layout()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=90)
    plt.close(fig)
    return out_path


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"
