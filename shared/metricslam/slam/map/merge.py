"""Extending a loaded map (``metricslam run --map MAP --save-map OUT``; docs/maps.md).

The session that relocalized into ``saved`` is joined to it in a Sim(3) pose graph solved once,
after the run (gtsam's C++ factors only, LM):

* the matched **map keyframes are fixed nodes** ``M_j = T_map_mapkf`` (a prior of σ 1e-6);
* the session's keyframes are nodes ``X_i = S_map_kf`` (metres per keyframe VO unit),
  initialized as ``S_map_world · S_world_kf`` (the relocalization's alignment);
* **odometry**: consecutive session keyframes keep the relative Sim(3) of the session's own final
  graph (``S_world_kf_i⁻¹ · S_world_kf_j``; σ 0.005 rad, 0.05 units, 0.01 log-scale);
* **cross-session loop factors**: every verified relocalization match consistent with
  ``S_map_world`` (the gates of :meth:`Relocalizer.S_map_world`) is ``M_j⁻¹ · X_i = S_mapkf_kf``
  (σ 0.05 rad, 0.5 m, 0.1 log-scale, Huber k 1.345), so the map corrects the session's drift
  between and beyond its matches instead of one rigid alignment for all of it.

The merged map keeps the loaded map's arrays unchanged (its keyframes are fixed; its vocabulary
stays the map's) and appends the session's keyframes with new ids (the map's largest + 1 + the
session's id), their solved ``T_map_kf``/``scale_kf``, their verification features (metres with
the solved scale) and landmarks, and — so that a later session can relocalize against them —
their bag-of-words rows **in the map's vocabulary**, computed when they were queried
(:attr:`Relocalizer.bow_by_frame`; a keyframe never queried keeps no row). Frames and units:
``docs/conventions.md``.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from metricslam.errors import MapError
from metricslam.geometry import sim3, so3
from metricslam.slam.graph.gtsam_sim3 import from_gtsam, to_gtsam
from metricslam.slam.map.format import SavedMap
from metricslam.slam.map.relocalizer import Relocalizer

#: σ of the session's own relative poses [ω rad ×3, u units ×3, λ log-scale]
ODOMETRY_SIGMAS = [0.005] * 3 + [0.05] * 3 + [0.01]
#: σ of one verified match (PnP against the map's metric points; scale from the session)
MATCH_SIGMAS = [0.05] * 3 + [0.5] * 3 + [0.1]
FIXED_SIGMA = 1e-6


def merge_session(saved: SavedMap, session: SavedMap, relocalizer: Relocalizer, S_map_world: np.ndarray,
                  metric_world: bool) -> tuple[SavedMap, dict]:
    """``(merged map, stats)`` of the loaded map ``saved`` and ``session`` (the session's own map
    in its world frame, :func:`~metricslam.slam.map.builder.map_from_session`), joined through
    ``relocalizer``'s matches (module docstring).

    Raises:
        MapError: the session has no verified match consistent with ``S_map_world``.
    """
    kf = session.arrays["keyframes"]
    S_world_kf = [sim3.from_rts(T[:3, :3], T[:3, 3], s) for T, s in zip(kf["T_map_kf"], kf["scale_kf"])]
    index = {int(f): i for i, f in enumerate(kf["frame_index"])}
    cross = [(m, index[m.kf_frame]) for m, _ in relocalizer.agreeing(
        S_map_world, {int(f): S_world_kf[i] for f, i in index.items()}, metric_world)]
    if not cross:
        raise MapError("--map with --save-map: no verified match agrees with the relocalization; "
                       "nothing joins the session to the map")
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    x = [gtsam.symbol("x", i) for i in range(len(S_world_kf))]
    for i, S in enumerate(S_world_kf):
        values.insert(x[i], to_gtsam(S_map_world @ S))
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array(ODOMETRY_SIGMAS))
    for i in range(len(x) - 1):
        graph.add(gtsam.BetweenFactorSimilarity3(
            x[i], x[i + 1], to_gtsam(sim3.inverse(S_world_kf[i]) @ S_world_kf[i + 1]), odo))
    fixed = gtsam.noiseModel.Isotropic.Sigma(7, FIXED_SIGMA)
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345),
                                            gtsam.noiseModel.Diagonal.Sigmas(np.array(MATCH_SIGMAS)))
    T_map_mapkf = {int(k): T for k, T in zip(saved.arrays["keyframes"]["kf_id"], saved.arrays["keyframes"]["T_map_kf"])}
    for m, i in cross:
        mk = gtsam.symbol("m", m.map_kf_id)
        if not values.exists(mk):
            values.insert(mk, to_gtsam(sim3.from_se3(T_map_mapkf[m.map_kf_id])))
            graph.add(gtsam.PriorFactorSimilarity3(mk, to_gtsam(sim3.from_se3(T_map_mapkf[m.map_kf_id])), fixed))
        graph.add(gtsam.BetweenFactorSimilarity3(
            mk, x[i], to_gtsam(relocalizer.measured_S_mapkf_kf(m, S_world_kf[i], metric_world)), robust))
    error_before = graph.error(values)
    solved = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    S_map_kf = [from_gtsam(solved.atSimilarity3(k)) for k in x]
    merged = _appended(saved, session, S_map_kf, relocalizer.bow_by_frame)
    moved = [float(np.linalg.norm(S[:3, 3] - (S_map_world @ S0)[:3, 3])) for S, S0 in zip(S_map_kf, S_world_kf)]
    return merged, {"session_keyframes": len(x), "cross_session_factors": len(cross),
                    "map_keyframes_fixed": len({m.map_kf_id for m, _ in cross}),
                    "graph_error_before": float(error_before), "graph_error_after": float(graph.error(solved)),
                    "moved_m_max": max(moved), "keyframes": merged.n_keyframes}


def _appended(saved: SavedMap, session: SavedMap, S_map_kf: list[np.ndarray], bow_by_frame: dict) -> SavedMap:
    """``saved`` with ``session``'s keyframes appended at their solved poses ``S_map_kf``."""
    kf, db = session.arrays["keyframes"], session.arrays["loop_db"]
    offset = int(saved.arrays["keyframes"]["kf_id"].max()) + 1 if saved.n_keyframes else 0
    new_kf = dict(kf)
    new_kf["kf_id"] = kf["kf_id"] + offset
    new_kf["T_map_kf"] = np.array([_rigid(S) for S in S_map_kf], dtype=np.float64).reshape(-1, 4, 4)
    new_kf["scale_kf"] = np.array([sim3.scale(S) for S in S_map_kf], dtype=np.float64)
    ratio = {int(k): new_kf["scale_kf"][i] / kf["scale_kf"][i] for i, k in enumerate(kf["kf_id"])}
    pose = {int(k): new_kf["T_map_kf"][i] for i, k in enumerate(kf["kf_id"])}
    frame_of = {int(k): int(f) for k, f in zip(kf["kf_id"], kf["frame_index"])}
    o = db["feature_offsets"]
    rows, ids, offsets = [], [], [0]
    parts: dict[str, list] = {"uv": [], "pts": [], "desc": [], "exact": [], "lm_p": [], "lm_kf": []}
    for j, k in enumerate(db["bow_kf_id"]):
        row = bow_by_frame.get(frame_of.get(int(k), -1))
        if row is None:
            continue  # never queried: no row in the map's vocabulary
        a, b = o[j], o[j + 1]
        pts = db["feature_points_kf_m"][a:b].astype(np.float64) * ratio[int(k)]
        T = pose[int(k)]
        rows.append(row)
        ids.append(int(k) + offset)
        offsets.append(offsets[-1] + (b - a))
        parts["uv"].append(db["feature_uv_px"][a:b])
        parts["pts"].append(pts.astype(np.float32))
        parts["desc"].append(db["feature_descriptors"][a:b])
        parts["exact"].append(db["feature_exact"][a:b])
        parts["lm_p"].append(pts @ T[:3, :3].T + T[:3, 3])
        parts["lm_kf"].append(np.full(b - a, int(k) + offset, np.int64))
    old_kf, old_lm, old_db = (saved.arrays[g] for g in ("keyframes", "landmarks", "loop_db"))
    F0 = len(old_db["feature_uv_px"])

    def cat(old, new):
        return np.concatenate([old, *new]).astype(old.dtype) if new else old.copy()

    loop_db = {"vocabulary_words": old_db["vocabulary_words"], "vocabulary_idf": old_db["vocabulary_idf"],
               "bow_kf_id": cat(old_db["bow_kf_id"], [np.array(ids, np.int64)]),
               "bow_rows": cat(old_db["bow_rows"], [np.array(rows, np.float32).reshape(len(rows), -1)]),
               "feature_offsets": cat(old_db["feature_offsets"], [F0 + np.array(offsets[1:], np.int64)]),
               "feature_uv_px": cat(old_db["feature_uv_px"], parts["uv"]),
               "feature_points_kf_m": cat(old_db["feature_points_kf_m"], parts["pts"]),
               "feature_descriptors": cat(old_db["feature_descriptors"], parts["desc"]),
               "feature_exact": cat(old_db["feature_exact"], parts["exact"])}
    landmarks = {"p_map_m": cat(old_lm["p_map_m"], parts["lm_p"]), "obs_kf_id": cat(old_lm["obs_kf_id"], parts["lm_kf"]),
                 "obs_uv_px": cat(old_lm["obs_uv_px"], parts["uv"])}
    keyframes = {name: cat(old_kf[name], [new_kf[name]]) for name in old_kf}
    source = {**saved.source, "extended_by": [*saved.source.get("extended_by", []), session.source]}
    return dataclasses.replace(saved, arrays={"keyframes": keyframes, "landmarks": landmarks, "loop_db": loop_db},
                               source=source)


def _rigid(S: np.ndarray) -> np.ndarray:
    R, t, _ = sim3.split(S)
    T = np.eye(4)
    T[:3, :3] = so3.project_to_so3(R)
    T[:3, 3] = t
    return T


def save_extended_map(localization, pipeline, path, depth_model_id: str | None, metric: bool,
                      source: dict | None = None) -> dict:
    """The loaded map extended by ``pipeline``'s session (relocalized through ``localization``, a
    :class:`~metricslam.slam.map.localization.MapLocalization`), saved to ``path`` atomically
    (``path`` may be the loaded map's own folder). Returns ``{"path", "keyframes", "save_s",
    "extended": merge stats}``.

    Raises:
        MapError: the session never relocalized, nothing joins it to the map, or ``path`` cannot
            be written (a previous map there is left as it was).
    """
    import time

    from metricslam.slam.map.format import save_map
    from metricslam.slam.map.localization import session_map

    t0 = time.perf_counter()
    if localization.S_map_world is None:
        raise MapError(f"--save-map {path}: the session never relocalized into {localization.path}; "
                       "the map was not extended (and not written)")
    session = session_map(pipeline, depth_model_id, metric, source)
    metric_world = localization.saved.metric and bool(getattr(pipeline.backend, "scale_established", False))
    merged, stats = merge_session(localization.saved, session, localization.relocalizer,
                                  localization.S_map_world, metric_world)
    save_map(merged, path)
    return {"path": str(path), "keyframes": merged.n_keyframes, "save_s": time.perf_counter() - t0,
            "extended": stats}
