"""``SegmentRelocalizer``: after a tracking loss, the new segment relocalizes in the session's own
map (issue #34 item 3).

A camera that loses tracking restarts its VO as a new tracking segment, linked to the previous
one by a loose factor at the pose the last motion, kept up for the gap, predicts (``coast_max_s``,
``docs/vo.md``). Where the camera comes back somewhere the session has mapped (a revisit after a
long loss, a robot carried or put down on a mapped street, a lens uncovered) that guess can be
tens of metres and degrees off, and an ordinary loop rarely fixes it: the loop gate measures a
loop against the link's own uncertainty and refuses one that far off.

So after a loss longer than the link's coasting covers (``coast_max_s`` + :data:`LOSS_MARGIN_S`;
within it the link holds, and a contradiction is likelier a place that looks like another) the
new segment's keyframes are queried against a snapshot of the session's map, taken at its first
keyframe (:func:`~metricslam.slam.map.localization.session_map`: every keyframe the back end
holds; metric once learned scale is established), exactly as a later session relocalizes into a
saved map (:class:`~metricslam.slam.map.relocalizer.Relocalizer`: retrieval with the session's own
vocabulary, verification, matches of different keyframes that agree). Once they agree:

* if the relocalization puts the segment's first keyframe within
  :data:`~metricslam.slam.graph.estimator.LINK_CONTRADICTED_SIGMAS` of the link's own sigmas
  (rotation, translation, scale), the link holds and nothing changes: the ordinary loop detector
  goes on as before (adding such relocalizations as loops moved short losses both ways,
  ``docs/history/rule_segment_reloc2_session23.md``);
* otherwise the link is wrong (the camera was carried, or lost too long) — once
  :data:`MIN_AGREEING_CONTRADICTING` matches agree, from keyframes at least :data:`MIN_SPAN_M`
  apart (early ones of window keyframes included), one of them in the global graph: the link is
  dropped, the segment's keyframes are moved where the relocalization puts them and joined to the
  map keyframes by the matches in the graph as loop factors
  (:meth:`~metricslam.slam.graph.estimator.GlobalEstimator.relink_segment`), and no pose is
  interpolated across the gap (:func:`~metricslam.slam.pose_gaps.fill_pose_gaps`). The back
  end's next correction moves the live poses there; the service says so (``segment_relocalized``).

Only the keyframes of the segment's first :data:`QUERY_WINDOW_S` seconds are queried (later, the
segment's own drift would read as a contradicted link). One decision per segment; queries stop once
it is made. Without a map yet (a loss before anything was indexed) the segment keeps its link.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.errors import MapError
from metricslam.geometry import sim3, so3
from metricslam.slam.events import KeyframeMarginalized, KeyframeSettled, ScaleMeasured, Solved
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.graph.estimator import LINK_CONTRADICTED_SIGMAS
from metricslam.slam.map.localization import session_map
from metricslam.slam.map.relocalizer import GATE_LOG_SCALE, GATE_M, GATE_RAD, Relocalizer

log = logging.getLogger(__name__)

#: the agreeing matches must include two session keyframes this far apart in the map (metres): two
#: views of one spot agree with each other however wrong they are (two keyframes 2 frames apart
#: matched a place 36 m away and 151° round, ``docs/history/rule_segment_reloc_session23.md``)
MIN_SPAN_M = 3.0
#: agreeing matches a relocalization needs to override the segment's link: one more than the
#: relocalizer's (:data:`~metricslam.slam.map.relocalizer.MIN_AGREEING_MATCHES`), as it overrides a prior
MIN_AGREEING_CONTRADICTING = 3
#: only the keyframes of a segment's first seconds are queried: the relocalization is about where
#: the segment started; later, its own drift would read as a contradicted link (a loop closure the
#: ordinary detector makes without dropping the link: ``docs/history/rule_segment_reloc3_session23.md``)
QUERY_WINDOW_S = 5.0
#: a relocalization may override the link only after a loss longer than the coasting covers plus
#: this (s; keyframe spacing and the VO's re-initialization): within it the link's prediction holds
#: and a contradiction is likelier a wrong match (twice on rendered loops: places 36-44 m away seen
#: 151-175° round, 3 matches agreeing; ``docs/history/rule_segment_reloc4_session23.md``)
LOSS_MARGIN_S = 3.0
#: σ of a relocalization loop (rad, metres, log scale before/after learned scale): half the gates
#: its matches agreed within
LOOP_SIGMA_RAD, LOOP_SIGMA_M = GATE_RAD / 2, GATE_M / 2
LOOP_SIGMA_LOG_SCALE, LOOP_SIGMA_LOG_SCALE_PREMETRIC = GATE_LOG_SCALE / 2, 0.2


class SegmentRelocalizer:
    """Relocalizes each new tracking segment of a session in that session's map (module docstring).

    Args:
        camera: the session's camera.
        config: loop parameters (the relocalizer's retrieval and verification).
        coast_max_s: the VO's ``coast_max_s`` (how long the link's coasting lasts).
    """

    def __init__(self, camera: PinholeCamera, config: LoopConfig | None = None, coast_max_s: float = 2.0) -> None:
        self.camera = camera
        self.config = config or LoopConfig()
        self.min_loss_s = coast_max_s + LOSS_MARGIN_S
        self._last_kf_t_ns: int | None = None  # the current segment's newest keyframe seen
        self._loss_s = 0.0  # newest keyframe before the current segment -> its first keyframe
        self._pipeline = None
        self._segment = 0
        self._reloc: Relocalizer | None = None
        self._scale_kf: dict[int, float] = {}  # map keyframe id -> its scale in the snapshot
        self._metric_map = False  # the snapshot was metric (learned scale established)
        self._t0_ns = 0  # the segment's first keyframe's time

    def attach(self, pipeline) -> None:
        """Watch ``pipeline``'s keyframes (a :class:`~metricslam.slam.pipeline.SlamPipeline` with a
        back end and a loop database)."""
        self._pipeline = pipeline
        pipeline.backend.events.subscribe(self._on_event, KeyframeSettled, KeyframeMarginalized,
                                          ScaleMeasured, Solved)

    def _on_event(self, ev) -> None:
        if isinstance(ev, Solved):  # the graph thread, inside the estimator's solve
            if self._reloc is not None and self._reloc.first_frame is not None:
                self._place()
            return
        kf = getattr(ev, "keyframe", None)
        if kf is not None and int(kf.segment_id) > self._segment:
            self._loss_s = 0.0 if self._last_kf_t_ns is None else (int(kf.t_ns) - self._last_kf_t_ns) / 1e9
            self._start(int(kf.segment_id), int(kf.t_ns))
        if kf is not None and int(kf.segment_id) == self._segment:
            self._last_kf_t_ns = max(self._last_kf_t_ns or 0, int(kf.t_ns))
        if self._reloc is not None and (kf is None or (int(kf.segment_id) == self._segment and
                                                       kf.t_ns - self._t0_ns <= QUERY_WINDOW_S * 1e9)):
            self._reloc.on_event(ev)

    def _start(self, segment_id: int, t0_ns: int) -> None:
        """A new segment's first keyframe (at ``t0_ns``): snapshot the session's map for its queries
        (none after a short loss: whatever they found, the link would stay)."""
        self._segment, self._reloc, self._t0_ns = segment_id, None, t0_ns
        if self._loss_s < self.min_loss_s:
            log.info("tracking segment %d after a %.1f s loss: its link's coasting covers it", segment_id, self._loss_s)
            return
        backend = self._pipeline.backend
        t0 = time.perf_counter()
        try:
            saved = session_map(self._pipeline, None, metric=bool(backend.scale_established))
        except MapError as exc:
            log.info("tracking segment %d: nothing mapped to relocalize in yet (%s)", segment_id, exc)
            return
        kf = saved.arrays["keyframes"]
        self._scale_kf = {int(k): float(s) for k, s in zip(kf["kf_id"], kf["scale_kf"])}
        self._metric_map = bool(saved.metric)
        self._reloc = Relocalizer(saved, self.camera, self.config)
        self._reloc.bind(self._pipeline)
        log.info("tracking segment %d: relocalizing in the session's map (%d keyframes, snapshot %.0f ms on the "
                 "tracking thread)", segment_id, saved.n_keyframes, 1e3 * (time.perf_counter() - t0))

    def _place(self) -> None:
        """Relocalized: confirm the segment's link, or replace it (module docstring)."""
        backend, reloc = self._pipeline.backend, self._reloc
        poses = backend.optimized_keyframe_poses()
        metric = self._metric_map and bool(backend.scale_established)
        S_map_world = reloc.S_map_world(poses, metric_world=metric)[0]
        if S_map_world is None:
            return
        off = backend.estimator.link_offset_sigmas(self._segment, S_map_world)
        if off is None:
            return  # its link is not in the graph yet: nothing to confirm or replace
        if off <= LINK_CONTRADICTED_SIGMAS:
            self._reloc = None  # the link holds: the ordinary loop detector takes it from here
            log.info("tracking segment %d: relocalized where its link put it (%.1f of its sigmas)", self._segment, off)
            return
        agreeing = [m for m, _ in reloc.agreeing(S_map_world, poses, metric)]  # window keyframes' early ones too
        p_map = np.array([reloc.map_position_m(m) for m in agreeing]).reshape(-1, 3)
        span_m = float(np.max(np.linalg.norm(p_map[:, None] - p_map[None], axis=2))) if len(p_map) else 0.0
        in_graph = [m for m in agreeing if m.kf_frame in poses]
        if len(agreeing) < MIN_AGREEING_CONTRADICTING or span_m < MIN_SPAN_M or not in_graph:
            return  # wait: for more evidence, or for an agreeing keyframe to reach the graph
        self._reloc = None
        at = np.stack([poses[m.kf_frame][:3, 3] for m in in_graph])
        loops = []
        for m in in_graph:
            R, t, s = sim3.split(reloc.measured_S_mapkf_kf(m, poses[m.kf_frame], metric))
            s_old = self._scale_kf[m.map_kf_id]
            sig = np.array([LOOP_SIGMA_RAD] * 3 + [LOOP_SIGMA_M / s_old] * 3
                           + [LOOP_SIGMA_LOG_SCALE if metric else LOOP_SIGMA_LOG_SCALE_PREMETRIC])
            loops.append((m.map_kf_id, m.kf_frame, sim3.from_rts(R, t / s_old, s / s_old), sig, m.n_inliers))
        frame = self._pipeline.frame_now  # placed while processing it (inline), or just after
        backend.estimator.relink_segment(self._segment, S_map_world, frame, loops)
        R, t, s = sim3.split(S_map_world)
        log.warning("tracking segment %d relocalized in the session's map at frame %d: moved %.1f m, "
                    "%.1f deg, scale x%.3f from where its link put it (%d matches agree)", self._segment,
                    frame, float(np.linalg.norm(sim3.transform_points(S_map_world, at) - at, axis=1).max()),
                    float(np.degrees(np.linalg.norm(so3.log(R)))), s, len(agreeing))

