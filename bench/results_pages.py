"""Generated blocks of the reference pages other than the results page: the own-rig tables of
``docs/own_camera.md``, the live-vs-offline table of ``docs/usage.md``, the soak and latency tables of
``docs/deployment.md`` (spliced by ``bench/make_results.py``)."""

from __future__ import annotations

import statistics
from pathlib import Path

from bench.results_common import BINS, ROOT, _load, _src, short_command


def own_rig_table(data: dict) -> str:
    """One row per model of a ``bench/own_rig.py`` result: the SLAM's scale and trajectory errors."""
    lines = ["| drive | model | weights | scale error | ATE SE(3) | ATE % of path | ATE Sim(3) | t_rel | loops "
             "accepted / rejected |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    drive = Path(data["seq"]).name
    for r in data["models"]:
        e = r.get("eval")
        if not e:
            lines.append(f"| {drive} | {r['name']} | {r.get('weights_precision', '?')} | failed | | | | | |")
            continue
        lines.append(f"| {drive} | {r['name']} (`{Path(r['model']).name}`) | {r['weights_precision']} | "
                     f"**{e['scale_error_pct']:.1f} %** | {e['ate_rmse_m']:.2f} m | {e['ate_pct_of_path']:.2f} % | "
                     f"{e['ate_rmse_sim3_m']:.2f} m | {e['t_rel_pct']:.1f} % | {r['run'].get('loops_accepted', '?')} / "
                     f"{r['run'].get('loops_rejected', '?')} |")
    return "\n".join(lines)


def own_rig_corners(data: dict) -> str:
    """Median z_net / z_tri per range bin per model of a ``bench/own_rig.py`` result."""
    bins = ("2-5", *BINS)
    lines = ["| drive: model | " + " | ".join(f"{b} m" for b in bins) + " | all |",
             "| --- |" + " --- |" * (len(bins) + 1)]
    for r in data["models"]:
        net = r["corners"]["network"]
        lines.append(f"| {Path(data['seq']).name}: {r['name']} | "
                     + " | ".join(f"×{net[b]['median']:.2f}" if net[b]["n"] else "–" for b in (*bins, "all")) + " |")
    return "\n".join(lines)


def own_rig_block() -> str:
    """The generated block of docs/own_camera.md (empty without the result files)."""
    parts = []
    for name in ("own_rig.json", "own_rig_turns.json"):
        data = _load(name)
        if data:
            parts += [own_rig_table(data), "", "Depth network at ground-truth-triangulated corners of the "
                      "same drive (median z_net / z_tri per range bin, 1 = right):", "", own_rig_corners(data), "",
                      _src(name, data) + f"; machine: {data.get('machine', '?')}", ""]
    return "\n".join(parts).rstrip() + "\n" if parts else ""


def live_vs_offline_block() -> str:
    """The generated block of docs/usage.md: the README stack recipe against the offline run,
    judged by the rule of ``docs/history/rule_live_vs_offline_session10.md``."""
    rows = ["| drive | live stream (`poses`) | live optimized (`poses --trajectory --finish`), per repeat | offline `run` "
            "| offline `run --deterministic` | median \\|live − offline\\| | within 1 pp |",
            "| --- | --- | --- | --- | --- | --- | --- |"]
    sources = []
    for name in ("stack_first_pose_06.json", "stack_first_pose_0013.json"):
        data = _load(name)
        if not data:
            continue
        live = [r for r in data["live"] if r.get("initial_scale")]
        offline = {r["deterministic"]: r["scale_error_pct"] for r in data["offline"]}
        opt = [r["optimized"]["scale_error_pct"] for r in live]
        diff = statistics.median(abs(e - offline[False]) for e in opt)
        stream = sorted({f"{r['recorded']['scale_error_pct']:.1f} %" for r in live})
        rows.append(f"| {Path(data['sequence']).name} | {', '.join(stream)} | "
                    f"{', '.join(f'{e:.1f} %' for e in opt)} | {offline[False]:.1f} % | {offline[True]:.1f} % | "
                    f"{diff:.1f} pp | {'yes' if diff <= 1.0 else 'no'} |")
        sources.append(_src(name, data))
    if not sources:
        return ""
    return "\n".join(["Scale error against the ground truth:", "", *rows, "", "\n\n".join(sources)]) + "\n"


#: the 10,000-frame soaks of docs/deployment.md (#19's target: peak RSS within 50 MiB of warm-up)
#: and how each row is told apart (every run of one setting is shown, not the best)
SOAK_FILES = (("slam_service_soak_10000.json", ""), ("slam_service_soak_10000_repeat.json", ", another run"),
              ("slam_service_soak_10000_third.json", ", a third run"), ("slam_service_soak_10000_500kf.json", ""))


def soak_block() -> str:
    """The generated block of docs/deployment.md: the SLAM service's 10,000-frame soaks."""
    rows = ["| settings over the shipped ones | roll-overs | RSS MiB after warm-up / end / max "
            "| peak above warm-up | growth MiB per 1000 frames (after warm-up; 2nd half) | within 50 MiB |",
            "| --- | --- | --- | --- | --- | --- |"]
    sources = []
    for name, label in SOAK_FILES:
        data = _load(name)
        if not data:
            continue
        for config, r in data["results"].items():
            env = (", ".join(f"`{k}={v}`" for k, v in r.get("env", {}).items()) or f"none ({config})") + label
            rows.append(f"| {env} | {r['rollovers']} | {r['rss_mib_at_warmup']} / {r['rss_mib_end']} / "
                        f"{r['rss_mib_max']} | {r['peak_mib_above_warmup']} MiB | "
                        f"{r['growth_mib_per_1000_frames_after_warmup']}; {r['growth_mib_per_1000_frames_second_half']} | "
                        f"{'yes' if r['peak_mib_above_warmup'] <= 50 else 'no'} |")
        sources.append(_src(name, data) + f"; machine before: {data.get('machine_before', '?')}")
    if not sources:
        return ""
    return "\n".join([*rows, "", "\n\n".join(sources)]) + "\n"


def latency_block() -> str:
    """The generated latency lines of docs/deployment.md: the live stack over a 1,500-frame
    rendered loop at 10 Hz (``bench/results/zenoh_loop1500_10hz.*``; the command is in the .md)."""
    runs, md = _load("zenoh_loop1500_10hz.json"), ROOT / "bench" / "results" / "zenoh_loop1500_10hz.md"
    if not runs or not md.is_file():
        return ""
    head = md.read_text().splitlines()
    command = next((ln.split("`")[1] for ln in head if ln.startswith("Command:")), "?")
    machine = next((ln.removeprefix("Machine: ").strip() for ln in head if ln.startswith("Machine:")), "?")
    pipe = next(r for r in runs if r["kind"] == "pipeline")
    one, two = pipe["sweep"][0], pipe["two_cameras"]
    lines = [f"Rendered loop, {one['frames']:,} frames 1241x376 (`metricslam synth DIR --frames 1500 --seed 3 --path loop`), "
             f"frame-in → pose-out at {one['rate_hz']:.0f} Hz: p50 {one['p50_ms']:.1f} ms, **p99 {one['p99_ms']:.1f} ms**, "
             f"max {one['max_ms']:.1f} ms, {one['queue_drops']} drops, {one['poses']}/{one['frames']} poses."]
    if two:
        lines.append("Two cameras at once: " + "; ".join(
            f"{c['poses']}/{c['frames']} poses, p99 {c['p99_ms']:.0f} ms, {c['queue_drops']} drops" for c in two)
            + " (two full SLAMs and the depth service need more than two cores).")
    return "\n".join([" ".join(lines), "", f"Source: `bench/results/zenoh_loop1500_10hz.json`, command: "
                      f"`{short_command(command)}`; machine: {machine}"]) + "\n"


def rendered_v2_block() -> list[str]:
    """Issue #34's rendered-world model v2 on ``docs/history/rule_rendered_v2.md``'s validation worlds."""
    runs = {(m, w): _load(f"rendered_v2_val_{m}_{w}.json") for m in ("baseline", "candidate") for w in ("620", "1241")}
    if not all(runs.values()):
        return []
    rows = ["| model | render width | mean scale ratio | mean \\|scale error\\| | failures |", "| --- | --- | --- | --- | --- |"]
    for (m, w), d in runs.items():
        r = [q["eval"]["metric"]["result"] for q in d["sequences"]]
        ok = [x for x in r if x["ate_rmse_sim3_m"] <= 1.0]
        rows.append(f"| {m} | {w} px | {statistics.mean(x['scale_ratio'] for x in ok):.3f} | "
                    f"{statistics.mean(x['scale_error_pct'] for x in ok):.2f} % | {len(r) - len(ok)} of {len(r)} |")
    return ["## The model for rendered worlds, v2 candidate (issue #34): not shipped", "",
            "Rule committed before the candidate was trained, and its outcome: `docs/history/rule_rendered_v2.md`. "
            "Validation worlds: seeds 41-52, loop, 150 frames; failure = ATE Sim(3) > 1 m (left out of the means).",
            "", *rows, "", _src("rendered_v2_val_candidate_620.json", runs["candidate", "620"]), ""]
