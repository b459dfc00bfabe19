"""``metricslam eval``: KITTI devkit t_rel/r_rel, ATE (unaligned, SE(3), Sim(3)), RPE, scale.

Example::

    metricslam eval --gt poses/07.txt --est out/07.txt --json out/07.json --plot out/07.png
    metricslam eval --gt 06.txt --est e06.txt --gt 07.txt --est e07.txt   # per-sequence + pooled
    metricslam eval --gt TUM_SEQ/groundtruth.txt --est est.tum              # associated by time
    metricslam eval --gt MH_01_easy --est est.tum     # EuRoC folder: body GT x T_BS -> camera poses
    metricslam eval --gt poses/06.txt --gt-times sequences/06/times.txt --est est.tum
"""

from __future__ import annotations

import argparse

from metricslam_cli.extras import require


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "eval",
        help="evaluate estimated trajectories against ground truth",
        description="KITTI devkit t_rel/r_rel, ATE RMSE (unaligned / SE(3) / Sim(3)), RPE and "
        "scale error of one or several (GT, estimate) pairs. Estimates are KITTI pose files "
        "(one 3x4 pose per frame) or TUM files (timestamp tx ty tz qx qy qz qw, associated by "
        "timestamp); ground truth is a KITTI, TUM or EuRoC (state_groundtruth_estimate0/data.csv) "
        "file or a KITTI / TUM / EuRoC dataset folder. See docs/evaluation.md.",
    )
    p.add_argument("--gt", action="append", required=True, metavar="GT",
                   help="ground-truth trajectory file or dataset folder (repeat, paired in order "
                        "with --est)")
    p.add_argument("--gt-times", action="append", default=None, metavar="TIMES.txt",
                   help="KITTI times.txt of a KITTI ground-truth file, to evaluate a TUM estimate "
                        "against it (repeat, paired in order with --gt)")
    p.add_argument("--est", action="append", required=True, metavar="EST",
                   help="estimated trajectory (repeat, paired in order with --gt)")
    p.add_argument("--format", choices=("auto", "kitti", "tum", "euroc"), default="auto",
                   help="file format (default: from the fields per line; euroc applies to the "
                        "ground truth only)")
    p.add_argument("--json", metavar="OUT.json", help="write the metrics as JSON")
    p.add_argument("--plot", metavar="OUT.png", help="write top view + error-vs-length plots")
    p.add_argument("--max-diff-ms", type=float, default=20.0,
                   help="TUM association tolerance in milliseconds (default 20)")
    p.add_argument("--rpe-delta", type=int, default=1, metavar="FRAMES",
                   help="frame offset of the RPE pairs (default 1)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    if args.plot:
        require("plots", command="eval --plot")
    import json
    from pathlib import Path

    from metricslam.errors import EvaluationError
    from metricslam.evaluation import build_report, evaluate_files

    if len(args.gt) != len(args.est):
        raise EvaluationError(
            f"got {len(args.gt)} --gt and {len(args.est)} --est: give them in pairs, "
            "--gt A --est A' --gt B --est B'"
        )
    gt_times = args.gt_times or [None] * len(args.gt)
    if len(gt_times) != len(args.gt):
        raise EvaluationError(f"got {len(args.gt_times)} --gt-times for {len(args.gt)} --gt: give one "
                              "per --gt, in the same order")
    names = [Path(e).stem for e in args.est]
    if len(set(names)) < len(names):
        names = [f"{Path(g).stem}:{Path(e).stem}" for g, e in zip(args.gt, args.est)]
    evaluations = [
        evaluate_files(g, e, fmt=args.format, name=n, max_diff_ns=int(args.max_diff_ms * 1e6),
                       rpe_delta_frames=args.rpe_delta, gt_times=t)
        for g, e, n, t in zip(args.gt, args.est, names, gt_times)
    ]
    report = build_report(evaluations)
    print(format_table(report))
    if args.json:
        out = Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report.to_json_dict(), indent=2) + "\n")
        print(f"wrote {out}")
    if args.plot:
        from metricslam.evaluation.plots import save_plot

        print(f"wrote {save_plot(evaluations, args.plot)}")
    return 0


COLUMNS = (
    ("t_rel %", "t_rel_pct", "{:.3f}"),
    ("r_rel deg/100m", "r_rel_deg_per_100m", "{:.3f}"),
    ("ATE raw m", "ate_rmse_unaligned_m", "{:.3f}"),
    ("ATE SE3 m", "ate_rmse_m", "{:.3f}"),
    ("ATE Sim3 m", "ate_rmse_sim3_m", "{:.3f}"),
    ("scale", "scale_ratio", "{:.4f}"),
    ("scale err %", "scale_error_pct", "{:.2f}"),
    ("RPE m", "rpe_trans_rmse_m", "{:.4f}"),
    ("RPE deg", "rpe_rot_rmse_deg", "{:.4f}"),
    ("frames", "n_frames", "{:d}"),
    ("path m", "path_length_m", "{:.1f}"),
)


def format_table(report) -> str:
    """A fixed-width table: one row per sequence, then pooled and mean rows, then notes."""
    rows = list(report.per_sequence)
    if len(rows) > 1:
        rows += [report.pooled, report.mean_of_sequences]
    header = ["sequence"] + [c[0] for c in COLUMNS]
    body = [[r.name] + ["n/a" if getattr(r, k) is None else f.format(getattr(r, k))
                        for _, k, f in COLUMNS] for r in rows]
    widths = [max(len(str(x)) for x in col) for col in zip(header, *body)]
    line = lambda cells: "  ".join(str(c).rjust(w) for c, w in zip(cells, widths))  # noqa: E731
    out = [line(header), line(["-" * w for w in widths])] + [line(b) for b in body]
    for r in report.per_sequence:
        lengths = ", ".join(f"{L:g}" for L in r.t_rel_lengths_m) or "none"
        out.append(f"{r.name}: t_rel over segment lengths [{lengths}] m, {r.n_segments} segments")
        out += [f"{r.name}: note: {n}" for n in r.notes]
    return "\n".join(out)
