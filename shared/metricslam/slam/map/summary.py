"""What a saved map holds, for ``metricslam map info`` (``docs/maps.md``, "Inspecting a map").

:func:`map_summary` reads nothing but the :class:`~metricslam.slam.map.format.SavedMap` it is given
(loaded, so every checksum, dtype and shape was checked) and the size of its folder; the command
line prints it or writes it as JSON. Positions are the keyframes' ``T_map_kf`` (metres in a
metric map; else the first keyframe's VO units).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metricslam.slam.map.format import SCHEMA_VERSION, SavedMap


def map_summary(saved: SavedMap, path: str | Path) -> dict:
    """A JSON-ready summary of ``saved`` (loaded from ``path``): counts, camera, depth model,
    vocabulary, the sessions that built it, the keyframes' time span (s) and the box their
    positions fill (map units), and the folder's size on disk (bytes). Learned scale: how many
    keyframes the depth network measured, the scale factors in all, and how far each measured
    keyframe's solved scale (``scale_kf``) is from its network's median measurement (|log|,
    median and 90th percentile over the measured keyframes)."""
    root = Path(path)
    kf, db = saved.arrays["keyframes"], saved.arrays["loop_db"]
    p = np.asarray(kf["T_map_kf"], float)[:, :3, 3].reshape(-1, 3)
    t_ns = np.asarray(kf["t_ns"], np.int64)
    measured = np.asarray(kf["scale_measured_median"], float)
    gap = np.abs(np.log(measured / np.asarray(kf["scale_kf"], float)))
    gap = gap[np.isfinite(gap)]
    source = dict(saved.source)
    extended = list(source.pop("extended_by", []) or [])
    return {
        "path": str(root), "schema_version": SCHEMA_VERSION, "metric": saved.metric,
        "units": "m" if saved.metric else "VO units of the first keyframe",
        "keyframes": saved.n_keyframes, "landmarks": int(len(saved.arrays["landmarks"]["p_map_m"])),
        "place_recognition_rows": int(len(db["bow_kf_id"])), "features": int(len(db["feature_uv_px"])),
        "vocabulary_words": int(len(db["vocabulary_words"])), "vocabulary_id": saved.vocabulary_id,
        "camera": saved.camera.model_dump(), "depth_model_id": saved.depth_model_id,
        "built_by": source, "extended_by": extended, "sessions": 1 + len(extended),
        "keyframes_scale_measured": int(np.isfinite(measured).sum()),
        "scale_factors": int(np.sum(kf["scale_factors"])),
        "scale_gap_log_median": float(np.median(gap)) if len(gap) else None,
        "scale_gap_log_p90": float(np.percentile(gap, 90)) if len(gap) else None,
        "time_span_s": float((t_ns.max() - t_ns.min()) / 1e9) if len(t_ns) else 0.0,
        "box_min": p.min(axis=0).tolist() if len(p) else None,
        "box_max": p.max(axis=0).tolist() if len(p) else None,
        "bytes": int(sum(f.stat().st_size for f in root.rglob("*") if f.is_file())),
    }


def summary_lines(s: dict) -> list[str]:
    """:func:`map_summary` as the lines ``metricslam map info`` prints."""
    unit = "m" if s["metric"] else "VO units"
    cam = s["camera"]
    lines = [
        f"map {s['path']}: schema {s['schema_version']}, {s['keyframes']} keyframes, {s['landmarks']} landmarks, "
        f"{s['place_recognition_rows']} place-recognition rows ({s['vocabulary_words']}-word vocabulary "
        f"{s['vocabulary_id']}); {'metric (metres)' if s['metric'] else 'NOT metric (' + s['units'] + ')'}",
        f"camera: fx_px={cam['fx_px']} fy_px={cam['fy_px']} cx_px={cam['cx_px']} cy_px={cam['cy_px']} "
        f"{cam['width_px']}x{cam['height_px']}; depth model {s['depth_model_id'] or 'none (no learned scale)'}",
        f"built by: {s['built_by'].get('sequence', '?')} ({s['built_by'].get('mode', '?')})"
        + "".join(f"; extended by {e.get('sequence', '?')} ({e.get('mode', '?')})" for e in s["extended_by"]),
    ]
    if s["scale_gap_log_median"] is None:
        lines.append("learned scale: no keyframe measured by a depth network")
    else:
        lines.append(f"learned scale: {s['keyframes_scale_measured']} of {s['keyframes']} keyframes measured "
                     f"({s['scale_factors']} scale factors); solved vs the network's median measurement per "
                     f"keyframe: {100 * np.expm1(s['scale_gap_log_median']):.1f} % apart at the median, "
                     f"{100 * np.expm1(s['scale_gap_log_p90']):.1f} % at the 90th percentile")
    if s["box_min"] is not None:
        size = np.subtract(s["box_max"], s["box_min"])
        lines.append(f"keyframe timestamps span {s['time_span_s']:.1f} s; their positions fill a "
                     f"{size[0]:.1f} x {size[1]:.1f} x {size[2]:.1f} {unit} box (x, y, z of the map frame)")
    lines.append(f"{s['bytes'] / 1e6:.1f} MB on disk; every file matches its checksum")
    return lines
