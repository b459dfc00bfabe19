"""The generated block of docs/ground_scale.md (spliced by ``bench/make_results.py``): accuracy of
each scale-source setting, road height per keyframe, the health signal on each drive, the road
estimator alone (``bench/results/ground_scale.json``, ``bench/ground_scale.py``) and the speed of
``metricslam run`` with learned and with learned + ground scale (``speed_0013.json``,
``speed_0013_ground.json``, ``bench/speed.py``). Numbers are never typed into the page."""

from __future__ import annotations

import math
from pathlib import Path

from bench.results_common import _load, _src, note_text

SETTINGS = ("learned", "ground", "learned,ground")
#: (result file, scale sources of its run)
SPEED_FILES = (("speed_0013.json", "learned"), ("speed_0013_ground.json", "learned,ground"))


def _cell(value: object, fmt: str = "") -> str:
    return "—" if value is None else format(value, fmt)


def accuracy_table(data: dict) -> str:
    rows = ["| drive | role | sources | scale error % | ATE % of path | t_rel % | keyframes with a ground "
            "factor % | road height: median \\|error\\| % |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, entry in data["sequences"].items():
        for sources in SETTINGS:
            r = entry.get(sources)
            if not r:
                continue
            g = r.get("ground", {})
            rows.append(f"| {name} | {entry['role']} | {sources} | {r['scale_error_pct']} | {r['ate_pct_of_path']} | "
                        f"{_cell(r.get('t_rel_pct'))} | {_cell(g.get('keyframes_with_factor_pct'))} | "
                        f"{_cell(g.get('height_median_abs_err_pct'))} |")
    return "\n".join(rows)


def health_lines(data: dict) -> str:
    out = []
    for name, entry in data["sequences"].items():
        g = entry.get("learned,ground", {}).get("ground", {})
        d = g.get("health_disagreement_log_median")
        if d is None:
            continue
        out.append(f"- {name} with learned,ground: learned / ground scale per keyframe, median "
                   f"**{math.exp(d):.3f}** (learned / true {g.get('learned_over_true_median')}, ground / true "
                   f"{g.get('ground_over_true_median')}); health warnings raised: "
                   f"**{g.get('health_warnings_issued')}**.")
    return "\n".join(out)


def estimator_lines(data: dict) -> str:
    out = []
    for name, entry in data["sequences"].items():
        a = entry.get("estimator_true_motion")
        if a:
            out.append(f"- {name}: {a['pairs']} frame pairs {a['gap_frames']} frames apart with the true "
                       f"relative pose: {a['accepted_pct']} % accepted, median height {a['height_median_m']} m, "
                       f"median |error| {a['median_abs_err_pct']} %.")
    return "\n".join(out)


def _code(result: dict) -> str:
    """``checkout HEAD f0c7471`` of a result's ``code`` line (the import path left out)."""
    code = str(result.get("code", "?"))
    return code.split("; ")[-1] if "; " in code else code


def speed_lines() -> str:
    out = []
    for name, sources in SPEED_FILES:
        speed = _load(name)
        if not speed:
            continue
        run = next((r for r in speed["runs"] if r.get("mode") == "metric" and "stats" in r), None)
        if run is None:
            continue
        stats, backend = run["stats"], run["stats"].get("backend", {})
        ground = backend.get("ground_ms_mean")
        out.append(f"- `metricslam run` on `{Path(speed['seq']).name}`, scale sources {sources}: "
                   f"**{stats['fps']:.1f} frames/s** (the run's own count: frames over the loop, image loading "
                   f"and the back end's final drain included), {1000 * run['cpu_s'] / stats['frames']:.0f} "
                   f"CPU-ms per frame"
                   + (f", road fit **{ground:.1f} ms** per keyframe" if ground else "")
                   + f"; {_code(speed)}, {speed.get('date_utc', '?')}"
                   + (f"; {note}" if (note := note_text((speed.get('notes') or [''])[0])) else "")
                   + f". {_src(name, speed)}")
    return "\n".join(out)


def ground_scale_block() -> str:
    """The block (empty without ``ground_scale.json``)."""
    data = _load("ground_scale.json")
    if not data:
        return ""
    parts = [f"Camera {data['mount_height_m']} m above the road; the estimator's parameters were set on "
             f"rendered streets and `{data['tuned_on']}`, every other drive is held out.", "",
             accuracy_table(data), "", "**Health signal** (`learned,ground` runs):", "", health_lines(data), "",
             "**Road estimator alone**:", "", estimator_lines(data), "", _src("ground_scale.json", data)]
    speed = speed_lines()
    if speed:
        parts += ["", "**Speed** (wall-clock: only a quiet machine's numbers mean anything):", "", speed]
    return "\n".join(parts) + "\n"
