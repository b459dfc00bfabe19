"""Loop queries and loop factors of :class:`~metricslam.slam.graph.backend.GlobalBackend`.

A mixin: it runs on the back end's own state (its lock held by the caller): ``_loop_waiting``
(keyframes in order, waiting for their depth map), ``_depth_done`` / ``_depth_dropped_ids``,
``_pending_loops`` (verified, gated after the next solve), ``_loops``, ``_records``, ``graph``,
``loop_detector``, ``depth_source``, ``events`` and ``config``.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from metricslam.errors import MetricSlamError
from metricslam.slam.events import LoopAccepted
from metricslam.slam.graph.records import LoopRecord

log = logging.getLogger("metricslam.slam.graph.backend")


class LoopHandling:
    """Loop detection calls and loop-factor insertion for the global back end (mixin)."""

    def _run_loop_queries(self, final: bool) -> None:
        """Query loops for waiting keyframes, in order, once each has its depth map (scale mode;
        a failed or dropped depth request, or ``final``, lets it go without). Caller holds the
        lock."""
        while self._loop_waiting:
            kf = self._loop_waiting[0]
            k = int(kf.kf_id)
            if self.depth_source is None or k in self._depth_done:
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
            self._loop_ms.append(1e3 * (time.perf_counter() - t0))
            self._loops_verified += len(candidates)
            # added after the next solve: the gate needs both keyframes inside ISAM2 (their
            # joint marginal); the newest keyframe is only pending until then
            self._pending_loops.extend(candidates)
        if self.loop_detector is None:
            self._depth_done.clear()

    def _add_loop(self, cand) -> None:
        sig = getattr(cand, "sigmas", None)
        if sig is not None:  # measured from geometry with its own covariance (floors only)
            sig = np.maximum(np.asarray(sig, dtype=float), [1e-4] * 3 + [self.config.odom_sigma_trans_min] * 3
                             + [0.005])
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
            self._loops.append(rec)
            self.events.emit(LoopAccepted(rec.kf_old, rec.kf_new, rec.frame_old, rec.frame_new,
                                          rec.n_inliers))

    def _loop_still_in_graph(self, lp: LoopRecord) -> bool:
        return any((v[0], v[1]) == (lp.kf_old, lp.kf_new) for v in self.graph._loop_indices.values())
