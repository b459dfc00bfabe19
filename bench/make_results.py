"""Build the current results from ``bench/results/*.json``: ``docs/results.md`` and the README block.

Numbers are never typed by hand: every cell below comes from a result file, and every table
names the file and the command that wrote it. Run it after re-running a benchmark
(``make results``); ``--check`` fails when the committed pages differ from what the files give
(CI runs it, so a page cannot drift from its data).

Sources (all under ``bench/results/``):

* ``landmark_depth.json`` — the corner check of the shipped model (``bench/landmark_depth.py``);
* ``depth_accuracy_0013.json`` — single-image LiDAR on 2011_09_26_drive_0013 (``bench/depth_accuracy.py``);
* ``accuracy_shipped.json`` (else ``accuracy_v3.json``) — deterministic SLAM runs with the shipped model (``bench/accuracy.py``);
* ``depth_speed_int8.json`` — the int8 network's latency (``bench/depth_speed.py``);
* ``speed.json`` — frames/s of ``metricslam run`` (``bench/speed.py``);
* ``depth_v3_selection.json`` — how the v3 candidates were judged (``bench/select_depth.py``, retired: docs/history/bench_retired.md);
* ``scale_measurements.json`` — what the scale factors consume (``bench/scale_measurements.py``);
* ``pose_jumps.json`` — live pose jumps vs the continuous odometry stream (``bench/pose_jumps.py``);
* ``own_rig.json``, ``own_rig_turns.json`` — one non-KITTI rig before and after fine-tuning
  (``bench/own_rig.py``), spliced into ``docs/own_camera.md``;
* ``ground_scale.json``, ``speed_0013.json``, ``speed_0013_ground.json`` — ground-plane scale
  (``bench/ground_scale.py``, ``bench/speed.py``), spliced into ``docs/ground_scale.md``
  (``bench/results_ground.py``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bench.results_common import BEGIN, BINS, COMMANDS_SHORTENED, END, RESULTS, ROOT, _load, _src, note_text
from bench.depth_folds import FOLD_SCORE_TEXT, decision_line, fold_table
from bench.results_pages import latency_block, live_vs_offline_block, own_rig_block, rendered_v2_block, soak_block

def corner_table(data: dict) -> str:
    lines = ["| sequence | " + " | ".join(f"{b} m" for b in BINS) + " | worst \\|log\\| |",
             "| --- |" + " --- |" * (len(BINS) + 1)]
    for name, res in data["sequences"].items():
        net, ora = res["network"], res.get("oracle") or {}
        cells = [f"×{net[b]['median']:.2f}" if net[b]["n"] else "–" for b in BINS]
        lines.append(f"| {name}: network | " + " | ".join(cells)
                     + f" | {data['summary'][name]['worst_abs_log_ratio']:.3f} |")
        if ora:
            cells = [f"×{ora[b]['median']:.2f}" if ora[b]["n"] else "–" for b in BINS]
            lines.append(f"| {name}: SGBM oracle on the 32x64 grid | " + " | ".join(cells) + " | |")
    return "\n".join(lines)


def lidar_table(data: dict) -> str:
    lid = data["lidar"]
    bins = lid.get("model_by_range", {})
    head = "| LiDAR, all | abs-rel | " + " | ".join(f"{b} m" for b in bins) + " |"
    return "\n".join([head, "|" + " --- |" * (head.count("|") - 1),
                      f"| ×{lid['model']['median_ratio']:.3f} | {lid['model']['abs_rel']:.3f} | "
                      + " | ".join(f"×{m['median_ratio']:.2f}" for m in bins.values()) + " |"])


def slam_table(data: dict) -> str:
    lines = ["| sequence | trained on | path (m) | scale error | ATE SE(3) | ATE % of path | t_rel |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for s in data["sequences"]:
        res = s["eval"]["metric"].get("result", {})
        if not res:
            continue
        path = res.get("path_length_m") or float("nan")
        lines.append(f"| {s['name']} | {s['trained_on']} | {path:.0f} | {res['scale_error_pct']:.1f} % | "
                     f"{res['ate_rmse_m']:.2f} m | {100 * res['ate_rmse_m'] / path:.2f} % | {res['t_rel_pct']:.1f} % |")
    return "\n".join(lines)


def speed_lines(depth: dict | None, speeds: dict[str, dict]) -> str:
    out = []
    if depth:
        one = depth["results"]["1"]["network"]["median_ms"]
        two = depth["results"]["2"]["network"]["median_ms"]
        out.append(f"- depth network `{depth['model_id']}` ({depth['weights_precision']}): **{one:.1f} ms** per "
                   f"image at 1 thread, {two:.1f} ms at 2 ({depth['machine']}). "
                   + _src("depth_speed_int8.json", depth))
    for name, speed in speeds.items():
        run = next(r for r in speed["runs"] if r["mode"] == "metric")
        fps = run["stats"]["frames"] / run["wall_s"]
        out.append(f"- `metricslam run` with learned scale on `{Path(speed['seq']).name}` "
                   f"({run['stats']['frames']} frames): **{fps:.1f} frames/s** wall, "
                   f"{1000 * run['cpu_s'] / run['stats']['frames']:.0f} CPU-ms per frame, "
                   f"{run['peak_rss_mib']:.0f} MiB peak"
                   + (f"; {note}. " if (note := note_text((speed.get("notes") or [""])[0])) else ". ")
                   + _src(name, speed))
    return "\n".join(out)


def selection_table(data: dict) -> str:
    rows = [data["default"], *data["candidates"]]
    seqs = list(data["default"]["bins"])
    head = ("| model | score | " + " | ".join(f"{s[-4:]} {b} m" for s in seqs for b in BINS)
            + " | LiDAR 0013 median |")
    lines = [head, "|" + " --- |" * (head.count("|") - 1)]
    for r in rows:
        cells = [f"×{r['bins'][s][b]:.2f}" if r["bins"][s].get(b) else "–" for s in seqs for b in BINS]
        lines.append(f"| {r['label']} | {r['score']:.3f} | " + " | ".join(cells)
                     + f" | ×{r['lidar']['median_ratio']:.3f} |")
    w = data.get("winner")
    lines += ["", f"Winner by the pre-registered rule: **{w['label'] if w else 'none'}**."]
    if data.get("slam"):
        per = data["slam"]
        names = list(next(iter(per.values())))
        lines += ["", "SLAM check of the same models (`metricslam run --deterministic --model M`; reported, "
                  "not used by the rule): scale error (scale ratio).", "",
                  "| model | " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
        for label, res in per.items():
            lines.append(f"| {label} | " + " | ".join(f"{res[n]['scale_error_pct']:.1f} % (×{res[n]['scale_ratio']:.3f})"
                                                      for n in names) + " |")
    return "\n".join(lines)


def slam_rule_table(data: dict) -> str:
    names = list(data["default"]["slam"])
    lines = ["| model | " + " | ".join(f"{n} scale error" for n in names) + " | "
             + " | ".join(f"{n} landmark-weighted corner \\|log\\|" for n in names) + " | eligible |",
             "| --- |" + " --- |" * (2 * len(names) + 1)]
    for r in [data["default"], *data["candidates"]]:
        lines.append(f"| {r['label']} | " + " | ".join(f"{r['slam'][n]['scale_error_pct']:.1f} % (×{r['slam'][n]['scale_ratio']:.3f})"
                                                      for n in names)
                     + " | " + " | ".join(f"{r['vo_weighted'][n]:.3f}" for n in names)
                     + f" | {'—' if 'eligible' not in r else ('yes' if r['eligible'] else 'no')} |")
    w = data.get("winner")
    lines += ["", f"Winner by the rule: **{w['label'] if w else 'none eligible'}**."]
    return "\n".join(lines)


def upper_bound_lines(data: dict) -> str:
    rows = [f"{r['name']} {r['metrics']['scale_error_pct']:.1f} % (ATE SE(3) {r['metrics']['ate_rmse_m']:.2f} m)"
            for r in data["rows"] if r["variant"] == "stereo"]
    return ("**The same SLAM with the stereo pair's SGBM depth in the network's place** (an upper bound: "
            "the VO, graph and warp are not what limits the scale): scale error " + ", ".join(rows) + ". "
            + _src("scale_upper_bound_0013.json", data))


def consumed_table(data: dict, ref: str = "stereo") -> str:
    """``bench/scale_measurements.py``: what the scale factors consume, per range bin."""
    first = next(iter(data["sequences"].values()))[ref]
    bins = list(first["bins"])
    lines = ["| sequence | measured / true scale | " + " | ".join(f"{b} m: share, net/ref" for b in bins) + " |",
             "| --- | --- |" + " --- |" * len(bins)]
    for name, res in data["sequences"].items():
        a = res.get(ref)
        if not a or not a.get("keyframes"):
            continue
        cells = [f"{100 * v['fraction']:.0f} %, " + ("–" if v["net_over_ref"] is None else f"×{v['net_over_ref']:.2f}")
                 for v in a["bins"].values()]
        lines.append(f"| {name} | ×{a['measured_over_true_median']:.3f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def pose_jumps_block(data: dict) -> str:
    """Issue #32 item 3: the live pose stream's largest jump vs the continuous ``…/odom`` stream's
    (``bench/pose_jumps.py``)."""
    from bench.pose_jumps import row

    rows = ["| sequence | true max step | live max step (frame) | live / true | continuous max step (frame) "
            "| continuous / true | within 2x | optimized unchanged |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    rows += [row(name, r) for name, r in data["sequences"].items()]
    return "\n".join(rows)


def build() -> tuple[str, str]:
    """(README block, docs/results.md)."""
    corners, lidar = _load("landmark_depth.json"), _load("depth_accuracy_0013.json")
    slam_file = "accuracy_shipped.json" if (RESULTS / "accuracy_shipped.json").is_file() else "accuracy_v3.json"
    slam, sel, dspeed = _load(slam_file), _load("depth_v3_selection_slam.json"), _load("depth_speed_int8.json")
    speeds = {n: d for n in ("speed_0013.json", "speed.json") if (d := _load(n))}
    final_corners, final_slam = _load("landmark_depth_v3_final_06.json"), _load("accuracy_v3_final_06.json")
    ft, bound = _load("depth_v3ft_selection.json"), _load("scale_upper_bound_0013.json")
    consumed = _load("scale_measurements.json")
    parts = []
    if slam:
        parts += ["**SLAM, deterministic runs** (`metricslam run --deterministic`, default settings):", "",
                  slam_table(slam), "", _src(slam_file, slam), ""]
    if bound:
        parts += [upper_bound_lines(bound), ""]
    if corners:
        parts += [f"**Depth network where SLAM samples it** (median z_net / z_tri at corners tracked "
                  f"over 3 frames and triangulated with the ground-truth motion; shipped model "
                  f"`{corners['model']['model_id']}`"
                  + (f"; {corners['name']}" if corners.get("name", "shipped default") != "shipped default" else "")
                  + "):", "", corner_table(corners), "", _src("landmark_depth.json", corners), ""]
    if lidar:
        seen = "2011_09_26_drive_0013" in str(lidar.get("training_data", ""))
        parts += ["**Single image vs LiDAR, 2011_09_26_drive_0013** (median pred/true by range"
                  + ("; this drive is TRAINING data of the model measured, so this is not a held-out score"
                     if seen else "") + "):", "", lidar_table(lidar), "", _src("depth_accuracy_0013.json", lidar), ""]
    speed_text = speed_lines(dspeed, speeds)
    if speed_text:
        parts += ["**Speed**", "", speed_text, ""]
    if parts:
        parts += [COMMANDS_SHORTENED, ""]
    block = "\n".join(parts).rstrip() + "\n"
    page = ["# Results (generated)", "", "Generated by `bench/make_results.py` from `bench/results/*.json`; "
            "do not edit by hand (`make results`). History of earlier sessions: `docs/history/`.", "", block]
    if consumed:
        page += ["## What the SLAM's scale factors consume (shipped model)", "",
                 "Per keyframe of a deterministic run, the landmarks the back end turns into scale factors, "
                 "against the keyframe's own stereo depth at the same pixels: the share of measurements per "
                 "range bin and the network's median depth ratio there; `measured / true` is the median over "
                 "keyframes of the back end's robust scale estimate over the true one (it tracks the "
                 "trajectory's scale ratio above).", "", consumed_table(consumed), "",
                 _src("scale_measurements.json", consumed), ""]
    for name, what in (("accuracy_rendered_default.json", "the shipped default (real streets only)"),
                       ("accuracy_rendered_model.json", "the model for rendered worlds, as `metricslam demo` runs it")):
        if rendered := _load(name):
            page += [f"## The demo's rendered world with {what}", "", slam_table(rendered), "", _src(name, rendered), ""]
    page += rendered_v2_block()
    if sel:
        page += ["## Depth v3 candidates (issue #16): the pre-registered rule and the SLAM check", "",
                 selection_table(sel), "", _src("depth_v3_selection_slam.json", sel),
                 "Raw-weight checkpoints and the spread between checkpoints: `bench/results/depth_v3_selection.md`.", ""]
    if final_corners and final_slam:
        page += ["## Depth v3 final retrain (training data + 0013), checked on KITTI 06", "",
                 corner_table(final_corners), "", _src("landmark_depth_v3_final_06.json", final_corners), "",
                 slam_table(final_slam), "", _src("accuracy_v3_final_06.json", final_slam), ""]
    for name, what in (("v4_folds", "v4, every real drive"), ("v5_folds", "v5, v4 + six rendered streets"),
                       ("v6_folds", "v6, v4 + 30 rendered streets"), ("v7_folds", "v7, v4 under contract v2"), ("v8_folds", "v8, v4 x1.7 wide"),
                       ("v5_ship", "v5 ship attempt: its all-drive runs, under rule_depth_ship.md")):
        folds = _load(f"depth_{name}.json")
        if folds:
            page += [f"## Depth {what}: leave-one-drive-out folds, seeds and their ensemble (issue #31)", "",
                     f"Rule committed before any number it decides on: `docs/history/rule_depth_{folds.get('rule', folds.get('recipe', 'v4'))}.md`. "
                     + FOLD_SCORE_TEXT, "", fold_table(folds), "", decision_line(folds), "",
                     _src(f"depth_{name}.json", folds), ""]
    jumps = _load("pose_jumps.json")
    if jumps:
        page += ["## Live pose jumps vs the continuous odometry stream (issue #32)", "",
                 "Largest frame-to-frame step of the live `…/pose` stream and of the continuous `…/odom` "
                 "stream (`metricslam run --deterministic --live-out --continuous-out`), against the largest "
                 "true per-frame motion; `optimized unchanged`: `--out` byte-identical without the streams.",
                 "", pose_jumps_block(jumps), "", _src("pose_jumps.json", jumps), ""]
    if ft:
        page += ["## Depth v3-ft: the shipped model fine-tuned on real city data, selected on SLAM scale", "",
                 slam_rule_table(ft), "", _src("depth_v3ft_selection.json", ft), ""]
    return block, "\n".join(page).rstrip() + "\n"


def splice(readme: str, block: str, name: str = "README.md", tag: str = "") -> str:
    begin = BEGIN.replace("begin", f"begin {tag}", 1) if tag else BEGIN
    end = END.replace("end", f"end {tag}", 1) if tag else END
    if begin not in readme or end not in readme:
        raise SystemExit(f"{name} lacks the markers {begin!r} … {end!r}")
    head, rest = readme.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n{block}{end}{tail}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--check", action="store_true",
                   help="fail if README.md, docs/results.md or docs/own_camera.md are stale")
    args = p.parse_args(argv)
    block, page = build()
    readme_path, page_path = ROOT / "README.md", ROOT / "docs" / "results.md"
    own_path, usage_path = ROOT / "docs" / "own_camera.md", ROOT / "docs" / "usage.md"
    outputs = [(readme_path, splice(readme_path.read_text(), block)), (page_path, page)]
    if own_path.is_file():
        outputs.append((own_path, splice(own_path.read_text(), own_rig_block(), "docs/own_camera.md")))
    if usage_path.is_file():
        outputs.append((usage_path, splice(usage_path.read_text(), live_vs_offline_block(), "docs/usage.md")))
    ground_path = ROOT / "docs" / "ground_scale.md"
    if ground_path.is_file():
        from bench.results_ground import ground_scale_block

        outputs.append((ground_path, splice(ground_path.read_text(), ground_scale_block(), "docs/ground_scale.md")))
    deploy_path = ROOT / "docs" / "deployment.md"
    if deploy_path.is_file():
        text = splice(deploy_path.read_text(), soak_block(), "docs/deployment.md")
        text = splice(text, latency_block(), "docs/deployment.md", tag="latency")
        from deploy.images_smoke import images_smoke_block  # the images' smoke test renders its own block

        outputs.append((deploy_path, splice(text, images_smoke_block(), "docs/deployment.md", tag="images")))
    if args.check:
        stale = [str(p.relative_to(ROOT)) for p, new in outputs if not p.is_file() or p.read_text() != new]
        if stale:
            print(f"stale generated results: {', '.join(stale)}; run `make results` and commit", file=sys.stderr)
            return 1
        return 0
    for path, text in outputs:
        path.write_text(text)
    print(f"wrote {', '.join(str(p.relative_to(ROOT)) for p, _ in outputs)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
