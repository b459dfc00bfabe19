"""``GlobalBackend``: the scheduler around :class:`~.estimator.GlobalEstimator` — threads and
bounded queues (:class:`metricslam.slam.types.Backend` for the pipeline).

Threads and queues (``GraphConfig.inline=False``):

* the caller's (tracking) thread runs :meth:`GlobalBackend.on_keyframe_marginalized`, which only
  queues the keyframe (never dropped) and a depth request on a bounded queue
  (``depth_queue_size``; when full the OLDEST request is dropped, so that keyframe gets no scale
  factors) — it never waits on depth, loop detection or the solver;
* a depth worker asks the :class:`~metricslam.slam.depth_source.DepthSource` for metric inverse
  depth and turns it into per-landmark scale measurements ``ξ_j / z_j`` (eq. 12), announced as a
  :class:`~metricslam.slam.events.ScaleMeasured` event;
* a graph worker hands keyframes and depth results to the estimator (one thread at a time, under
  ``_lock``), which integrates, queries loops, adds scale factors and solves; the newest solved
  pose is then offered to the tracking thread as the warp ``S_new_vo`` (:meth:`take_correction`).

With ``inline=True`` everything runs inside ``on_keyframe_marginalized`` (deterministic).
``depth_source=None`` means no learned scale at all (the ``--no-scale`` ablation: the first
keyframe's scale is anchored instead). Everything the back end does is on ``events``.
"""

from __future__ import annotations

import collections
import logging
import threading
import time

import numpy as np

from metricslam.errors import MetricSlamError
from metricslam.geometry import sim3
from metricslam.slam.depth_source import DepthSource
from metricslam.slam.events import EventBus, ScaleMeasured, WarpApplied
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.estimator import GlobalEstimator, SolvedPose
from metricslam.slam.graph.records import LoopRecord
from metricslam.slam.graph.scale_factor import scale_measurements
from metricslam.slam.timing import TimingSummary
from metricslam.slam.types import MarginalizedKeyframe

log = logging.getLogger(__name__)


class GlobalBackend:
    """Implements :class:`metricslam.slam.types.Backend`.

    Args:
        config: graph, loop and threading parameters.
        depth_source: metric inverse depth provider, or None for no learned scale.
        loop_detector: a :class:`metricslam.slam.loop.LoopDetector` (or None: no loops).
        ground_meter: a :class:`metricslam.slam.ground.meter.GroundScaleMeter` for ground-plane
            scale factors (measured on the graph's thread, in keyframe order), or None.
    """

    def __init__(self, config: GraphConfig | None = None, depth_source: DepthSource | None = None,
                 loop_detector: object | None = None, ground_meter: object | None = None) -> None:
        self.config = config or GraphConfig()
        self.depth_source = depth_source
        self.ground_meter = ground_meter
        #: what the back end did (:mod:`metricslam.slam.events`): subscribe here to observe it
        self.events = EventBus()
        ground_k = ground_meter.config.ground_huber_k if ground_meter is not None else None
        #: learned and ground scale per keyframe, their spread and disagreement warning (an
        #: observer of the events: with either source, so learned-only runs report the spread)
        self.scale_health = None
        if ground_meter is not None or depth_source is not None:
            from metricslam.slam.ground.health import ScaleHealth

            self.scale_health = ScaleHealth(ground_meter.config.health if ground_meter is not None else None,
                                            self.config.scale_sigma_log, self.config.scale_huber_k)
            self.scale_health.attach(self.events)
        self._scale_sigma_log: float | None = None  # the newest solved keyframe's, last read
        self._solved_kf_id: int | None = None  # the keyframe of the newest solve handed over
        #: leave the loop detector's features open at :meth:`close` (a map is saved from them
        #: afterwards; the saver closes the detector)
        self.keep_loop_database = False
        self.estimator = GlobalEstimator(self.config, depth_source is not None, loop_detector, self.events,
                                         ground_huber_k=ground_k)
        self._lock = threading.RLock()  # one estimator call at a time
        self._cv = threading.Condition()  # guards the queues below and _busy/_stop
        self._incoming: collections.deque = collections.deque()  # (kf, epoch)
        self._depth_requests: collections.deque = collections.deque()  # MarginalizedKeyframe
        self._scale_results: collections.deque = collections.deque()  # (kf_id, scales, inv_map)
        self._dropped: list[int] = []  # kf ids whose depth request was dropped, for the estimator
        self._corr_lock = threading.Lock()  # guards _pending_correction, _poses_snapshot (never held long)
        self._pending_correction: SolvedPose | None = None
        self._poses_snapshot: dict[int, np.ndarray] = {}  # last optimized_keyframe_poses() answer
        self._busy = 0
        self._stop = False
        self._counters: collections.Counter = collections.Counter()
        self._depth_ms = TimingSummary()
        self._threads: list[threading.Thread] = []
        if not self.config.inline:
            self._threads.append(threading.Thread(target=self._graph_worker, name="graph", daemon=True))
            if depth_source is not None:
                self._threads.append(threading.Thread(target=self._depth_worker, name="depth", daemon=True))
            for t in self._threads:
                t.start()

    @property
    def graph(self):
        """The estimator's :class:`~.sim3_graph.GlobalPoseGraph` (read it under no lock only for counts)."""
        return self.estimator.graph

    # -- Backend protocol ---------------------------------------------------------------------
    def on_keyframe_marginalized(self, kf: MarginalizedKeyframe) -> None:
        """Record ``kf`` (in the VO frame of the current epoch). Never blocks on depth/solve."""
        epoch = self.estimator.history.epoch
        if self.config.inline:
            with self._lock:
                self.estimator.integrate(kf, epoch)
                self._measure_ground(kf)
                if self.depth_source is not None:
                    self.estimator.add_depth_result(kf.kf_id, *self._measure_scale(kf))
                self.estimator.update()
                self._take_solved()
            return
        with self._cv:
            self._incoming.append((kf, epoch))
            if self.depth_source is not None:
                if len(self._depth_requests) >= self.config.depth_queue_size:
                    dropped = self._depth_requests.popleft()
                    self._dropped.append(int(dropped.kf_id))
                    self._counters["depth_dropped"] += 1
                self._depth_requests.append(kf)
            self._cv.notify_all()

    def take_correction(self) -> np.ndarray | None:
        """``S_new_vo`` (4, 4) mapping the current VO frame onto the optimized metric world frame
        (the newest solved keyframe lands on its graph pose), once per solve; else None.

        Never waits for a running solve (its own small lock): the tracking thread calls it every
        frame. The caller must apply it to the VO before it marginalizes the next keyframe:
        keyframes received after this call are taken to be in the corrected frame (see
        :func:`metricslam.slam.graph.odometry.resolve_epoch` for the tolerated exception).
        """
        with self._corr_lock:
            solved, self._pending_correction = self._pending_correction, None
            if solved is None:
                return None
            S_new_vo = self.estimator.issue_warp(solved)
            epoch = self.estimator.history.epoch
            self._counters["corrections"] += 1
        self.events.emit(WarpApplied(S_new_vo, sim3.scale(S_new_vo), epoch))
        return S_new_vo

    def exclusive(self) -> threading.RLock:
        """Hold the estimator (``with backend.exclusive(): ...``): no solve or loop detection
        runs meanwhile. Saving a map mid-session reads its keyframes and loop database so."""
        return self._lock

    def optimized_keyframe_poses(self) -> dict[int, np.ndarray]:
        """The keyframe poses of the newest solve that has finished (frame index -> (4, 4)).

        Never waits for a running one: while the graph worker holds the estimator (loop
        detection, a batch re-solve after a loop: up to hundreds of ms), the previous answer is
        returned at once. A live caller on the tracking thread (the SLAM service's ``…/path``
        after each keyframe) used to wait here and fall seconds behind at every loop. Once the
        back end is idle (after :meth:`wait_idle` or :meth:`close`, and always inline) the answer
        is the current one.
        """
        if not self._lock.acquire(blocking=False):
            with self._corr_lock:
                return dict(self._poses_snapshot)
        try:
            poses = self.estimator.optimized_keyframe_poses()
        finally:
            self._lock.release()
        with self._corr_lock:
            self._poses_snapshot = poses
        return dict(poses)

    @property
    def relinked_segments(self) -> frozenset[int]:
        """Tracking segments a relocalization in the session's own map moved off their link."""
        return frozenset(self.estimator.relocalized_segments)

    @property
    def scale_established(self) -> bool:
        if self.depth_source is None and self.ground_meter is None:
            return False
        solved = self.estimator.scale_factors_solved if self.depth_source is not None else 0
        return solved + self.estimator.ground_factors_solved >= self.config.min_scale_factors_established

    @property
    def scale_factors_solved(self) -> int:
        """Learned scale measurements in the latest solve (0 without a depth source)."""
        return int(self.estimator.scale_factors_solved) if self.depth_source is not None else 0

    @property
    def loops(self) -> list[LoopRecord]:
        with self._lock:
            return list(self.estimator.loops)

    def wait_idle(self, timeout_s: float = 30.0) -> bool:
        """Block until all queued keyframes and depth requests are processed (tests, close)."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while self._incoming or self._depth_requests or self._scale_results or self._busy:
                left = deadline - time.monotonic()
                if left <= 0 or not any(t.is_alive() for t in self._threads):
                    return False
                self._cv.wait(min(left, 0.05))
        return True

    def close(self, timeout_s: float = 60.0) -> None:
        """Finish pending depth requests and solves (up to ``timeout_s``), then stop workers."""
        if not self.config.inline:
            if not self.wait_idle(timeout_s):
                log.warning("global back end: pending work left at close after %.0f s", timeout_s)
            with self._cv:
                self._stop = True
                self._cv.notify_all()
            for t in self._threads:
                t.join(timeout=5.0)
        with self._lock:
            self.estimator.finish()
            self._take_solved()
            if self.estimator.loop_detector is not None and not self.keep_loop_database:
                self.estimator.loop_detector.close()  # its temporary feature file

    def stats(self) -> dict:
        """Counters and timings (ms) of the back end."""
        # no lock: plain counters and list copies (a status publisher must not wait on a solve)
        est = self.estimator
        loops = list(est.loops)
        counters = {**est.counters, **self._counters}
        return {
            "keyframes": est.graph.n_keyframes,
            "scale_factors": est.graph.n_scale_factors,
            "loops_accepted": len(loops),
            "loops_rejected": est.graph.n_loops_rejected,
            "loops": [(lp.frame_old, lp.frame_new) for lp in loops],
            "loop_keyframes": [(lp.kf_old, lp.kf_new) for lp in loops],
            "loop_inliers": [lp.n_inliers for lp in loops],
            "loops_verified": est.loops_verified,
            **{k: counters.get(k, 0) for k in ("depth_requests", "depth_failures", "depth_dropped",
                                               "corrections", "segment_links", "segments_relocalized",
                                               "epoch_mismatches")},
            "relocalized_segments": {str(k): v for k, v in est.relocalized_segments.items()},
            "graph_rebuilds": est.graph.n_rebuilds,
            "graph_stabilized": est.graph.n_stabilized,
            "depth_ms_mean": self._depth_ms.mean_ms,
            "solve_ms_mean": est.solve_ms.mean_ms,
            "solve_ms_max": est.solve_ms.max_ms,
            "loop_ms_mean": est.loop_ms.mean_ms,
            "scale_established": self.scale_established,
            **(est.loop_detector.store_counters if est.loop_detector is not None else {}),
            **(self._ground_stats() if self.ground_meter is not None else {}),
            **({"scale_health": self.scale_health.snapshot(), "scale_sigma_log": self.scale_sigma_log()}
               if self.scale_health is not None else {}),
        }

    def _ground_stats(self) -> dict:
        meter = self.ground_meter
        timing = {f"ground_{name}_mean": getattr(meter, attr).mean_ms  # (a test's fake meter has none)
                  for name, attr in (("ms", "wall_ms"), ("cpu_ms", "cpu_ms")) if hasattr(meter, attr)}
        return {"ground_factors": self.estimator.n_ground_factors, **meter.counts,
                "ground_rejected_reasons": dict(meter.reasons), **timing}

    def scale_sigma_log(self) -> float | None:
        """σ of the newest solved keyframe's log-scale (ISAM2's marginal); while a solve runs, or
        while the newest keyframe waits for its first solve, the last value read (a status
        publisher must not wait on a solve)."""
        if not self._lock.acquire(blocking=False):
            return self._scale_sigma_log
        try:
            graph = self.estimator.graph
            for kf_id in (self.estimator.newest_kf_id, self._solved_kf_id):
                sigma = graph.scale_sigma_log(kf_id) if kf_id is not None else None
                if sigma is not None:
                    self._scale_sigma_log = sigma
                    break
        finally:
            self._lock.release()
        return self._scale_sigma_log

    # -- work ---------------------------------------------------------------------------------
    def _take_solved(self) -> None:
        """After an estimator call (caller holds ``_lock``): offer its newest solved pose."""
        solved, self.estimator.solved = self.estimator.solved, None
        if solved is not None:
            self._solved_kf_id = self.estimator.newest_kf_id
            with self._corr_lock:
                self._pending_correction = solved

    def _measure_ground(self, kf: MarginalizedKeyframe) -> None:
        """Road-plane scale of ``kf`` (caller holds ``_lock``; after ``integrate``), announced as
        :class:`~metricslam.slam.events.GroundScaleMeasured`; accepted ones go to the estimator."""
        if self.ground_meter is None:
            return
        try:
            ev = self.ground_meter.measure(kf, self._graph_scale)
        except MetricSlamError as exc:
            log.warning("no ground scale for keyframe %d: %s", kf.kf_id, exc)
            return
        if ev.accepted:
            self.estimator.add_ground_result(ev.kf_id, ev.scale, ev.sigma_log)
        self.events.emit(ev)

    def _graph_scale(self, kf_id: int) -> float | None:
        """Scale of keyframe ``kf_id``'s ``S_world_kf`` now (m per its VO unit; caller holds
        ``_lock``), None when the graph does not know it."""
        graph = self.estimator.graph
        return sim3.scale(graph.estimate(kf_id)) if graph.has(kf_id) else None

    def _measure_scale(self, kf: MarginalizedKeyframe) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Depth request -> (per-landmark scale measurements, the metric inverse-depth map
        (h, w) 1/m kept for loop verification); ``(None, None)`` on failure. Emits
        :class:`~metricslam.slam.events.ScaleMeasured` either way."""
        from metricslam.depth.sample import sample_map

        self._counters["depth_requests"] += 1
        image = kf.image
        size = (int(image.shape[1]), int(image.shape[0]))
        uv = np.asarray(kf.landmarks_uv_px, dtype=float).reshape(-1, 2)
        xi = np.asarray(kf.landmarks_inv_depth, dtype=float).reshape(-1)
        t0 = time.perf_counter()
        error = ""
        try:
            inv_map = self.depth_source.inv_depth_map(image, kf.camera)
            z = sample_map(inv_map, uv, size)
        except MetricSlamError as exc:  # DepthSourceError, ImageError: skip this keyframe
            error = str(exc)
            log.warning("no scale factors for keyframe %d: %s", kf.kf_id, exc)
        except Exception as exc:  # noqa: BLE001 -- a foreign source must never kill the worker
            error = f"{type(exc).__name__}: {exc}"
            log.warning("depth source raised %s for keyframe %d: %s", type(exc).__name__, kf.kf_id, exc)
        if error:
            self._counters["depth_failures"] += 1
            self.events.emit(ScaleMeasured(int(kf.kf_id), int(kf.frame_index), int(kf.t_ns), uv, xi,
                                           np.empty(0), np.empty(0), None, size, error))
            return None, None
        self._depth_ms.append(1e3 * (time.perf_counter() - t0))
        scales = scale_measurements(xi, z, self.config)
        inv_map = np.asarray(inv_map, dtype=np.float32)
        self.events.emit(ScaleMeasured(int(kf.kf_id), int(kf.frame_index), int(kf.t_ns), uv, xi,
                                       np.asarray(z, dtype=float), scales, inv_map, size))
        return scales, inv_map

    # -- workers ------------------------------------------------------------------------------
    def _depth_worker(self) -> None:
        while True:
            with self._cv:
                while not self._depth_requests and not self._stop:
                    self._cv.wait()
                if self._stop and not self._depth_requests:
                    return
                req = self._depth_requests.popleft()
                self._busy += 1
            res = (None, None)
            try:
                res = self._measure_scale(req)
            finally:
                with self._cv:
                    self._scale_results.append((req.kf_id, *res))
                    self._busy -= 1
                    self._cv.notify_all()

    def _graph_worker(self) -> None:
        while True:
            with self._cv:
                while not self._incoming and not self._scale_results and not self._stop:
                    self._cv.wait()
                if self._stop and not self._incoming and not self._scale_results:
                    return
                incoming = list(self._incoming)
                self._incoming.clear()
                results = list(self._scale_results)
                self._scale_results.clear()
                dropped, self._dropped = self._dropped, []
                self._busy += 1
            try:
                with self._lock:
                    for kf, epoch in incoming:
                        self.estimator.integrate(kf, epoch)
                        self._measure_ground(kf)
                    for kf_id in dropped:
                        self.estimator.depth_dropped(kf_id)
                    for kf_id, scales, inv_map in results:
                        self.estimator.add_depth_result(kf_id, scales, inv_map)
                    self.estimator.update()
                    self._take_solved()
            except Exception:  # never let the worker die silently; the pipeline keeps tracking
                log.exception("global graph worker failed on a batch; continuing")
            finally:
                with self._cv:
                    self._busy -= 1
                    self._cv.notify_all()
