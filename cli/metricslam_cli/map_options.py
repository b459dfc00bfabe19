"""``metricslam run --save-map MAP`` / ``--map MAP``: maps that outlive a session (docs/maps.md).

``--save-map`` writes the finished session's map (keyframes, landmarks, loop database, camera,
depth model id) atomically. ``--map`` loads one before the first frame (a bad, old, foreign map is
a one-line error), relocalizes the session into it through the map's loop database and the
geometric Sim(3) verification (:mod:`metricslam.slam.map.relocalizer`), and writes the trajectory
in the map frame from the first relocalized frame on: the frames before it have no map-frame
pose and are left out of the file (KITTI: the file's first line is frame
``map.first_localized_frame``; TUM: timestamps say which), counted in the summary and ``--json``.
A ``--map`` run that never relocalizes writes an empty pose file and its ``--json``, then exits
with a one-line error (code 1). ``--map MAP --save-map OUT`` extends the loaded map: the session
is joined to it in a Sim(3) graph (map keyframes fixed, relocalization matches as cross-session
factors) and appended (:mod:`metricslam.slam.map.merge`); ``OUT`` may be ``MAP`` itself.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_map_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--save-map", metavar="MAP",
                   help="after the run, write its map to the folder MAP (docs/maps.md; an existing "
                        "map there is replaced atomically); with --map, the loaded map extended by this run")
    p.add_argument("--map", metavar="MAP",
                   help="localize in the saved map MAP: poses are written in the map frame from the "
                        "first relocalized frame on; earlier frames are left out and counted")


class MapRun:
    """What ``--map`` / ``--save-map`` add to one ``metricslam run`` (module docstring); the
    logic is :mod:`metricslam.slam.map.localization`, shared with the SLAM service."""

    def __init__(self, args: argparse.Namespace, config, camera) -> None:
        from metricslam.depth.model import DEFAULT_MODEL_PATH
        from metricslam.errors import ConfigError, MapError
        from metricslam.slam.map.format import depth_model_id
        from metricslam.slam.map.localization import open_map

        if (args.map or args.save_map) and config.vo_only:
            raise ConfigError("--map / --save-map need the global graph: drop --vo-only")
        self.args, self.config, self.camera = args, config, camera
        self.model_id = depth_model_id(config.depth.model_path or DEFAULT_MODEL_PATH) if config.use_scale else None
        self.saved = open_map(args.map, camera, self.model_id) if args.map else None
        self.localization = None
        if args.save_map:
            out = Path(args.save_map)
            if out.exists() and not out.is_dir():
                raise MapError(f"--save-map {out} is a file: name a folder for the map")
        self._stats: dict = {}

    def attach(self, pipeline) -> None:
        if self.args.save_map:
            pipeline.backend.keep_loop_database = True
        if self.saved is not None:
            from metricslam.slam.map.localization import MapLocalization

            self.localization = MapLocalization(self.saved, self.camera, self.config.graph_config().loop,
                                                self.args.map)
            self.localization.attach(pipeline)

    def finish(self, pipeline, trajectory: list) -> list:
        """After ``pipeline.close()``: return the trajectory to write — in the map frame, from the
        first relocalized frame on, with ``--map`` — and save the map (``--save-map``: the
        session's own, or with ``--map`` the loaded map extended by it, ``merge.py``)."""
        kept = trajectory
        if self.localization is not None:
            self.localization.refresh(force=True)
            kept = self.localization.map_trajectory(trajectory)
            self._stats["map"] = self.localization.stats(len(trajectory), len(kept))
        if self.args.save_map:
            self._save(pipeline)
        return kept

    def _save(self, pipeline) -> None:
        from metricslam.slam.map.localization import save_session_map
        from metricslam.slam.map.merge import save_extended_map

        detector = pipeline.backend.estimator.loop_detector
        source = {"sequence": str(self.args.seq_dir), "mode": self.config.mode}
        try:
            if self.localization is None:
                self._stats["map_saved"] = save_session_map(
                    pipeline, self.args.save_map, self.model_id, metric=self.config.use_scale, source=source)
            elif self.localization.S_map_world is None:  # the run fails anyway: "never relocalized"
                self._stats["map_saved"] = {"path": str(self.args.save_map), "skipped": "never relocalized"}
            else:
                self._stats["map_saved"] = save_extended_map(
                    self.localization, pipeline, self.args.save_map, self.model_id,
                    metric=self.config.use_scale, source=source)
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
        s = self._stats.get("map_saved")
        if s is not None and "skipped" in s:
            lines.append(f"map: NOT saved to {s['path']} ({s['skipped']})")
        elif s is not None and "extended" in s:
            e = s["extended"]
            lines.append(f"map: saved {s['keyframes']} keyframes to {s['path']}: {e['session_keyframes']} of this "
                         f"session appended, joined by {e['cross_session_factors']} cross-session factors to "
                         f"{e['map_keyframes_fixed']} fixed map keyframes")
        elif s is not None:
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
