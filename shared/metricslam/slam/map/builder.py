"""A :class:`~metricslam.slam.map.format.SavedMap` from a finished session.

The map frame is the session's world frame (its first keyframe's camera, ``docs/conventions.md``),
in metres when learned scale made it metric. Per keyframe ``S_world_kf`` (the global graph's
final estimate) becomes the rigid ``T_map_kf`` plus ``scale_kf`` (metres per keyframe VO unit);
the loop database's verification features (each indexed keyframe's ORB corners with the depth
network's depth, then its VO landmarks, ``exact``; keyframe VO units) are converted to metres
with that scale, so a later session verifies against metric points. Landmarks are those points
in the map frame, each with its one observation (keyframe, pixel): marginalized keyframes keep no
landmark ids, so a point seen by two keyframes is two landmarks.
"""

from __future__ import annotations

import numpy as np

from metricslam.errors import MapError
from metricslam.geometry import sim3, so3
from metricslam.slam.map.format import SavedMap


def map_from_session(session, depth_model_id: str | None, metric: bool, source: dict | None = None) -> SavedMap:
    """The map of a closed :class:`~metricslam.slam.pipeline.SlamPipeline` whose back end kept
    its loop database open (``backend.keep_loop_database = True``).

    Raises:
        MapError: no global graph (``--vo-only``), loop closure disabled, nothing indexed.
    """
    backend = session.backend
    if backend is None:
        raise MapError("--save-map needs the global graph: drop --vo-only")
    detector = backend.estimator.loop_detector
    if detector is None:
        raise MapError("--save-map needs the loop database: enable graph.loop in the config")
    S_by_frame = backend.optimized_keyframe_poses()
    history = [h for h in session.scale_history()["scale_history"] if h["frame_index"] in S_by_frame]
    history.sort(key=lambda h: h["kf_id"])
    if not history:
        raise MapError("--save-map: the session has no optimized keyframe to save (too short a run)")
    T_map_kf, scale_kf = [], []
    for h in history:
        S = S_by_frame[h["frame_index"]]
        s = sim3.scale(S)
        T = np.eye(4)
        T[:3, :3] = so3.project_to_so3(S[:3, :3] / s)
        T[:3, 3] = S[:3, 3]
        T_map_kf.append(T)
        scale_kf.append(s)
    kf_ids = np.array([h["kf_id"] for h in history], dtype=np.int64)
    keyframes = {
        "kf_id": kf_ids,
        "frame_index": np.array([h["frame_index"] for h in history], dtype=np.int64),
        "t_ns": np.array([h["t_ns"] for h in history], dtype=np.int64),
        "T_map_kf": np.array(T_map_kf, dtype=np.float64).reshape(-1, 4, 4),
        "scale_kf": np.array(scale_kf, dtype=np.float64),
        "scale_live": np.array([h["scale_live"] for h in history], dtype=np.float64),
        "scale_factors": np.array([h["scale_factors"] or 0 for h in history], dtype=np.int64),
        "scale_measured_median": np.array([np.nan if h["scale_measured_median"] is None
                                           else h["scale_measured_median"] for h in history], dtype=np.float64),
    }
    exported = detector.export_database()
    if exported is None:
        raise MapError("--save-map: the loop database indexed no keyframe (too short a run)")
    vocab, ids, rows, features = exported
    index = {int(k): i for i, k in enumerate(kf_ids)}
    keep = [j for j, k in enumerate(ids) if int(k) in index]
    loop_db, landmarks = _loop_db(vocab, ids[keep], rows[keep], [features[j] for j in keep], index,
                                  keyframes)
    return SavedMap(_camera_of(session), depth_model_id, metric,
                    {"keyframes": keyframes, "landmarks": landmarks, "loop_db": loop_db}, dict(source or {}))


def _camera_of(session):
    return session.camera


def _loop_db(vocab, ids, rows, features, index, keyframes) -> tuple[dict, dict]:
    offsets = np.zeros(len(ids) + 1, dtype=np.int64)
    uv, pts, desc, exact, lm_p, lm_kf, lm_uv = [], [], [], [], [], [], []
    for j, (k, (f_uv, f_desc, f_pts, f_exact)) in enumerate(zip(ids, features)):
        i = index[int(k)]
        p_m = np.asarray(f_pts, float).reshape(-1, 3) * keyframes["scale_kf"][i]
        uv.append(np.asarray(f_uv, np.float32).reshape(-1, 2))
        pts.append(p_m.astype(np.float32))
        desc.append(np.asarray(f_desc, np.uint8).reshape(-1, 32))
        exact.append(np.asarray(f_exact, bool).reshape(-1))
        T = keyframes["T_map_kf"][i]
        lm_p.append(p_m @ T[:3, :3].T + T[:3, 3])
        lm_kf.append(np.full(len(p_m), int(k), np.int64))
        lm_uv.append(uv[-1])
        offsets[j + 1] = offsets[j] + len(p_m)

    def cat(parts, shape, dtype):
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)

    loop_db = {"vocabulary_words": np.ascontiguousarray(vocab.words, np.uint8),
               "vocabulary_idf": np.asarray(vocab.idf, np.float32),
               "bow_kf_id": np.asarray(ids, np.int64),
               "bow_rows": np.asarray(rows, np.float32).reshape(len(ids), vocab.size),
               "feature_offsets": offsets, "feature_uv_px": cat(uv, (0, 2), np.float32),
               "feature_points_kf_m": cat(pts, (0, 3), np.float32),
               "feature_descriptors": cat(desc, (0, 32), np.uint8),
               "feature_exact": cat(exact, (0,), np.bool_)}
    landmarks = {"p_map_m": cat(lm_p, (0, 3), np.float64), "obs_kf_id": cat(lm_kf, (0,), np.int64),
                 "obs_uv_px": cat(lm_uv, (0, 2), np.float32)}
    return loop_db, landmarks
