"""The VO's sliding window: keyframes, landmarks, marginalization prior, BA and marginalization.

:class:`SlidingWindow` is the back-end half of :class:`~metricslam.slam.vo.local_vo.LocalVO`
(paper §III-C.3/4). All state is guarded by one re-entrant lock so the tracking thread, the BA
worker (:class:`BAWorker`) and ``apply_similarity`` (the global graph's warp) can interleave:
a solve copies the window under the lock, optimizes without it, and writes back its result
re-expressed through any warps applied meanwhile (``warps``). Marginalized keyframes are queued in ``outbox``; the owner
delivers them from its own thread.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.geometry import se3, sim3
from metricslam.slam.timing import TimingSummary
from metricslam.slam.types import MarginalizedKeyframe
from metricslam.slam.vo.ba import bundle_adjust
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.landmarks import LandmarkMap
from metricslam.slam.vo.linear_system import Prior, residuals
from metricslam.slam.vo.marginalization import marginalize_pose, project_out_gauge, rescale_prior
from metricslam.slam.vo.reprojection import triangulate_inverse_depth

log = logging.getLogger(__name__)


@dataclass
class Keyframe:
    """A window keyframe: ``T_world_kf`` (4, 4) in the segment's VO world, its gray image."""

    kf_id: int
    frame_index: int
    t_ns: int
    segment_id: int
    T_world_kf: np.ndarray
    image: np.ndarray


class SlidingWindow:
    """Window state and the operations on it (all thread-safe through ``lock``).

    Args:
        config: VO parameters (window size, Huber threshold, iterations, parallax).
        camera: intrinsics of the keyframe images.
        counters, timings_ms: the owner's statistics, updated in place.
    """

    def __init__(self, config: VOConfig, camera: PinholeCamera, counters: dict,
                 timings_ms: dict[str, TimingSummary]) -> None:
        self.config = config
        self.camera = camera
        self.lock = threading.RLock()
        self.keyframes: list[Keyframe] = []
        self.map = LandmarkMap(camera)
        self.prior: Prior | None = None
        self.prior_ids: list[int] = []
        self.warps: list[np.ndarray] = []  # every S_new_old applied so far (generation = len)
        self.outbox: deque[MarginalizedKeyframe] = deque()
        self.frozen_poses: dict[int, np.ndarray] = {}  # frame_index -> T at marginalization
        self._last_marg: dict[int, np.ndarray] = {}  # segment -> T_vo_kf of its last marginalized
        self._next_kf_id = 0
        #: called (under ``lock``) with ``C_new_old`` (4, 4) after a solve moved the newest
        #: solved keyframe; the owner moves its current pose with it
        self.on_correction: Callable[[np.ndarray], None] | None = None
        self.counters = counters
        self.timings_ms = timings_ms

    # -- building -------------------------------------------------------------------------------
    def add_keyframe(self, frame_index: int, t_ns: int, segment_id: int, T_world_kf: np.ndarray,
                     image: np.ndarray) -> Keyframe:
        with self.lock:
            kf = Keyframe(self._next_kf_id, frame_index, t_ns, segment_id,
                          np.array(T_world_kf, dtype=float), image)
            self._next_kf_id += 1
            self.keyframes.append(kf)
            self.counters["keyframes"] += 1
            return kf

    def observe(self, kf: Keyframe, ids: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
        """Record tracked pixels as observations in ``kf`` and triangulate landmarks that had no
        depth yet (enough parallax required). Returns ids of landmarks found inconsistent
        (negative depth), which are deleted and should stop being tracked."""
        cfg = self.config
        with self.lock:
            fresh = []
            for lid, uv in zip(ids, uv_px):
                lm = self.map.landmarks.get(int(lid))
                if lm is None or lm.host_kf == kf.kf_id:
                    continue
                lm.obs[kf.kf_id] = np.array(uv, dtype=float)
                if not lm.has_depth:
                    fresh.append(lm)
            T_by_kf = {k.kf_id: k.T_world_kf for k in self.keyframes}
            fresh = [lm for lm in fresh if lm.host_kf in T_by_kf]
            if not fresh:
                return np.zeros(0, dtype=np.int64)
            n = len(fresh)
            uv = np.array([lm.obs[kf.kf_id] for lm in fresh])
            rho, parallax = triangulate_inverse_depth(
                np.array([T_by_kf[lm.host_kf] for lm in fresh]), np.repeat(kf.T_world_kf[None], n, 0),
                np.array([lm.bearing for lm in fresh]), self.camera.normalized(uv))
            enough = parallax >= np.radians(cfg.min_landmark_parallax_deg)
            bad = []
            for lm, r, ok in zip(fresh, rho, enough):
                if not ok:
                    continue  # wait for more baseline
                if np.isfinite(r) and r > 0:
                    lm.rho, lm.has_depth = float(r), True
                else:
                    bad.append(lm.lm_id)
            for lid in bad:
                del self.map.landmarks[lid]
            return np.array(bad, dtype=np.int64)

    # -- queries --------------------------------------------------------------------------------
    def poses_by_kf(self) -> dict[int, np.ndarray]:
        with self.lock:
            return {kf.kf_id: kf.T_world_kf.copy() for kf in self.keyframes}

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """``frame_index -> T_world_kf`` of every keyframe so far (window ones current)."""
        with self.lock:
            out = dict(self.frozen_poses)
            for kf in self.keyframes:
                out[kf.frame_index] = kf.T_world_kf.copy()
            return out

    # -- optimization ---------------------------------------------------------------------------
    def _window_prior(self, kf_ids: list[int], T: np.ndarray) -> Prior | None:
        """The marginalization prior zero-padded to the window's keyframes."""
        if self.prior is None:
            return None
        n = len(kf_ids)
        H, b = np.zeros((6 * n, 6 * n)), np.zeros(6 * n)
        T_lin = np.array(T, copy=True)
        pos = [kf_ids.index(k) for k in self.prior_ids]
        idx = np.concatenate([np.arange(6 * p, 6 * p + 6) for p in pos])
        H[np.ix_(idx, idx)] = self.prior.H
        b[idx] = self.prior.b
        T_lin[pos] = self.prior.T_lin
        return Prior(H, b, T_lin)

    def optimize_and_marginalize(self) -> None:
        """One LM solve of the window (oldest pose fixed), outlier pruning, then marginalize
        keyframes beyond ``window_size``."""
        cfg = self.config
        t0 = time.perf_counter()
        with self.lock:
            kf_ids = [kf.kf_id for kf in self.keyframes]
            T = np.array([kf.T_world_kf for kf in self.keyframes])
            problem, lm_ids = self.map.problem(kf_ids, T, self._window_prior(kf_ids, T))
            generation = len(self.warps)
        if problem.n_landmarks >= 6 and len(kf_ids) >= 2:
            res = bundle_adjust(problem, cfg.huber_px, cfg.ba_iterations, fixed_poses=(0,))
            final = problem.with_values(res.T_world_kf, res.lm_rho)
            err = np.linalg.norm(residuals(final).residual_px, axis=1)
            with self.lock:
                T_new, rho_new = res.T_world_kf, res.lm_rho
                if len(self.warps) > generation:  # warped while solving: follow the warps
                    S = np.eye(4)
                    for W in self.warps[generation:]:
                        S = W @ S
                    T_new, rho_new = _warp_poses(S, T_new), rho_new / sim3.scale(S)
                self._write_back(kf_ids, lm_ids, problem, T_new, rho_new, err)
            self.timings_ms["ba"].append(1e3 * (time.perf_counter() - t0))
        with self.lock:
            while len(self.keyframes) > cfg.window_size:
                t1 = time.perf_counter()
                self.marginalize_oldest()
                self.timings_ms["marginalization"].append(1e3 * (time.perf_counter() - t1))

    def _write_back(self, kf_ids, lm_ids, problem, T_new, rho_new, err_px) -> None:
        by_id = {kf.kf_id: kf for kf in self.keyframes}
        newest = by_id.get(kf_ids[-1])
        # keyframes added while the solve ran (background mode) follow the newest solved one,
        # so the map the tracker uses stays consistent
        C = None if newest is None else T_new[-1] @ se3.inverse(newest.T_world_kf)
        for k, Tk in zip(kf_ids, T_new):
            if k in by_id:
                by_id[k].T_world_kf = Tk
        if C is not None:
            solved = set(kf_ids)
            for kf in self.keyframes:
                if kf.kf_id not in solved:
                    kf.T_world_kf = C @ kf.T_world_kf
            if self.on_correction is not None:
                self.on_correction(C)
        for j, lid in enumerate(lm_ids):
            lm = self.map.landmarks.get(lid)
            if lm is not None:
                lm.rho = float(rho_new[j])
        for o in np.flatnonzero(err_px > 3.0 * self.config.huber_px):
            lm = self.map.landmarks.get(lm_ids[problem.obs_lm[o]])
            if lm is not None:
                lm.obs.pop(kf_ids[problem.obs_kf[o]], None)
                if not lm.obs:
                    lm.has_depth = False
        self.counters["ba_solves"] += 1

    def marginalize_oldest(self) -> None:
        """Schur out the oldest keyframe and its child landmarks; queue it in ``outbox``."""
        with self.lock:
            kf = self.keyframes[0]
            kf_ids = [k.kf_id for k in self.keyframes]
            T = np.array([k.T_world_kf for k in self.keyframes])
            if len(kf_ids) > 1:
                problem, _ = self.map.problem(kf_ids, T, self._window_prior(kf_ids, T),
                                              only_hosts={kf.kf_id})
                self.prior = project_out_gauge(marginalize_pose(problem, 0, self.config.huber_px))
                self.prior_ids = kf_ids[1:]
            else:
                self.prior, self.prior_ids = None, []
            prev = self._last_marg.get(kf.segment_id)
            self.outbox.append(self._handoff(kf, None if prev is None else se3.inverse(prev) @ kf.T_world_kf))
            self._last_marg[kf.segment_id] = kf.T_world_kf.copy()
            self.frozen_poses[kf.frame_index] = kf.T_world_kf.copy()
            self.keyframes.pop(0)
            self.map.remove_keyframe(kf.kf_id)
            self.counters["marginalized"] += 1

    def _handoff(self, kf: Keyframe, T_prevkf_kf: np.ndarray | None) -> MarginalizedKeyframe:
        """``kf`` with its child landmarks that have a depth, as the global graph receives it."""
        kids = [lm for lm in self.map.children(kf.kf_id) if lm.has_depth and lm.rho > 0]
        return MarginalizedKeyframe(
            kf_id=kf.kf_id, frame_index=kf.frame_index, t_ns=kf.t_ns, segment_id=kf.segment_id,
            T_vo_kf=kf.T_world_kf.copy(), T_prevkf_kf=T_prevkf_kf,
            landmarks_uv_px=np.array([lm.uv_host_px for lm in kids]).reshape(-1, 2),
            landmarks_inv_depth=np.array([lm.rho for lm in kids], dtype=float),
            image=kf.image, camera=self.camera)

    def settled_after(self, kf_id: int) -> tuple[list[MarginalizedKeyframe], int]:
        """Snapshots (``T_prevkf_kf`` None) of the window keyframes newer than ``kf_id`` that are
        not the newest (a later keyframe observed them, so their landmarks have depth), and the
        warp generation they are expressed in (``len(warps)``)."""
        with self.lock:
            return [self._handoff(kf, None) for kf in self.keyframes[:-1] if kf.kf_id > kf_id], len(self.warps)

    def warp_since(self, generation: int) -> np.ndarray:
        """The Sim(3) (4, 4) of every warp applied since ``generation`` (``len(warps)`` then),
        composed: it maps that moment's VO world to today's."""
        with self.lock:
            S = np.eye(4)
            for W in self.warps[generation:]:
                S = W @ S
            return S

    def clear(self) -> None:
        """Forget the window (after it was marginalized, e.g. on tracking loss)."""
        with self.lock:
            self.keyframes.clear()
            self.map = LandmarkMap(self.camera)
            self.prior, self.prior_ids = None, []

    # -- the global graph's warp ----------------------------------------------------------------
    def apply_similarity(self, S_new_old: np.ndarray, segment_id: int) -> Callable[[np.ndarray], np.ndarray]:
        """Re-express the window in a world related by ``S_new_old``; returns the pose warp."""
        S = np.asarray(S_new_old, dtype=float)
        s = sim3.scale(S)
        R, t = S[:3, :3] / s, S[:3, 3]

        def warp(T: np.ndarray) -> np.ndarray:
            out = np.eye(4)
            out[:3, :3] = R @ T[:3, :3]
            out[:3, 3] = s * R @ T[:3, 3] + t
            return out

        with self.lock:
            for kf in self.keyframes:
                kf.T_world_kf = warp(kf.T_world_kf)
            for lm in self.map.landmarks.values():
                lm.rho /= s
            if self.prior is not None:
                self.prior = rescale_prior(self.prior, S)
            if segment_id in self._last_marg:
                self._last_marg[segment_id] = warp(self._last_marg[segment_id])
            # keyframes marginalized but not yet delivered must arrive in the new frame too
            for k, mkf in enumerate(self.outbox):
                rel = None
                if mkf.T_prevkf_kf is not None:
                    rel = mkf.T_prevkf_kf.copy()
                    rel[:3, 3] *= s
                self.outbox[k] = dataclasses.replace(
                    mkf, T_vo_kf=warp(mkf.T_vo_kf), T_prevkf_kf=rel,
                    landmarks_inv_depth=mkf.landmarks_inv_depth / s)
                # the owner rescales anchors of undelivered keyframes: their poses follow too
                self.frozen_poses[mkf.frame_index] = self.outbox[k].T_vo_kf.copy()
            self.warps.append(S.copy())
        return warp


def _warp_poses(S_new_old: np.ndarray, T_old: np.ndarray) -> np.ndarray:
    """Rigid poses (n, 4, 4) mapped by a similarity: rotation ``R·R_i``, position ``S·t_i``."""
    s = sim3.scale(S_new_old)
    R = S_new_old[:3, :3] / s
    out = np.array(T_old, copy=True)
    out[:, :3, :3] = R @ out[:, :3, :3]
    out[:, :3, 3] = out[:, :3, 3] @ S_new_old[:3, :3].T + S_new_old[:3, 3]
    return out


class BAWorker:
    """Runs ``window.optimize_and_marginalize`` in a background thread; requests coalesce."""

    def __init__(self, window: SlidingWindow) -> None:
        self.window = window
        self._queue: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._loop, name="vo-ba", daemon=True)
        self._thread.start()

    def request(self) -> None:
        self._queue.put("solve")

    def wait_idle(self) -> None:
        if self._thread.is_alive():
            self._queue.join()

    def stop(self) -> None:
        if self._thread.is_alive():
            self._queue.put("stop")
            self._thread.join(timeout=10.0)

    def _loop(self) -> None:
        while True:
            item = self._queue.get()
            n_items = 1
            while item != "stop":  # several queued requests: one solve serves them all
                try:
                    nxt = self._queue.get_nowait()
                except queue.Empty:
                    break
                n_items += 1
                item = "stop" if nxt == "stop" else item
            try:
                if item != "stop":
                    self.window.optimize_and_marginalize()
            except Exception:  # noqa: BLE001 -- keep the worker alive
                log.exception("window solve failed")
            finally:
                for _ in range(n_items):
                    self._queue.task_done()
            if item == "stop":
                return
