"""Offline, in-process reproduction of the live map-frame poses (MapFrameSession as the SLAM
service builds it), session 2 of KITTI raw 0013 against the session-1 map.
usage: repro.py OUT.npz [--rate HZ] [--deterministic]"""
import argparse, json, time, os
from pathlib import Path
import numpy as np
from metricslam.datasets import open_sequence
from metricslam.datasets.frame_reader import FrameReader
from metricslam.slam.config_file import load_system_config
from metricslam.slam.system_config import LIVE_PROFILE
from metricslam.slam.session_builder import build_session
from metricslam.slam.depth_source import OnnxDepthSource
from metricslam.slam.map.localization import MapLocalization, MapFrameSession, open_map
from metricslam.slam.map.relocalizer import to_map_frame

ap = argparse.ArgumentParser()
ap.add_argument("out"); ap.add_argument("--rate", type=float, default=10.0)
ap.add_argument("--deterministic", action="store_true")
ap.add_argument("--seq", default="/work/exp/s22/live/work/k13_s2"); ap.add_argument("--map", default="/work/exp/s22/live/work/k13_map")
ap.add_argument("--preset", default="kitti"); ap.add_argument("--model", default=None); ap.add_argument("--depth-queue", type=int, default=None)
a = ap.parse_args()
W = Path("/work/exp/s22/live/work")
ov = {"vo": {"preset": a.preset}}
if a.model: ov["depth"] = {"model_path": a.model}
if a.depth_queue: ov["graph"] = {"depth_queue_size": a.depth_queue}
if a.deterministic:
    ov["deterministic"] = True
config = load_system_config(None, env={}, profile=LIVE_PROFILE, overrides=ov)
depth = OnnxDepthSource(config.depth.model_path).load()
seq = open_sequence(a.seq)
frames = FrameReader(seq)
pipe = build_session(seq.camera, config, depth_source=depth)
from metricslam.slam.map.format import load_map
saved = load_map(a.map)
loc = MapLocalization(saved, seq.camera, config.graph_config().loop, a.map)
events = []
mfs = MapFrameSession(pipe, loc, lambda f, d: events.append((f, d)))
est_flags = []; used_log = []; S_pre = []; n_pre = []
inner_est, live, S_used, frame_id, anchors, newest_graph_kf, graph_at = [], [], [], [], [], [], []
t0 = time.monotonic()
for i in range(len(seq)):
    if a.rate > 0:
        dt = t0 + i / a.rate - time.monotonic()
        if dt > 0:
            time.sleep(dt)
    fr = frames[i]
    orig = pipe.process
    got = {}
    def wrapped(f, _o=orig):
        e = _o(f); got["e"] = e; return e
    pipe.process = wrapped
    e = mfs.process(fr)
    pipe.process = orig
    inner_est.append(np.asarray(got["e"].T_world_cam, float))
    live.append(np.asarray(e.T_world_cam, float))
    S_used.append(np.full((4, 4), np.nan) if mfs.S_map_world is None else np.array(mfs.S_map_world))
    frame_id.append(mfs.frame_id)
    g = pipe.backend.optimized_keyframe_poses()
    Sp = loc.relocalizer.S_map_world(g, metric_world=False)
    cands = loc.relocalizer.candidates(g, metric_world=bool(pipe.backend.scale_established))
    used_log.append((loc.matches_used, len(cands), len(loc.relocalizer.matches), sorted(m.kf_frame for m, _ in cands)))
    S_pre.append(np.full((4, 4), np.nan) if Sp[0] is None else Sp[0]); n_pre.append(Sp[1])
    newest_graph_kf.append(max(g) if g else -1)
    # live-time composition from the back end's latest solve, where the anchor kf is in it
    an = pipe._anchors.get(i)
    anchors.append(-1 if an is None else an[0])
    est_flags.append((bool(got["e"].scale_established), got["e"].scale_state.value, int(got["e"].scale_factors)))
wall = time.monotonic() - t0
mfs.close()
final_world = [np.asarray(p.T_world_cam, float) for p in pipe.trajectory()]
S_final = np.array(loc.S_map_world)
final_map = {p.frame_index: np.asarray(p.T_world_cam, float) for p in mfs.trajectory()}
np.savez(a.out, inner=np.array(inner_est), live=np.array(live), S=np.array(S_used),
         is_map=np.array([f == "map" for f in frame_id]), final_world=np.array(final_world), S_final=S_final,
         final_map=np.array([final_map.get(i, np.full((4, 4), np.nan)) for i in range(len(seq))]),
         newest_graph_kf=np.array(newest_graph_kf), S_pre=np.array(S_pre), n_pre=np.array(n_pre), anchor_kf=np.array(anchors),
         first_frame=-1 if loc.first_frame is None else loc.first_frame,
         first_map_frame=-1 if mfs.first_map_frame is None else mfs.first_map_frame)
json.dump({"used": used_log, "flags": est_flags, "corrections": pipe._scale_history.corrections(),
           "matches": [[m.kf_frame, m.map_kf_id, m.frame_now, m.n_inliers, m.S_world_kf_vo is not None] for m in loc.relocalizer.matches]},
          open(a.out.replace(".npz", ".json"), "w"))
print(json.dumps({"wall_s": wall, "events": events, "first_frame": loc.first_frame,
                  "first_map_frame": mfs.first_map_frame, "matches": len(loc.relocalizer.matches),
                  "used": loc.matches_used, "n_queries": loc.relocalizer.n_queries, "query_ms_mean": float(np.mean(loc.relocalizer.query_ms)) if loc.relocalizer.query_ms else None, "load": os.getloadavg()}))  # n_queries, query_ms_mean: added in session 24
