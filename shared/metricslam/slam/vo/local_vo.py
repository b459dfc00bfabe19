"""Local monocular VO (paper §III-C): KLT frontend + sliding-window BA + marginalization.

:class:`LocalVO` is driven frame by frame through :meth:`LocalVO.process`, which never raises.
Every frame is tracked against the window map by motion-only BA; keyframes are added when the
mean corner motion since the last keyframe exceeds a threshold (or tracks run low); a background
worker then runs windowed LM (``ba.py``) and marginalizes the oldest keyframe
(``marginalization.py``) once the window is full. Marginalized keyframes are queued and handed
to the consumer from the thread that calls ``process`` / ``flush`` (so consumers need no locks).

Every frame is *anchored* to a keyframe (``T_kf_cam``) so that later refinements of keyframe
poses (window BA, global graph) move it too: :meth:`take_anchor_updates` returns the anchors of
newly processed frames. Poses are ``T_world_cam`` in the VO world of the current segment
(first camera of the segment, or the last known pose before a tracking loss).
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections import defaultdict, deque
from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets.base import Frame
from metricslam.geometry import se3, so3
from metricslam.slam.types import KeyframeConsumer, MarginalizedKeyframe, PoseEstimate, TrackingState
from metricslam.slam.vo.ba import bundle_adjust, orthonormalized
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.frontend import KLTFrontend
from metricslam.slam.vo.initializer import try_initialize
from metricslam.slam.vo.landmarks import LandmarkMap
from metricslam.slam.vo.linear_system import Prior, residuals
from metricslam.slam.vo.marginalization import marginalize_pose, project_out_gauge, rescale_prior
from metricslam.slam.vo.motion_only import estimate_pose
from metricslam.slam.vo.reprojection import triangulate_inverse_depth

log = logging.getLogger(__name__)


def _limit_blas_threads(n: int) -> None:
    """Cap OpenBLAS threads process-wide (the window's matrices are tiny; oversubscribed BLAS
    threads on a busy machine made one Schur product ~10x slower)."""
    try:
        import threadpoolctl
    except ImportError:  # optional: only a speed-up
        log.debug("threadpoolctl not installed; BLAS thread count left alone")
        return
    threadpoolctl.threadpool_limits(n, user_api="blas")


@dataclass
class _Keyframe:
    kf_id: int
    frame_index: int
    t_ns: int
    segment_id: int
    T_world_kf: np.ndarray
    image: np.ndarray


@dataclass(frozen=True)
class Anchor:
    """Frame ``frame_index`` sits at ``T_kf_cam`` from keyframe frame ``kf_frame_index``."""

    frame_index: int
    kf_frame_index: int
    T_kf_cam: np.ndarray


@dataclass
class _InitRef:
    frame_index: int
    t_ns: int
    image: np.ndarray
    ids: np.ndarray
    uv_px: np.ndarray
    T_world_ref: np.ndarray
    pending: list  # (frame_index, t_ns) of frames processed since the reference


class LocalVO:
    """Monocular sliding-window VO for one camera.

    Args:
        config: algorithm parameters (:meth:`VOConfig.preset`).
        camera: intrinsics of the incoming images.
        consumer: receives each :class:`MarginalizedKeyframe` (e.g. the global graph), or None.
    """

    def __init__(self, config: VOConfig, camera: PinholeCamera,
                 consumer: KeyframeConsumer | None = None) -> None:
        self.config = config
        self.camera = camera
        self.consumer = consumer
        self._lock = threading.RLock()
        self.frontend = KLTFrontend(config, camera)
        self.map = LandmarkMap(camera)
        self.window: list[_Keyframe] = []
        self._prior: Prior | None = None
        self._prior_ids: list[int] = []
        self._segment = 0
        self._tracking = False
        self._ref: _InitRef | None = None
        self._next_kf_id = 0
        self._T_world_last = np.eye(4)
        self._T_last_cur = np.eye(4)  # constant-velocity model
        self._last_kf: _Keyframe | None = None
        self._kf_track_ids = np.zeros(0, dtype=np.int64)
        self._kf_track_uv = np.zeros((0, 2))
        self._frames_since_kf = 0
        self._outbox: deque[MarginalizedKeyframe] = deque()
        self._anchors: list[Anchor] = []
        self._kf_poses: dict[int, np.ndarray] = {}
        self._last_marg: dict[int, np.ndarray] = {}
        self._generation = 0
        self.timings_ms: dict[str, list[float]] = defaultdict(list)
        self.counters = {"frames": 0, "keyframes": 0, "tracking_losses": 0, "invalid_frames": 0,
                         "marginalized": 0, "ba_solves": 0}
        if config.blas_threads is not None:
            _limit_blas_threads(config.blas_threads)
        self._queue: queue.Queue | None = None
        self._worker: threading.Thread | None = None
        if config.ba_in_background:
            self._queue = queue.Queue()
            self._worker = threading.Thread(target=self._worker_loop, name="vo-ba", daemon=True)
            self._worker.start()

    # ------------------------------------------------------------------ public API
    def process(self, frame: Frame) -> PoseEstimate:
        """Track one frame; never raises (bad input -> INVALID_FRAME, failure -> LOST)."""
        self.counters["frames"] += 1
        try:
            gray = self._to_gray(frame)
            if gray is None:
                self.counters["invalid_frames"] += 1
                est = self._estimate(frame, TrackingState.INVALID_FRAME)
            elif not self._tracking:
                est = self._process_init(frame, gray)
            else:
                est = self._process_tracking(frame, gray)
        except Exception:  # noqa: BLE001 -- a bad frame must never kill the caller's loop
            log.exception("VO failed on frame %d; starting a new segment", frame.index)
            est = self._lose(frame)
        self._deliver()
        return est

    def flush(self) -> None:
        """Wait for the worker, marginalize the whole window, deliver everything."""
        self._wait_idle()
        with self._lock:
            while self.window:
                self._marginalize_oldest()
        self._deliver()

    def close(self) -> None:
        """Flush and stop the worker thread."""
        self.flush()
        if self._worker is not None and self._queue is not None:
            self._queue.put("stop")
            self._worker.join(timeout=10.0)
            self._worker = None

    def take_anchor_updates(self) -> list[Anchor]:
        """Anchors of frames processed since the last call (frames during initialization are
        anchored once it succeeds)."""
        with self._lock:
            out, self._anchors = self._anchors, []
        return out

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """``frame_index -> T_world_kf`` of every keyframe so far (window ones current,
        marginalized ones as they were at marginalization), in their segment's VO world."""
        with self._lock:
            out = dict(self._kf_poses)
            for kf in self.window:
                out[kf.frame_index] = kf.T_world_kf.copy()
        return out

    def window_frame_indices(self) -> list[int]:
        with self._lock:
            return [kf.frame_index for kf in self.window]

    @property
    def segment_id(self) -> int:
        return self._segment

    def apply_similarity(self, S_new_old: np.ndarray) -> None:
        """Re-express the window in a world frame related by the Sim(3) ``S_new_old`` (4, 4).

        Moves keyframe poses, landmark inverse depths (÷ s), the last marginalized keyframe's
        pose, the marginalization prior, the motion model and the current pose. Thread-safe: a
        BA solve started before the warp is discarded.
        """
        S = np.asarray(S_new_old, dtype=float)
        s = float(np.cbrt(np.linalg.det(S[:3, :3])))
        R, t = S[:3, :3] / s, S[:3, 3]

        def warp(T: np.ndarray) -> np.ndarray:
            out = np.eye(4)
            out[:3, :3] = R @ T[:3, :3]
            out[:3, 3] = s * R @ T[:3, 3] + t
            return out

        with self._lock:
            for kf in self.window:
                kf.T_world_kf = warp(kf.T_world_kf)
            for lm in self.map.landmarks.values():
                lm.rho /= s
            if self._prior is not None:
                self._prior = rescale_prior(self._prior, S)
            if self._segment in self._last_marg:
                self._last_marg[self._segment] = warp(self._last_marg[self._segment])
            self._T_world_last = warp(self._T_world_last)
            self._T_last_cur = self._T_last_cur.copy()
            self._T_last_cur[:3, 3] *= s
            if self._ref is not None:
                self._ref.T_world_ref = warp(self._ref.T_world_ref)
            # keyframes marginalized but not yet delivered must arrive in the new frame too
            for k, mkf in enumerate(self._outbox):
                rel = None
                if mkf.T_prevkf_kf is not None:
                    rel = mkf.T_prevkf_kf.copy()
                    rel[:3, 3] *= s
                self._outbox[k] = dataclasses.replace(
                    mkf, T_vo_kf=warp(mkf.T_vo_kf), T_prevkf_kf=rel,
                    landmarks_inv_depth=mkf.landmarks_inv_depth / s)
            self._generation += 1

    # ------------------------------------------------------------------ frames
    def _to_gray(self, frame: Frame) -> np.ndarray | None:
        img = frame.image
        if not isinstance(img, np.ndarray) or img.size == 0:
            return None
        if img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        if img.ndim != 2 or img.dtype != np.uint8:
            return None
        if img.shape != (self.camera.height_px, self.camera.width_px):
            return None
        if float(img[::4, ::4].std()) < self.config.min_texture_std:
            return None
        return img

    def _estimate(self, frame: Frame, state: TrackingState, is_kf: bool = False) -> PoseEstimate:
        return PoseEstimate(frame_index=frame.index, t_ns=int(frame.t_ns),
                            T_world_cam=self._T_world_last.copy(), state=state,
                            is_keyframe=is_kf, segment_id=self._segment)

    def _lose(self, frame: Frame) -> PoseEstimate:
        """Tracking loss: marginalize what is left, start a new segment at the last pose."""
        self.counters["tracking_losses"] += 1
        try:
            self.flush()
        except Exception:  # noqa: BLE001
            log.exception("flushing the window after a tracking loss failed")
            with self._lock:
                self.window.clear()
        with self._lock:
            self.map = LandmarkMap(self.camera)
            self._prior, self._prior_ids = None, []
            self._tracking = False
            self._ref = None
            self._last_kf = None
            self._segment += 1
            self.frontend.reset()
            self._T_last_cur = np.eye(4)
        return self._estimate(frame, TrackingState.LOST)

    # ------------------------------------------------------------------ initialization
    def _new_reference(self, frame: Frame, gray: np.ndarray) -> None:
        self.frontend.reset()
        self.frontend.track(gray)
        self.frontend.detect(gray)
        tr = self.frontend.tracks
        self._ref = _InitRef(frame.index, int(frame.t_ns), gray, tr.ids, tr.uv_px,
                             self._T_world_last.copy(), [])

    def _process_init(self, frame: Frame, gray: np.ndarray) -> PoseEstimate:
        t0 = time.perf_counter()
        if self._ref is None:
            self._new_reference(frame, gray)
            self.timings_ms["frontend"].append(1e3 * (time.perf_counter() - t0))
            return self._estimate(frame, TrackingState.INITIALIZING)
        tracks = self.frontend.track(gray)
        self.timings_ms["frontend"].append(1e3 * (time.perf_counter() - t0))
        ref = self._ref
        res = try_initialize(self.config, self.camera, ref.ids, ref.uv_px, tracks.ids, tracks.uv_px)
        if res is None:
            too_old = frame.index - ref.frame_index > self.config.init_max_frames
            if too_old or len(tracks) < self.config.init_min_inliers:
                self._new_reference(frame, gray)
            else:
                ref.pending.append((frame.index, int(frame.t_ns)))
            return self._estimate(frame, TrackingState.INITIALIZING)
        t1 = time.perf_counter()
        self._initialize_map(frame, gray, res)
        self.timings_ms["keyframe"].append(1e3 * (time.perf_counter() - t1))
        return self._estimate(frame, TrackingState.TRACKING, is_kf=True)

    def _initialize_map(self, frame: Frame, gray: np.ndarray, res) -> None:
        ref = self._ref
        # keep the scale of the previous segment when there was one: baseline = speed x frames
        speed = float(np.linalg.norm(self._T_last_cur[:3, 3]))
        n_frames = max(frame.index - ref.frame_index, 1)
        baseline = speed * n_frames if speed > 0 else 1.0
        T_ref_cur = res.T_ref_cur.copy()
        T_ref_cur[:3, 3] *= baseline
        T_world_cur = ref.T_world_ref @ T_ref_cur
        with self._lock:
            kf0 = self._make_kf(ref.frame_index, ref.t_ns, ref.T_world_ref, ref.image)
            kf1 = self._make_kf(frame.index, int(frame.t_ns), T_world_cur, gray)
            tr = self.frontend.tracks
            pos = {int(i): k for k, i in enumerate(tr.ids)}
            ref_pos = {int(i): k for k, i in enumerate(ref.ids)}
            uv0 = np.array([ref.uv_px[ref_pos[int(i)]] for i in res.ids])
            for lm in self.map.add_many(res.ids, kf0.kf_id, uv0, res.rho_ref / baseline):
                lm.obs[kf1.kf_id] = tr.uv_px[pos[lm.lm_id]].copy()
            self.frontend.drop(np.setdiff1d(tr.ids, res.ids))
            new_ids, new_uv = self._detect(gray)
            self.map.add_many(new_ids, kf1.kf_id, new_uv)
            self._snapshot_kf_tracks()
            self._tracking = True
            self._T_world_last = T_world_cur
            self._T_last_cur = np.eye(4)
            self._T_last_cur[:3, 3] = T_ref_cur[:3, 3] / n_frames
            # frames between the two views: interpolate (they had no map to track against)
            self._anchors.append(Anchor(ref.frame_index, ref.frame_index, np.eye(4)))
            span = max(frame.t_ns - ref.t_ns, 1)
            w_ref = so3.log(T_ref_cur[:3, :3])
            for idx, t_ns in ref.pending:
                a = (t_ns - ref.t_ns) / span
                T = se3.from_rt(so3.exp(a * w_ref), a * T_ref_cur[:3, 3])
                self._anchors.append(Anchor(idx, ref.frame_index, T))
            self._anchors.append(Anchor(frame.index, frame.index, np.eye(4)))
            self._ref = None
        self._optimize_and_marginalize()  # the first solve is synchronous

    def _make_kf(self, frame_index: int, t_ns: int, T_world_kf: np.ndarray, image: np.ndarray) -> _Keyframe:
        kf = _Keyframe(self._next_kf_id, frame_index, t_ns, self._segment,
                       np.array(T_world_kf, dtype=float), image)
        self._next_kf_id += 1
        self.window.append(kf)
        self._last_kf = kf
        self._frames_since_kf = 0
        self.counters["keyframes"] += 1
        return kf

    def _detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        new = self.frontend.detect(gray)
        return new.ids, new.uv_px

    def _snapshot_kf_tracks(self) -> None:
        tr = self.frontend.tracks
        self._kf_track_ids, self._kf_track_uv = tr.ids, tr.uv_px

    # ------------------------------------------------------------------ tracking
    def _process_tracking(self, frame: Frame, gray: np.ndarray) -> PoseEstimate:
        cfg = self.config
        t0 = time.perf_counter()
        n0 = len(self.frontend.ids)
        T_pred = orthonormalized(self._T_world_last @ self._T_last_cur)
        with self._lock:
            T_by_kf = {kf.kf_id: kf.T_world_kf for kf in self.window}
            guess = self.map.predict_pixels(self.frontend.ids, T_by_kf, T_pred)
        self.frontend.track(gray, guess)
        n1 = len(self.frontend.ids)
        with self._lock:
            orphan = [i for i in self.frontend.ids if int(i) not in self.map.landmarks]
        self.frontend.drop(np.array(orphan, dtype=np.int64))
        self.frontend.reject_by_essential(self._kf_track_ids, self._kf_track_uv)
        tracks = self.frontend.tracks
        log.debug("tracks: %d -> klt %d -> orphans %d -> essential %d", n0, n1, n1 - len(orphan),
                  len(tracks))
        t1 = time.perf_counter()
        with self._lock:
            T_by_kf = {kf.kf_id: kf.T_world_kf for kf in self.window}
            mask, p_world = self.map.points_world(tracks.ids, T_by_kf)
        T_world_cam, inl = estimate_pose(T_pred, p_world, tracks.uv_px[mask], self.camera.K,
                                         cfg.huber_px, cfg.pose_iterations)
        t2 = time.perf_counter()
        self.timings_ms["frontend"].append(1e3 * (t1 - t0))
        self.timings_ms["pose"].append(1e3 * (t2 - t1))
        if int(inl.sum()) < cfg.min_tracked_landmarks:
            log.info("frame %d: %d pose inliers < %d: tracking lost", frame.index, int(inl.sum()),
                     cfg.min_tracked_landmarks)
            return self._lose(frame)
        self.frontend.drop(tracks.ids[mask][~inl])
        log.debug("pose: %d with depth, %d inliers", int(mask.sum()), int(inl.sum()))
        self._T_last_cur = se3.inverse(self._T_world_last) @ T_world_cam
        self._T_world_last = T_world_cam
        self._frames_since_kf += 1
        is_kf = self._need_keyframe()
        if is_kf:
            self._add_keyframe(frame, gray, T_world_cam)
            self.timings_ms["keyframe"].append(1e3 * (time.perf_counter() - t2))
        with self._lock:
            kf = self._last_kf
            self._anchors.append(Anchor(frame.index, kf.frame_index,
                                        se3.inverse(kf.T_world_kf) @ T_world_cam))
        return self._estimate(frame, TrackingState.TRACKING, is_kf=is_kf)

    def _need_keyframe(self) -> bool:
        cfg = self.config
        tr = self.frontend.tracks
        common, i_cur, i_kf = np.intersect1d(tr.ids, self._kf_track_ids, return_indices=True)
        if len(common) == 0:
            return True
        motion = float(np.mean(np.linalg.norm(tr.uv_px[i_cur] - self._kf_track_uv[i_kf], axis=1)))
        ratio = len(common) / max(len(self._kf_track_ids), 1)
        log.debug("keyframe check: motion %.1f px, track ratio %.2f, %d frames", motion, ratio,
                  self._frames_since_kf)
        return (motion > cfg.keyframe_motion_px or ratio < cfg.keyframe_min_track_ratio
                or self._frames_since_kf >= cfg.keyframe_max_frames)

    def _add_keyframe(self, frame: Frame, gray: np.ndarray, T_world_cam: np.ndarray) -> None:
        cfg = self.config
        tr = self.frontend.tracks
        with self._lock:
            kf = self._make_kf(frame.index, int(frame.t_ns), T_world_cam, gray)
            fresh, fresh_uv = [], []
            for lid, uv in zip(tr.ids, tr.uv_px):
                lm = self.map.landmarks.get(int(lid))
                if lm is None:
                    continue
                lm.obs[kf.kf_id] = uv.copy()
                if not lm.has_depth and lm.host_kf != kf.kf_id:
                    fresh.append(lm)
                    fresh_uv.append(uv)
            T_by_kf = {k.kf_id: k.T_world_kf for k in self.window}
            if fresh:
                fresh = [lm for lm in fresh if lm.host_kf in T_by_kf]
            if fresh:
                n = len(fresh)
                uv = np.array([lm.obs[kf.kf_id] for lm in fresh])
                rho, par = triangulate_inverse_depth(
                    np.array([T_by_kf[lm.host_kf] for lm in fresh]),
                    np.repeat(T_world_cam[None], n, 0),
                    np.array([lm.bearing for lm in fresh]), self.camera.normalized(uv))
                enough = par >= np.radians(cfg.min_landmark_parallax_deg)
                bad = []
                for lm, r, ok in zip(fresh, rho, enough):
                    if not ok:
                        continue
                    if np.isfinite(r) and r > 0:
                        lm.rho, lm.has_depth = float(r), True
                    else:
                        bad.append(lm.lm_id)
                for lid in bad:
                    del self.map.landmarks[lid]
                self.frontend.drop(np.array(bad, dtype=np.int64))
            new_ids, new_uv = self._detect(gray)
            self.map.add_many(new_ids, kf.kf_id, new_uv)
            self._snapshot_kf_tracks()
        if self._queue is not None:
            self._queue.put("solve")
        else:
            self._optimize_and_marginalize()

    # ------------------------------------------------------------------ back end
    def _worker_loop(self) -> None:
        assert self._queue is not None
        while True:
            item = self._queue.get()
            n_done = 1
            while item != "stop":  # coalesce queued solve requests
                try:
                    nxt = self._queue.get_nowait()
                except queue.Empty:
                    break
                n_done += 1
                if nxt == "stop":
                    item = "stop"
            try:
                if item != "stop":
                    self._optimize_and_marginalize()
            except Exception:  # noqa: BLE001 -- keep the worker alive
                log.exception("window solve failed")
            finally:
                for _ in range(n_done):
                    self._queue.task_done()
            if item == "stop":
                return

    def _wait_idle(self) -> None:
        if self._queue is not None and self._worker is not None and self._worker.is_alive():
            self._queue.join()

    def _window_prior(self, kf_ids: list[int], T: np.ndarray) -> Prior | None:
        """The marginalization prior expanded (zero-padded) to the window's keyframes."""
        if self._prior is None:
            return None
        n = len(kf_ids)
        H = np.zeros((6 * n, 6 * n))
        b = np.zeros(6 * n)
        T_lin = np.array(T, copy=True)
        pos = [kf_ids.index(k) for k in self._prior_ids]
        idx = np.concatenate([np.arange(6 * p, 6 * p + 6) for p in pos])
        H[np.ix_(idx, idx)] = self._prior.H
        b[idx] = self._prior.b
        T_lin[pos] = self._prior.T_lin
        return Prior(H, b, T_lin)

    def _optimize_and_marginalize(self) -> None:
        cfg = self.config
        t0 = time.perf_counter()
        with self._lock:
            kf_ids = [kf.kf_id for kf in self.window]
            T = np.array([kf.T_world_kf for kf in self.window])
            problem, lm_ids = self.map.problem(kf_ids, T, self._window_prior(kf_ids, T))
            generation = self._generation
        if problem.n_landmarks >= 6 and len(kf_ids) >= 2:
            res = bundle_adjust(problem, cfg.huber_px, cfg.ba_iterations, fixed_poses=(0,))
            final = problem.with_values(res.T_world_kf, res.lm_rho)
            err = np.linalg.norm(residuals(final).residual_px, axis=1)
            with self._lock:
                if generation == self._generation:
                    by_id = {kf.kf_id: kf for kf in self.window}
                    for k, Tk in zip(kf_ids, res.T_world_kf):
                        if k in by_id:
                            by_id[k].T_world_kf = Tk
                    outlier = err > 3.0 * cfg.huber_px
                    for j, lid in enumerate(lm_ids):
                        lm = self.map.landmarks.get(lid)
                        if lm is not None:
                            lm.rho = float(res.lm_rho[j])
                    for o in np.nonzero(outlier)[0]:
                        lm = self.map.landmarks.get(lm_ids[problem.obs_lm[o]])
                        if lm is not None:
                            lm.obs.pop(kf_ids[problem.obs_kf[o]], None)
                            if not lm.obs:
                                lm.has_depth = False
                    self.counters["ba_solves"] += 1
            self.timings_ms["ba"].append(1e3 * (time.perf_counter() - t0))
        with self._lock:
            t1 = time.perf_counter()
            while len(self.window) > cfg.window_size:
                self._marginalize_oldest()
            if t1 != time.perf_counter() and self.counters["marginalized"]:
                self.timings_ms["marginalization"].append(1e3 * (time.perf_counter() - t1))

    def _marginalize_oldest(self) -> None:
        """Schur out the oldest keyframe and its children; queue it for the consumer."""
        cfg = self.config
        kf = self.window[0]
        kf_ids = [k.kf_id for k in self.window]
        T = np.array([k.T_world_kf for k in self.window])
        if len(kf_ids) > 1:
            problem, _ = self.map.problem(kf_ids, T, self._window_prior(kf_ids, T),
                                          only_hosts={kf.kf_id})
            self._prior = project_out_gauge(marginalize_pose(problem, 0, cfg.huber_px))
            self._prior_ids = kf_ids[1:]
        else:
            self._prior, self._prior_ids = None, []
        kids = [lm for lm in self.map.children(kf.kf_id) if lm.has_depth and lm.rho > 0]
        prev = self._last_marg.get(kf.segment_id)
        mkf = MarginalizedKeyframe(
            kf_id=kf.kf_id, frame_index=kf.frame_index, t_ns=kf.t_ns, segment_id=kf.segment_id,
            T_vo_kf=kf.T_world_kf.copy(),
            T_prevkf_kf=None if prev is None else se3.inverse(prev) @ kf.T_world_kf,
            landmarks_uv_px=np.array([lm.uv_host_px for lm in kids]).reshape(-1, 2),
            landmarks_inv_depth=np.array([lm.rho for lm in kids], dtype=float),
            image=kf.image, camera=self.camera)
        self._last_marg[kf.segment_id] = kf.T_world_kf.copy()
        self._kf_poses[kf.frame_index] = kf.T_world_kf.copy()
        self.window.pop(0)
        self.map.remove_keyframe(kf.kf_id)
        self._outbox.append(mkf)
        self.counters["marginalized"] += 1

    def _deliver(self) -> None:
        while True:
            with self._lock:
                if not self._outbox:
                    return
                mkf = self._outbox.popleft()
            if self.consumer is not None:
                try:
                    self.consumer.on_keyframe_marginalized(mkf)
                except Exception:  # noqa: BLE001
                    log.exception("keyframe consumer failed on keyframe %d", mkf.kf_id)
