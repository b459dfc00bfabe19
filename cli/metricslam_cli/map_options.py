"""``metricslam run --save-map MAP`` / ``--map MAP``: maps that outlive a session (docs/maps.md).

``--save-map`` writes the finished session's map (keyframes, landmarks, loop database, camera,
depth model id) atomically. ``--map`` loads one before the first frame (a bad, old, foreign map is
a one-line error), relocalizes the session into it through the map's loop database and the
geometric Sim(3) verification (:mod:`metricslam.slam.map.relocalizer`), and writes the trajectory
in the map frame from the first relocalized frame on: the frames before it have no map-frame
pose and are left out of the file (KITTI: the file's first line is frame
``map.first_localized_frame``; TUM: timestamps say which), counted in the summary and ``--json``.
A ``--map`` run that never relocalizes writes an empty pose file and its ``--json``, then exits
with a one-line error (code 1).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path


def add_map_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--save-map", metavar="MAP",
                   help="after the run, write its map to the folder MAP (docs/maps.md; an existing "
                        "map there is replaced atomically)")
    p.add_argument("--map", metavar="MAP",
                   help="localize in the saved map MAP: poses are written in the map frame from the "
                        "first relocalized frame on; earlier frames are left out and counted")


class MapRun:
    """What ``--map`` / ``--save-map`` add to one ``metricslam run`` (module docstring)."""

    def __init__(self, args: argparse.Namespace, config, camera) -> None:
        from metricslam.depth.model import DEFAULT_MODEL_PATH
        from metricslam.errors import ConfigError, MapError
        from metricslam.slam.map.format import depth_model_id, load_map

        if args.map and args.save_map:
            raise ConfigError("--map with --save-map (extending a loaded map) is not implemented yet: "
                              "localize with --map, or build a new map with --save-map")
        if (args.map or args.save_map) and config.vo_only:
            raise ConfigError("--map / --save-map need the global graph: drop --vo-only")
        self.args, self.config, self.camera = args, config, camera
        self.model_id = depth_model_id(config.depth.model_path or DEFAULT_MODEL_PATH) if config.use_scale else None
        self.saved = None
        self.relocalizer = None
        if args.map:
            self.saved = load_map(args.map)
            self.saved.check_fits(camera, self.model_id, args.map)
        if args.save_map:
            out = Path(args.save_map)
            if out.exists() and not out.is_dir():
                raise MapError(f"--save-map {out} is a file: name a folder for the map")
        self._stats: dict = {}

    def attach(self, pipeline) -> None:
        if self.args.save_map:
            pipeline.backend.keep_loop_database = True
        if self.saved is not None:
            from metricslam.slam.map.relocalizer import Relocalizer

            self.relocalizer = Relocalizer(self.saved, self.camera, self.config.graph_config().loop)
            self.relocalizer.attach(pipeline)

    def finish(self, pipeline, trajectory: list) -> list:
        """After ``pipeline.close()``: save the map (``--save-map``) and return the trajectory to
        write — in the map frame, from the first relocalized frame on, with ``--map``."""
        if self.args.save_map:
            self._save(pipeline)
        if self.relocalizer is None:
            return trajectory
        from metricslam.slam.map.relocalizer import to_map_frame

        reloc = self.relocalizer
        S, used, rejected = reloc.S_map_world(pipeline.backend.optimized_keyframe_poses())
        first = reloc.first_frame if S is not None else None
        kept = [] if first is None else [dataclasses.replace(e, T_world_cam=to_map_frame(S, e.T_world_cam))
                                         for e in trajectory if e.frame_index >= first]
        self._stats["map"] = {
            "path": str(self.args.map), "relocalized": first is not None,
            "first_localized_frame": first, "unlocalized_frames": len(trajectory) - len(kept),
            "relocalization_queries": reloc.n_queries,
            "relocalization_query_ms_mean": float(sum(reloc.query_ms) / max(len(reloc.query_ms), 1)), "relocalization_matches": len(reloc.matches),
            "matches_used": used, "matches_rejected": rejected,
            "map_keyframes": self.saved.n_keyframes,
            "S_map_world": None if S is None else S.tolist(),
            "matched_frames": [[m.kf_frame, m.map_kf_id, m.frame_now, m.n_inliers] for m in reloc.matches]}
        return kept

    def _save(self, pipeline) -> None:
        import time

        from metricslam.slam.map.builder import map_from_session
        from metricslam.slam.map.format import save_map

        detector = pipeline.backend.estimator.loop_detector
        try:
            t0 = time.perf_counter()
            saved = map_from_session(pipeline, self.model_id, metric=self.config.use_scale,
                                     source={"sequence": str(self.args.seq_dir), "mode": self.config.mode})
            save_map(saved, self.args.save_map)
            self._stats["map_saved"] = {"path": str(self.args.save_map), "keyframes": saved.n_keyframes,
                                        "save_s": time.perf_counter() - t0}
        finally:
            if detector is not None:
                detector.close()

    def raise_if_not_relocalized(self) -> None:
        """After the files are written: a ``--map`` run that never relocalized is an error."""
        from metricslam.errors import MapError

        m = self._stats.get("map")
        if m is not None and not m["relocalized"]:
            raise MapError(f"never relocalized into map {m['path']} ({m['relocalization_queries']} keyframe "
                           f"queries, {m['relocalization_matches']} verified): no map-frame poses were written; "
                           "is this the place (and camera) the map was built in?")

    def stats(self) -> dict:
        return dict(self._stats)

    def summary(self) -> str | None:
        m = self._stats.get("map")
        lines = []
        if "map_saved" in self._stats:
            s = self._stats["map_saved"]
            lines.append(f"map: saved {s['keyframes']} keyframes to {s['path']}")
        if m is not None:
            if m["relocalized"]:
                lines.append(f"map: relocalized at frame {m['first_localized_frame']} ({m['matches_used']} "
                             f"of {m['relocalization_matches']} matches used); {m['unlocalized_frames']} "
                             "frames before it are not localized and left out")
            else:
                lines.append(f"map: NOT relocalized into {m['path']} ({m['relocalization_queries']} keyframe "
                             "queries); no poses written")
        return "\n".join(lines) or None
