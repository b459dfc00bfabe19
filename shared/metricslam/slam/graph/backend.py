"""``GlobalBackend``: marginalized keyframes -> global Sim(3) graph -> metric warp for the VO.

Threads and queues (``GraphConfig.inline=False``):

* the caller's (tracking) thread runs :meth:`GlobalBackend.on_keyframe_marginalized`, which only
  records the keyframe (never dropped) and puts a depth request on a bounded queue
  (``depth_queue_size``; when full the OLDEST request is dropped, so that keyframe gets no scale
  factors) — it never waits on depth, loop detection or the solver;
* a depth worker asks the :class:`~metricslam.slam.depth_source.DepthSource` for metric inverse
  depth and turns it into per-landmark scale measurements ``ξ_j / z_j`` (eq. 12);
* a graph worker inserts keyframes with their odometry (see :mod:`.odometry` for the units
  bookkeeping across corrections), runs loop detection (in scale mode once the keyframe's depth
  map has arrived — loop verification uses it for corner depth; a failed or dropped request lets
  the query go without), adds scale factors and solves (ISAM2); verified loops are gated and
  added after that solve, when the new keyframe is inside ISAM2, and solved again.
  After a solve it offers the warp ``S_new_vo`` via :meth:`take_correction`.

With ``inline=True`` everything runs inside ``on_keyframe_marginalized`` (deterministic).
``depth_source=None`` means no learned scale at all (the ``--no-scale`` ablation: the first
keyframe's scale is anchored instead).
"""

from __future__ import annotations

import collections
import logging
import threading
import time

import numpy as np

from metricslam.errors import GraphError, MetricSlamError
from metricslam.geometry import sim3
from metricslam.slam.depth_source import DepthSource
from metricslam.slam.events import EventBus, ScaleMeasured, Solved, WarpApplied
from metricslam.slam.graph.backend_loops import LoopHandling
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.odometry import (
    VoFrameHistory,
    odometry_information,
    orthonormalize,
    relative_sim3,
    resolve_epoch,
)
from metricslam.slam.graph.records import KeyframeRecord, LoopRecord
from metricslam.slam.graph.scale_factor import scale_measurements
from metricslam.slam.graph.sim3_graph import GlobalPoseGraph
from metricslam.slam.types import MarginalizedKeyframe

log = logging.getLogger(__name__)


class GlobalBackend(LoopHandling):
    """Implements :class:`metricslam.slam.types.Backend`.

    Args:
        config: graph, loop and threading parameters.
        depth_source: metric inverse depth provider, or None for no learned scale.
        loop_detector: a :class:`metricslam.slam.loop.LoopDetector` (or None: no loops).
    """

    def __init__(self, config: GraphConfig | None = None, depth_source: DepthSource | None = None,
                 loop_detector: object | None = None) -> None:
        self.config = config or GraphConfig()
        self.depth_source = depth_source
        self.loop_detector = loop_detector
        #: what the back end did (:mod:`metricslam.slam.events`): subscribe here to observe it
        self.events = EventBus()
        self.graph = GlobalPoseGraph(self.config, anchor_scale=depth_source is None)
        self.history = VoFrameHistory()
        self._lock = threading.RLock()  # guards graph + records + correction state
        self._cv = threading.Condition()
        self._incoming: collections.deque = collections.deque()  # (kf, epoch)
        self._depth_requests: collections.deque = collections.deque()
        self._scale_results: collections.deque = collections.deque()  # (kf_id, scales, inv_map)
        # loop queries wait for their keyframe's depth map (scale mode): keyframes in order,
        # finished depth requests (kf_id -> map or None on failure) and dropped request ids
        self._loop_waiting: collections.deque = collections.deque()
        self._depth_done: dict[int, np.ndarray | None] = {}
        self._depth_dropped_ids: set[int] = set()
        self._loops_verified = 0
        self._pending_loops: list = []  # verified LoopCandidates waiting for the next solve
        self._pending_scales: dict[int, np.ndarray] = {}
        self._records: dict[int, KeyframeRecord] = {}
        self._last_of_segment: dict[int, int] = {}
        self._newest_kf: int | None = None
        self._corr_lock = threading.Lock()  # guards _pending_correction only (never held long)
        self._pending_correction: tuple[np.ndarray, int, np.ndarray] | None = None
        self._loops: list[LoopRecord] = []
        self._busy = 0
        self._stop = False
        self._scale_factors_solved = 0
        self._stats = collections.Counter()
        self._solve_ms: list[float] = []
        self._depth_ms: list[float] = []
        self._loop_ms: list[float] = []
        self._threads: list[threading.Thread] = []
        if not self.config.inline:
            self._threads.append(threading.Thread(target=self._graph_worker, name="graph", daemon=True))
            if depth_source is not None:
                self._threads.append(threading.Thread(target=self._depth_worker, name="depth", daemon=True))
            for t in self._threads:
                t.start()

    # -- Backend protocol ---------------------------------------------------------------------
    def on_keyframe_marginalized(self, kf: MarginalizedKeyframe) -> None:
        """Record ``kf`` (in the VO frame of the current epoch). Never blocks on depth/solve."""
        epoch = self.history.epoch
        if self.config.inline:
            with self._lock:
                self._integrate(kf, epoch)
                if self.depth_source is not None:
                    scales, inv_map = self._measure_scale(kf)
                    if scales is not None:
                        self._pending_scales[kf.kf_id] = scales
                    self._depth_done[kf.kf_id] = inv_map
                self._run_loop_queries(final=False)
                self._flush_scales()
                self._solve()
            return
        with self._cv:
            self._incoming.append((kf, epoch))
            if self.depth_source is not None:
                if len(self._depth_requests) >= self.config.depth_queue_size:
                    dropped = self._depth_requests.popleft()
                    self._depth_dropped_ids.add(int(dropped.kf_id))
                    self._stats["depth_dropped"] += 1
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
            if self._pending_correction is None:
                return None
            T_vo_n, epoch_n, S_world_n = self._pending_correction
            self._pending_correction = None
            S_ve_n = self.history.between(epoch_n, self.history.epoch) @ T_vo_n
            S_new_vo = orthonormalize(S_world_n @ sim3.inverse(orthonormalize(S_ve_n)))
            epoch = self.history.issue(S_new_vo)
            self._stats["corrections"] += 1
        self.events.emit(WarpApplied(S_new_vo, sim3.scale(S_new_vo), epoch))
        return S_new_vo

    def _offer_correction(self) -> None:
        """After a solve (caller holds ``_lock``): remember the newest keyframe's solved pose."""
        if self._newest_kf is None:
            return
        rec = self._records[self._newest_kf]
        S_world_n = self.graph.estimate(rec.kf_id)
        with self._corr_lock:
            self._pending_correction = (rec.T_vo_kf, rec.epoch, S_world_n)

    def optimized_keyframe_poses(self) -> dict[int, np.ndarray]:
        with self._lock:
            est = self.graph.estimates()
            return {self._records[k].frame_index: S for k, S in est.items()}

    @property
    def scale_established(self) -> bool:
        if self.depth_source is None:
            return False
        return self._scale_factors_solved >= self.config.min_scale_factors_established

    @property
    def loops(self) -> list[LoopRecord]:
        with self._lock:
            return list(self._loops)

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
            self._run_loop_queries(final=True)
            self._flush_scales()
            if self._pending_loops:
                self._solve()
            try:
                self.graph.solve(extra_iterations=max(self.config.extra_iterations, 5))
                self._offer_correction()
            except GraphError as exc:
                log.warning("final global solve failed: %s", exc)

    def stats(self) -> dict:
        """Counters and timings (ms) of the back end."""
        def _mean(x: list[float]) -> float:
            return float(np.mean(x)) if x else 0.0
        # no lock: plain counters and list copies (a status publisher must not wait on a solve)
        loops = list(self._loops)
        solve_ms = list(self._solve_ms)
        return {
            "keyframes": self.graph.n_keyframes,
            "scale_factors": self.graph.n_scale_factors,
            "loops_accepted": len(loops),
            "loops_rejected": self.graph.n_loops_rejected,
            "loops": [(lp.frame_old, lp.frame_new) for lp in loops],
            "loop_keyframes": [(lp.kf_old, lp.kf_new) for lp in loops],
            "loop_inliers": [lp.n_inliers for lp in loops],
            "loops_verified": self._loops_verified,
            "depth_requests": self._stats["depth_requests"],
            "depth_failures": self._stats["depth_failures"],
            "depth_dropped": self._stats["depth_dropped"],
            "corrections": self._stats["corrections"],
            "segment_links": self._stats["segment_links"],
            "epoch_mismatches": self._stats["epoch_mismatches"],
            "graph_rebuilds": self.graph.n_rebuilds,
            "graph_stabilized": self.graph.n_stabilized,
            "depth_ms_mean": _mean(list(self._depth_ms)),
            "solve_ms_mean": _mean(solve_ms),
            "solve_ms_max": float(max(solve_ms)) if solve_ms else 0.0,
            "loop_ms_mean": _mean(list(self._loop_ms)),
            "scale_established": self.scale_established,
        }

    # -- work ---------------------------------------------------------------------------------
    def _measure_scale(self, kf: MarginalizedKeyframe) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Depth request -> (per-landmark scale measurements, the metric inverse-depth map
        (h, w) 1/m kept for loop verification); ``(None, None)`` on failure. Emits
        :class:`~metricslam.slam.events.ScaleMeasured` either way."""
        from metricslam.depth.sample import sample_map

        self._stats["depth_requests"] += 1
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
            self._stats["depth_failures"] += 1
            self.events.emit(ScaleMeasured(int(kf.kf_id), int(kf.frame_index), int(kf.t_ns), uv, xi,
                                           np.empty(0), np.empty(0), None, size, error))
            return None, None
        self._depth_ms.append(1e3 * (time.perf_counter() - t0))
        scales = scale_measurements(xi, z, self.config)
        inv_map = np.asarray(inv_map, dtype=np.float32)
        self.events.emit(ScaleMeasured(int(kf.kf_id), int(kf.frame_index), int(kf.t_ns), uv, xi,
                                       np.asarray(z, dtype=float), scales, inv_map, size))
        return scales, inv_map

    def _integrate(self, kf: MarginalizedKeyframe, epoch: int) -> None:
        """Insert one keyframe (odometry or prior) and queue its loop query. Caller holds the lock."""
        prev_id = self._last_of_segment.get(int(kf.segment_id))
        T_vo_kf = np.asarray(kf.T_vo_kf, dtype=float)
        S_prev_k = None
        if prev_id is not None:
            prev = self._records[prev_id]
            epoch, S_prev_k, consistent = resolve_epoch(self.history, prev.T_vo_kf, prev.epoch,
                                                        T_vo_kf, kf.T_prevkf_kf, epoch)
            if kf.T_prevkf_kf is not None and not consistent:
                self._stats["epoch_mismatches"] += 1
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
            self.graph.add_keyframe(rec.kf_id, guess, last.kf_id, S_last_k, np.diag(1.0 / sig**2))
            self._stats["segment_links"] += 1
        self._records[rec.kf_id] = rec
        self._last_of_segment[rec.segment_id] = rec.kf_id
        self._newest_kf = rec.kf_id
        if self.loop_detector is not None:
            self._loop_waiting.append(kf)

    def _flush_scales(self) -> None:
        for kf_id in [k for k in self._pending_scales if self.graph.has(k)]:
            self.graph.add_scale_measurements(kf_id, self._pending_scales.pop(kf_id))

    def _solve(self) -> None:
        t0 = time.perf_counter()
        n_before = self.graph.n_scale_factors
        try:
            res = self.graph.solve()
            if self._pending_loops:  # gate against the solved graph, then solve with the loops
                for cand in self._pending_loops:
                    self._add_loop(cand)
                self._pending_loops = []
                res2 = self.graph.solve()
                res = {**res2, "loops_removed": res["loops_removed"] + res2["loops_removed"]}
        except GraphError as exc:
            log.warning("global solve failed: %s", exc)
            return
        if res["loops_removed"]:
            self._loops = [lp for lp in self._loops if self._loop_still_in_graph(lp)]
        solve_ms = 1e3 * (time.perf_counter() - t0)
        self._solve_ms.append(solve_ms)
        self._scale_factors_solved = n_before
        self._offer_correction()
        newest = -1 if self._newest_kf is None else self._records[self._newest_kf].frame_index
        self.events.emit(Solved(self.graph.n_keyframes, self.graph.n_scale_factors, newest,
                                int(res["loops_removed"]), solve_ms))

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
                self._busy += 1
            try:
                with self._lock:
                    for kf, epoch in incoming:
                        self._integrate(kf, epoch)
                    for kf_id, scales, inv_map in results:
                        if scales is not None:
                            self._pending_scales[kf_id] = scales
                        if self.loop_detector is not None:
                            self._depth_done[int(kf_id)] = inv_map
                    self._run_loop_queries(final=False)
                    self._flush_scales()
                    self._solve()
            except Exception:  # never let the worker die silently; the pipeline keeps tracking
                log.exception("global graph worker failed on a batch; continuing")
            finally:
                with self._cv:
                    self._busy -= 1
                    self._cv.notify_all()
