"""``GlobalEstimator``: the global back end's whole algorithm, single-threaded.

Integrate a marginalized keyframe (odometry or a new segment's link), take its learned scale
measurements, run loop queries (waiting for the keyframe's depth map in scale mode), add the
scale factors, solve (ISAM2), gate and add verified loops, and compute the metric warp for the
VO with all the epoch bookkeeping (:mod:`.odometry`). No threads, no locks: the scheduler
(:class:`~metricslam.slam.graph.backend.GlobalBackend`) calls it from one thread at a time —
inline (deterministic) or from its graph worker — and owns the queues (Basalt's split of an
estimator from the thread that feeds it). What it does is announced on ``events``
(:mod:`metricslam.slam.events`).

The one exception is :meth:`GlobalEstimator.issue_warp`, which the tracking thread calls while a
solve may be running: it touches only the :class:`~.odometry.VoFrameHistory` (its own lock) and
the solved pose handed over by :meth:`GlobalEstimator.solve`.
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass

import numpy as np

from metricslam.errors import GraphError, MetricSlamError
from metricslam.geometry import sim3, so3
from metricslam.slam.events import EventBus, LoopAccepted, SegmentRelocalized, Solved
from metricslam.slam.graph import ground_factor
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.odometry import (
    VoFrameHistory,
    odometry_information,
    orthonormalize,
    relative_sim3,
    resolve_epoch,
)
from metricslam.slam.graph.records import KeyframeRecord, LoopRecord
from metricslam.slam.graph.sim3_graph import GlobalPoseGraph
from metricslam.slam.timing import TimingSummary
from metricslam.slam.types import MarginalizedKeyframe

log = logging.getLogger("metricslam.slam.graph.backend")

#: a relocalization contradicts a new segment's link when it puts the segment this many of the
#: link's sigmas off it in rotation, translation or scale (:meth:`GlobalEstimator.link_offset_sigmas`)
LINK_CONTRADICTED_SIGMAS = 3.0


@dataclass(frozen=True)
class SolvedPose:
    """The newest keyframe's pose after a solve: ``T_vo_kf`` (4, 4) in the VO frame of ``epoch``
    and its solved ``S_world_kf`` (4, 4). The warp for the VO is computed from it."""

    T_vo_kf: np.ndarray
    epoch: int
    S_world_kf: np.ndarray


class GlobalEstimator:
    """The global graph and everything the back end keeps about keyframes and loops.

    Args:
        config: graph, loop and scale-factor parameters.
        use_scale: learned scale factors arrive (else the first keyframe's scale is anchored).
        loop_detector: a :class:`metricslam.slam.loop.LoopDetector`, or None (no loops).
        events: where :class:`~metricslam.slam.events.Solved` and ``LoopAccepted`` are emitted.
        ground_huber_k: Huber threshold of ground-plane scale factors, which then arrive
            (:meth:`add_ground_result`); None: none do. Either source frees the first scale.
    """

    def __init__(self, config: GraphConfig, use_scale: bool, loop_detector: object | None,
                 events: EventBus, ground_huber_k: float | None = None) -> None:
        self.config = config
        self.use_scale = use_scale
        self.loop_detector = loop_detector
        self.events = events
        self.ground_huber_k = ground_huber_k
        self.graph = GlobalPoseGraph(config, anchor_scale=not use_scale and ground_huber_k is None)
        self.history = VoFrameHistory()
        self.loops: list[LoopRecord] = []
        self.loops_verified = 0
        self.scale_factors_solved = 0
        self.counters: collections.Counter = collections.Counter()
        self.solve_ms = TimingSummary()  # count / total / max, constant memory
        self.loop_ms = TimingSummary()
        self.solved: SolvedPose | None = None  # newest solve's pose, taken by the scheduler
        self._records: dict[int, KeyframeRecord] = {}
        self._last_of_segment: dict[int, int] = {}
        self._links: dict[int, tuple] = {}  # segment -> (kf before, its first kf, Ŝ link, sigmas (7,))
        self._newest_kf: int | None = None
        self._pending_scales: dict[int, np.ndarray] = {}
        self._pending_ground: dict[int, tuple[float, float]] = {}  # kf_id -> (scale, sigma_log)
        self.ground_factors_solved = 0
        self.n_ground_factors = 0  # road-plane scale factors added to the graph
        self._pending_loops: list = []  # verified LoopCandidates waiting for the next solve
        self._pending_relinks: list = []  # (segment_id, S_map_world, frame, loops) for the next solve
        #: segment id -> frame index when it was placed off its link by a relocalization in the
        #: session's own map (:meth:`relink_segment`)
        self.relocalized_segments: dict[int, int] = {}
        # loop queries wait for their keyframe's depth map (scale mode): keyframes in order,
        # finished depth requests (kf_id -> map or None on failure) and dropped request ids
        self._loop_waiting: collections.deque = collections.deque()
        self._depth_done: dict[int, np.ndarray | None] = {}
        self._depth_dropped_ids: set[int] = set()

    # -- inputs -------------------------------------------------------------------------------
    def integrate(self, kf: MarginalizedKeyframe, epoch: int) -> None:
        """Insert one keyframe (odometry, first prior or a new segment's link) in the VO frame of
        ``epoch``, and queue its loop query."""
        prev_id = self._last_of_segment.get(int(kf.segment_id))
        T_vo_kf = np.asarray(kf.T_vo_kf, dtype=float)
        S_prev_k = None
        if prev_id is not None:
            prev = self._records[prev_id]
            epoch, S_prev_k, consistent = resolve_epoch(self.history, prev.T_vo_kf, prev.epoch,
                                                        T_vo_kf, kf.T_prevkf_kf, epoch)
            if kf.T_prevkf_kf is not None and not consistent:
                self.counters["epoch_mismatches"] += 1
                log.warning("keyframe %d: T_vo_kf matches no recent VO frame; using the newest",
                            kf.kf_id)
        rec = KeyframeRecord(int(kf.kf_id), int(kf.frame_index), int(kf.segment_id), epoch, T_vo_kf)
        if prev_id is not None:
            guess = self.graph.estimate(prev_id) @ S_prev_k
            info = odometry_information(S_prev_k, kf.information, self.config)
            rec.step_length = max(float(np.linalg.norm(S_prev_k[:3, 3])), 1e-6)
            self.graph.add_keyframe(rec.kf_id, guess, prev_id, S_prev_k, info)
        elif self._newest_kf is None:
            self.graph.add_keyframe(rec.kf_id, T_vo_kf)
        else:  # new tracking segment: the VO restarts from its last known pose, so link it to
            # the newest keyframe by a loose relative factor (a loop can tighten it later)
            last = self._records[self._newest_kf]
            S_last_k = relative_sim3(last.T_vo_kf, T_vo_kf, self.history.between(last.epoch, epoch))
            guess = self.graph.estimate(last.kf_id) @ S_last_k
            t_len = float(np.linalg.norm(S_last_k[:3, 3]))
            sig = np.array([0.2] * 3 + [max(t_len, 5.0 * last.step_length)] * 3 + [0.5])
            self.graph.add_keyframe(rec.kf_id, guess, last.kf_id, S_last_k, np.diag(1.0 / sig**2),
                                    link_kind=f"segment_link {rec.segment_id}")
            self._links[rec.segment_id] = (last.kf_id, rec.kf_id, S_last_k, sig)
            self.counters["segment_links"] += 1
        self._records[rec.kf_id] = rec
        self._last_of_segment[rec.segment_id] = rec.kf_id
        self._newest_kf = rec.kf_id
        if self.loop_detector is not None:
            self._loop_waiting.append(kf)

    def add_depth_result(self, kf_id: int, scales: np.ndarray | None, inv_map: np.ndarray | None) -> None:
        """A keyframe's depth request finished: its scale measurements (None on failure) and the
        metric inverse-depth map (kept for its loop query)."""
        if scales is not None:
            self._pending_scales[int(kf_id)] = scales
        if self.loop_detector is not None:
            self._depth_done[int(kf_id)] = inv_map

    @property
    def newest_kf_id(self) -> int | None:
        """The newest keyframe in the graph (None: none yet)."""
        return self._newest_kf

    def add_ground_result(self, kf_id: int, scale: float, sigma_log: float) -> None:
        """A keyframe's accepted road-plane scale ``h_mount_m / h_vo`` (m per keyframe unit)."""
        self._pending_ground[int(kf_id)] = (float(scale), float(sigma_log))

    def depth_dropped(self, kf_id: int) -> None:
        """A keyframe's depth request was dropped (queue full): its loop query goes without."""
        self._depth_dropped_ids.add(int(kf_id))

    # -- work ---------------------------------------------------------------------------------
    def update(self) -> None:
        """After new inputs: loop queries that can run, scale factors, one solve."""
        self._run_loop_queries(final=False)
        self._flush_scales()
        self.solve()

    def finish(self) -> None:
        """At close: the remaining loop queries and scale factors, then a longer final solve."""
        self._run_loop_queries(final=True)
        self._flush_scales()
        if self._pending_loops:
            self.solve()
        try:
            self.graph.solve(extra_iterations=max(self.config.extra_iterations, 5))
            self._hand_over_newest()
        except GraphError as exc:
            log.warning("final global solve failed: %s", exc)

    def solve(self) -> None:
        """One incremental solve; verified loops are gated against it, added, and solved again."""
        t0 = time.perf_counter()
        n_before = self.graph.n_scale_factors
        n_ground_before = self.n_ground_factors
        try:
            self._relink_segments()
            res = self.graph.solve()
            if self._pending_loops:  # gate against the solved graph, then solve with the loops
                for cand in self._pending_loops:
                    self._add_loop(cand)
                self._pending_loops = []
                res2 = self.graph.solve()
                res = {**res2, "loops_removed": res["loops_removed"] + res2["loops_removed"],
                       "batch": res["batch"] or res2["batch"]}
        except GraphError as exc:
            log.warning("global solve failed: %s", exc)
            return
        if res["loops_removed"]:
            pairs = self.graph.loop_pairs()
            self.loops = [lp for lp in self.loops if (lp.kf_old, lp.kf_new) in pairs]
        solve_ms = 1e3 * (time.perf_counter() - t0)
        self.solve_ms.append(solve_ms)
        self.scale_factors_solved = n_before
        self.ground_factors_solved = n_ground_before
        self._hand_over_newest()
        newest = -1 if self._newest_kf is None else self._records[self._newest_kf].frame_index
        n_relinks = len(self._pending_relinks)
        self.events.emit(Solved(self.graph.n_keyframes, self.graph.n_scale_factors, newest,
                                int(res["loops_removed"]), solve_ms, bool(res["batch"])))
        if len(self._pending_relinks) > n_relinks:  # a relocalization placed a segment: now, not a
            self.solve()  # keyframe later (the last keyframes of a stream would never see it)

    def relink_segment(self, segment_id: int, S_map_world: np.ndarray, frame_now: int,
                       loops: list[tuple[int, int, np.ndarray, np.ndarray, int]]) -> None:
        """Place tracking segment ``segment_id`` where its relocalization into the session's own
        map puts it (:mod:`metricslam.slam.map.segments`), at the next solve: its loose link to
        the previous segment is dropped (the relocalization contradicts it: the camera did not
        get there the way the link says), its keyframes start the solve from ``S_map_world``
        (4, 4; the graph's world before -> after) times their estimate, and ``loops`` ``(kf_old,
        frame_new, S_old_new (4, 4), sigmas (7,), inliers)`` join it to earlier keyframes,
        ungated (the relocalization's matches agreed with each other instead)."""
        self._pending_relinks.append((int(segment_id), np.asarray(S_map_world, float), int(frame_now), loops))

    def link_offset_sigmas(self, segment_id: int, S_map_world: np.ndarray) -> float | None:
        """How far off its link (the largest of rotation, translation, log scale, in the link's own
        sigmas) ``S_map_world`` (4, 4) moves segment ``segment_id``'s first keyframe; None while
        the segment has no link in the graph (its first keyframe still in the VO window)."""
        if segment_id not in self._links:
            return None
        last_id, first_id, S_link, sig_link = self._links[segment_id]
        S_moved = sim3.inverse(self.graph.estimate(last_id)) @ S_map_world @ self.graph.estimate(first_id)
        (R1, t1, s1), (R2, t2, s2) = sim3.split(S_link), sim3.split(S_moved)
        return float(np.max(np.array([np.linalg.norm(so3.log(R1.T @ R2)), np.linalg.norm(t2 - t1),
                                      abs(np.log(s2 / s1))]) / sig_link[[0, 3, 6]]))

    def _relink_segments(self) -> None:
        by_frame = {r.frame_index: k for k, r in self._records.items()}
        pending, self._pending_relinks = self._pending_relinks, []
        for seg, S_map_world, frame_now, loops in pending:
            joined = [(old, by_frame[f], S, sig, n) for old, f, S, sig, n in loops
                      if f in by_frame and self.graph.has(old)]
            if seg in self.relocalized_segments or seg not in self._links:
                continue  # placed already; the graph's first segment (nothing to relink)
            if not joined:  # its keyframes are not in the graph yet
                self._pending_relinks.append((seg, S_map_world, frame_now, loops))
                continue
            off = self.link_offset_sigmas(seg, S_map_world)
            moved = [k for k, r in self._records.items() if r.segment_id >= seg and self.graph.has(k)]
            self.graph.replace_factor(f"segment_link {seg}", {k: S_map_world @ self.graph.estimate(k) for k in moved})
            for old, new, S, sig, n in joined:
                self.graph.add_loop(old, new, S, sig, gate=False)
                rec = LoopRecord(old, new, self._records[old].frame_index, self._records[new].frame_index, n)
                self.loops.append(rec)
                self.events.emit(LoopAccepted(rec.kf_old, rec.kf_new, rec.frame_old, rec.frame_new, n))
            self.relocalized_segments[seg] = frame_now
            self.events.emit(SegmentRelocalized(seg, frame_now, len(joined)))
            self.counters["segments_relocalized"] += 1
            log.info("tracking segment %d relocalized in the session's map at frame %d (%d loops in place "
                     "of its link, %.1f of the link's sigmas off it)", seg, frame_now, len(joined), off)

    def issue_warp(self, solved: SolvedPose) -> np.ndarray:
        """``S_new_vo`` (4, 4): maps the current VO frame onto the metric world frame so that the
        solved keyframe lands on its graph pose; recorded as the start of a new VO epoch.

        Callable from the tracking thread during a solve (see the module docstring).
        """
        S_ve_n = self.history.between(solved.epoch, self.history.epoch) @ solved.T_vo_kf
        S_new_vo = orthonormalize(solved.S_world_kf @ sim3.inverse(orthonormalize(S_ve_n)))
        self.history.issue(S_new_vo)
        return S_new_vo

    def optimized_keyframe_poses(self) -> dict[int, np.ndarray]:
        """Input frame index -> solved ``S_world_kf`` (4, 4) of every keyframe in the graph."""
        return {self._records[k].frame_index: S for k, S in self.graph.estimates().items()}

    # -- internals ----------------------------------------------------------------------------
    def _hand_over_newest(self) -> None:
        if self._newest_kf is None:
            return
        rec = self._records[self._newest_kf]
        self.solved = SolvedPose(rec.T_vo_kf, rec.epoch, self.graph.estimate(rec.kf_id))

    def _flush_scales(self) -> None:
        for kf_id in [k for k in self._pending_scales if self.graph.has(k)]:
            self.graph.add_scale_measurements(kf_id, self._pending_scales.pop(kf_id))
        for kf_id in [k for k in self._pending_ground if self.graph.has(k)]:
            scale, sigma_log = self._pending_ground.pop(kf_id)
            ground_factor.add_ground_scale(self.graph, kf_id, scale, sigma_log, self.ground_huber_k)
            self.n_ground_factors += 1

    def _run_loop_queries(self, final: bool) -> None:
        """Query loops for waiting keyframes, in order, once each has its depth map (scale mode;
        a failed or dropped depth request, or ``final``, lets it go without)."""
        while self._loop_waiting:
            kf = self._loop_waiting[0]
            k = int(kf.kf_id)
            if not self.use_scale or k in self._depth_done:
                inv_map = self._depth_done.pop(k, None)
            elif final or k in self._depth_dropped_ids or any(d > k for d in self._depth_done):
                self._depth_dropped_ids.discard(k)
                inv_map = None
            else:
                return
            self._loop_waiting.popleft()
            t0 = time.perf_counter()
            try:
                candidates = self.loop_detector.add_and_query(
                    k, kf.image, kf.camera, kf.landmarks_uv_px, kf.landmarks_inv_depth,
                    inv_depth_map=inv_map, T_prevkf_kf=kf.T_prevkf_kf)
            except MetricSlamError as exc:
                log.warning("loop detection failed on keyframe %d: %s", k, exc)
                candidates = []
            self.loop_ms.append(1e3 * (time.perf_counter() - t0))
            self.loops_verified += len(candidates)
            # added after the next solve: the gate needs both keyframes inside ISAM2 (their
            # joint marginal); the newest keyframe is only pending until then
            self._pending_loops.extend(candidates)

    def _add_loop(self, cand) -> None:
        sig = getattr(cand, "sigmas", None)
        if sig is not None:  # measured from geometry with its own covariance (floors only)
            sig = np.maximum(np.asarray(sig, dtype=float),
                             [1e-4] * 3 + [self.config.odom_sigma_trans_min] * 3 + [0.005])
        else:
            step = self._records[cand.kf_old].step_length
            t_len = float(np.linalg.norm(cand.S_old_new[:3, 3]))
            sig_t = max(self.config.loop_sigma_trans_rel * max(t_len, step), self.config.odom_sigma_trans_min)
            sig = np.array([self.config.loop_sigma_rot_rad] * 3 + [sig_t] * 3
                           + [self.config.loop_sigma_log_scale])
        decision = self.graph.add_loop(cand.kf_old, cand.kf_new, cand.S_old_new, sig)
        log.info("loop %d -> %d: %s (d2=%.1f, %d inliers)", cand.kf_old, cand.kf_new, decision.reason,
                 decision.mahalanobis_sq, cand.n_inliers)
        if decision.accepted:
            rec = LoopRecord(cand.kf_old, cand.kf_new, self._records[cand.kf_old].frame_index,
                             self._records[cand.kf_new].frame_index, cand.n_inliers)
            self.loops.append(rec)
            self.events.emit(LoopAccepted(rec.kf_old, rec.kf_new, rec.frame_old, rec.frame_new,
                                          rec.n_inliers))
