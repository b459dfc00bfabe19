"""Local monocular VO (paper §III-C): KLT frontend + sliding-window BA + marginalization.

:class:`LocalVO` is driven frame by frame through :meth:`LocalVO.process`, which never raises.
Every frame is tracked against the window map by motion-only BA; keyframes are added when the
mean corner motion since the last keyframe exceeds a threshold (or tracks run low); a background
worker then runs windowed LM and marginalizes the oldest keyframe once the window is full
(:mod:`.window`). Marginalized keyframes are queued and handed to the consumer from the thread
that calls ``process`` / ``flush`` (so consumers need no locks).

Every frame is *anchored* to a keyframe (``T_kf_cam``) so that later refinements of keyframe
poses (window BA, global graph) move it too: :meth:`LocalVO.take_anchor_updates` returns the
anchors of newly processed frames. Poses are ``T_world_cam`` in the VO world of the current
segment (first camera of the segment, or the last known pose before a tracking loss).
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets.base import Frame
from metricslam.geometry import se3, sim3
from metricslam.slam.timing import TimingSummary
from metricslam.slam.types import KeyframeConsumer, PoseEstimate, TrackingState
from metricslam.slam.vo.aliasing import SuspectFrames, retrack
from metricslam.slam.vo.ba import orthonormalized
from metricslam.slam.vo.coasting import MotionMemory
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.frontend import KLTFrontend
from metricslam.slam.vo.initializer import InitRef, InitResult, pending_poses, start_confirmed, try_initialize
from metricslam.slam.vo.landmarks import LandmarkMap
from metricslam.slam.vo.motion_only import estimate_pose, relocalize_pnp
from metricslam.slam.vo.frame_check import limit_blas_threads, usable_gray
from metricslam.slam.vo.window import BAWorker, Keyframe, SlidingWindow

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Anchor:
    """Frame ``frame_index`` sits at ``T_kf_cam`` from keyframe frame ``kf_frame_index``."""

    frame_index: int
    kf_frame_index: int
    T_kf_cam: np.ndarray


class LocalVO:
    """Monocular sliding-window VO for one camera.

    Args:
        config: algorithm parameters (:meth:`VOConfig.preset`).
        camera: intrinsics of the incoming images.
        consumer: receives each :class:`~metricslam.slam.types.MarginalizedKeyframe` (e.g. the
            global graph), or None.
    """

    def __init__(self, config: VOConfig, camera: PinholeCamera,
                 consumer: KeyframeConsumer | None = None) -> None:
        self.config = config
        self.camera = camera
        self.consumer = consumer
        self.timings_ms: dict[str, TimingSummary] = defaultdict(TimingSummary)  # constant memory
        self.counters = {"frames": 0, "keyframes": 0, "tracking_losses": 0, "invalid_frames": 0,
                         "marginalized": 0, "ba_solves": 0, "retracks": 0, "retracks_kept": 0}
        self.frontend = KLTFrontend(config, camera)
        self.suspect = SuspectFrames(config.suspect_reject_share)  # frames whose tracks may be aliased
        self.window = SlidingWindow(config, camera, self.counters, self.timings_ms)
        self._lock = self.window.lock  # one lock for the window and the motion state
        self._segment = 0
        self._tracking = False
        self._ref: InitRef | None = None
        self._T_world_last = np.eye(4)
        self._T_last_cur = np.eye(4)  # constant-velocity model
        self._last_kf: Keyframe | None = None
        self._kf_track_ids = np.zeros(0, dtype=np.int64)
        self._kf_track_uv = np.zeros((0, 2))
        self._frames_since_kf = 0
        self._last_pose_inliers = 0  # pose inliers of the previous tracked frame
        self._anchors: list[Anchor] = []
        self._C_pending = np.eye(4)
        self._motion = MotionMemory(config.coast_max_s)  # where a lost camera went (:mod:`.coasting`)
        if config.blas_threads is not None:
            limit_blas_threads(config.blas_threads)
        self._worker = BAWorker(self.window) if config.ba_in_background else None
        self._solve_requested = False  # a background solve started since the last join
        self.window.on_correction = self._follow_window

    @property
    def map(self) -> LandmarkMap:
        """The window's landmarks (read under ``window.lock``)."""
        return self.window.map

    @property
    def segment_id(self) -> int:
        return self._segment

    # ------------------------------------------------------------------ public API
    def process(self, frame: Frame) -> PoseEstimate:
        """Track one frame; never raises (bad input -> INVALID_FRAME, failure -> LOST)."""
        self.counters["frames"] += 1
        try:
            if self.config.ba_joins_next_frame:
                self._join_solve()
            gray = usable_gray(frame.image, self.camera, self.config.min_texture_std)
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
        if self._worker is not None:
            self._worker.wait_idle()
        with self._lock:
            while self.window.keyframes:
                self.window.marginalize_oldest()
        self._deliver()

    def close(self) -> None:
        """Flush and stop the worker thread."""
        self.flush()
        if self._worker is not None:
            self._worker.stop()
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
        return self.window.keyframe_poses()

    def apply_similarity(self, S_new_old: np.ndarray) -> None:
        """Re-express the VO in a world frame related by the Sim(3) ``S_new_old`` (4, 4).

        Moves keyframe poses, landmark inverse depths (÷ s), the last marginalized keyframe's
        pose, the marginalization prior, queued keyframes, the motion model and the current
        pose. Thread-safe: a BA solve started before the warp is discarded.
        """
        with self._lock:
            warp = self.window.apply_similarity(S_new_old, self._segment)
            s = sim3.scale(S_new_old)
            self._T_world_last = warp(self._T_world_last)
            self._T_last_cur = self._T_last_cur.copy()
            self._T_last_cur[:3, 3] *= s
            if self._ref is not None:
                self._ref.T_world_ref = warp(self._ref.T_world_ref)
            self._motion.warp(s)
            S = np.asarray(S_new_old, dtype=float)
            self._C_pending = orthonormalized(S @ self._C_pending @ np.linalg.inv(S))

    def _follow_window(self, C_new_old: np.ndarray) -> None:
        """The newest keyframe moved by ``C_new_old`` in a (background) solve: remember it so
        the tracker moves its poses along (they were estimated against the old map)."""
        self._C_pending = C_new_old @ self._C_pending

    def _take_correction(self) -> np.ndarray | None:
        with self._lock:
            C, self._C_pending = self._C_pending, np.eye(4)
        return None if np.allclose(C, np.eye(4), atol=1e-15) else C

    # ------------------------------------------------------------------ frames
    def _estimate(self, frame: Frame, state: TrackingState, is_kf: bool = False,
                  suspect: bool = False) -> PoseEstimate:
        return PoseEstimate(frame_index=frame.index, t_ns=int(frame.t_ns),
                            T_world_cam=self._T_world_last.copy(), state=state,
                            is_keyframe=is_kf, segment_id=self._segment, vo_suspect=suspect)

    def _lose(self, frame: Frame) -> PoseEstimate:
        """Tracking loss: marginalize the window; a new segment starts where the camera went (:mod:`.coasting`)."""
        self.counters["tracking_losses"] += 1
        self.suspect.interrupt()
        self._motion.lost(self._T_last_cur)  # before the motion model resets below
        try:
            self.flush()
        except Exception:  # noqa: BLE001
            log.exception("flushing the window after a tracking loss failed")
        with self._lock:
            self.window.clear()
            self._tracking = False
            self._ref = None
            self._last_kf = None
            self._segment += 1
            self.frontend.reset()
            self._T_last_cur = np.eye(4)
        return self._estimate(frame, TrackingState.LOST)

    def _deliver(self) -> None:
        while True:
            with self._lock:
                if not self.window.outbox:
                    return
                mkf = self.window.outbox.popleft()
            if self.consumer is not None:
                try:
                    self.consumer.on_keyframe_marginalized(mkf)
                except Exception:  # noqa: BLE001
                    log.exception("keyframe consumer failed on keyframe %d", mkf.kf_id)

    # ------------------------------------------------------------------ initialization
    def _new_reference(self, frame: Frame, gray: np.ndarray) -> None:
        self.frontend.reset()
        self.frontend.track(gray)
        self.frontend.detect(gray)
        tr = self.frontend.tracks
        self._ref = InitRef(frame.index, int(frame.t_ns), gray, tr.ids, tr.uv_px,
                            self._motion.pose_at(self._T_world_last, int(frame.t_ns)), [])

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
                ref.pending.append((frame.index, int(frame.t_ns), tracks.ids, tracks.uv_px))
            return self._estimate(frame, TrackingState.INITIALIZING)
        t1 = time.perf_counter()
        confirmed = self._initialize_map(frame, gray, res)
        self.timings_ms["keyframe"].append(1e3 * (time.perf_counter() - t1))
        return self._estimate(frame, TrackingState.TRACKING, is_kf=True, suspect=not confirmed)

    def _initialize_map(self, frame: Frame, gray: np.ndarray, res: InitResult) -> bool:  # False: not confirmed
        ref = self._ref
        # keep the scale of the previous segment when there was one: baseline = speed x frames,
        # the speed when tracking was lost (the motion model restarts at rest then)
        speed = self._motion.step_at_loss
        n_frames = max(frame.index - ref.frame_index, 1)
        baseline = speed * n_frames if speed > 0 else 1.0
        T_ref_cur = res.T_ref_cur.copy()
        T_ref_cur[:3, 3] *= baseline
        T_world_cur = ref.T_world_ref @ T_ref_cur
        poses = pending_poses(self.camera, self.config, ref, res, T_ref_cur, int(frame.t_ns))  # frames between
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
            new = self.frontend.detect(gray)
            self.map.add_many(new.ids, kf1.kf_id, new.uv_px)
            self._snapshot_kf_tracks()
            self._tracking = True
            self._T_world_last = T_world_cur
            self._last_pose_inliers = 0  # a new segment: nothing to compare the next frame with
            self._T_last_cur = np.eye(4)
            self._T_last_cur[:3, 3] = T_ref_cur[:3, 3] / n_frames
            self._motion.started(int(frame.t_ns))
            # frames between the two views: posed against the two-view points (else interpolated)
            self._anchors.append(Anchor(ref.frame_index, ref.frame_index, np.eye(4)))
            self._anchors.extend(Anchor(idx, ref.frame_index, T) for idx, T, _ in poses)
            self._anchors.append(Anchor(frame.index, frame.index, np.eye(4)))
            self._ref = None
        confirmed = start_confirmed(self.config, poses, ref.frame_index, frame.index)
        if not confirmed:
            self.suspect.mark(ref.frame_index, frame.index)
        self.window.optimize_and_marginalize()  # the first solve is synchronous
        return confirmed

    def _make_kf(self, frame_index: int, t_ns: int, T_world_kf: np.ndarray, image: np.ndarray) -> Keyframe:
        kf = self.window.add_keyframe(frame_index, t_ns, self._segment, T_world_kf, image)
        self._last_kf = kf
        self._frames_since_kf = 0
        return kf

    def _snapshot_kf_tracks(self) -> None:
        tr = self.frontend.tracks
        self._kf_track_ids, self._kf_track_uv = tr.ids, tr.uv_px

    # ------------------------------------------------------------------ tracking
    def _process_tracking(self, frame: Frame, gray: np.ndarray) -> PoseEstimate:
        cfg = self.config
        t0 = time.perf_counter()
        C = self._take_correction()
        if C is not None:
            self._T_world_last = orthonormalized(C @ self._T_world_last)
        T_pred = orthonormalized(self._T_world_last @ self._T_last_cur)
        with self._lock:
            T_by_kf = self.window.poses_by_kf()
            guess = self.map.predict_pixels(self.frontend.ids, T_by_kf, T_pred)
        self.frontend.track(gray, guess)
        share = self._check_tracks()
        if share > cfg.retrack_reject_share and guess is not None:  # tracks may be aliased
            share = retrack(self.frontend, gray, share, self._check_tracks, self.counters)
        suspect = self.suspect.update(frame.index, share)
        tracks = self.frontend.tracks
        t1 = time.perf_counter()
        with self._lock:
            mask, p_world = self.map.points_world(tracks.ids, self.window.poses_by_kf())
        T_world_cam, inl = estimate_pose(T_pred, p_world, tracks.uv_px[mask], self.camera.K,
                                         cfg.huber_px, cfg.pose_iterations)
        collapsed = int(inl.sum()) < cfg.pose_collapse_ratio * self._last_pose_inliers
        if int(inl.sum()) < cfg.min_tracked_landmarks or collapsed:  # sudden motion: no prediction
            found = relocalize_pnp(p_world, tracks.uv_px[mask], self.camera.K, cfg.huber_px,
                                   cfg.pose_iterations)
            if found is not None and int(found[1].sum()) > int(inl.sum()):
                T_world_cam, inl = found
        t2 = time.perf_counter()
        self.timings_ms["frontend"].append(1e3 * (t1 - t0))
        self.timings_ms["pose"].append(1e3 * (t2 - t1))
        if int(inl.sum()) < cfg.min_tracked_landmarks:
            log.info("frame %d: %d pose inliers < %d: tracking lost", frame.index, int(inl.sum()),
                     cfg.min_tracked_landmarks)
            return self._lose(frame)
        self._last_pose_inliers = int(inl.sum())
        self.frontend.drop(tracks.ids[mask][~inl])
        C = self._take_correction()  # a solve finished while this frame was tracked
        if C is not None:
            self._T_world_last = orthonormalized(C @ self._T_world_last)
            T_world_cam = orthonormalized(C @ T_world_cam)
        self._T_last_cur = se3.inverse(self._T_world_last) @ T_world_cam
        self._motion.tracked(self._T_last_cur, int(frame.t_ns))
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
        return self._estimate(frame, TrackingState.TRACKING, is_kf=is_kf, suspect=suspect)

    def _check_tracks(self) -> float:
        """Drop tracks without a landmark and those the essential check rejects; the share rejected."""
        with self._lock:  # tracks whose landmark left with a marginalized keyframe
            orphan = [i for i in self.frontend.ids.tolist() if i not in self.map.landmarks]
        self.frontend.drop(np.array(orphan, dtype=np.int64))
        bad, n_checked = self.frontend.reject_by_essential(self._kf_track_ids, self._kf_track_uv)
        return len(bad) / n_checked if n_checked else 0.0

    def _need_keyframe(self) -> bool:
        """Paper's rule: mean pixel motion since the last keyframe; plus low track survival."""
        cfg = self.config
        tr = self.frontend.tracks
        common, i_cur, i_kf = np.intersect1d(tr.ids, self._kf_track_ids, return_indices=True)
        if len(common) == 0:
            return True
        motion = float(np.mean(np.linalg.norm(tr.uv_px[i_cur] - self._kf_track_uv[i_kf], axis=1)))
        ratio = len(common) / max(len(self._kf_track_ids), 1)
        return (motion > cfg.keyframe_motion_px or ratio < cfg.keyframe_min_track_ratio
                or self._frames_since_kf >= cfg.keyframe_max_frames)

    def _join_solve(self) -> None:
        """Wait for the window solve the last keyframe started, if any (``ba_joins_next_frame``
        at every frame, ``keyframe_waits_for_ba`` at a keyframe): at most one in flight."""
        if self._worker is not None and self._solve_requested:
            t0 = time.perf_counter()
            self._worker.wait_idle()
            self._solve_requested = False
            self.timings_ms["ba_wait"].append(1e3 * (time.perf_counter() - t0))

    def _add_keyframe(self, frame: Frame, gray: np.ndarray, T_world_cam: np.ndarray) -> None:
        if self.config.keyframe_waits_for_ba:
            self._join_solve()
        tr = self.frontend.tracks
        with self._lock:
            kf = self._make_kf(frame.index, int(frame.t_ns), T_world_cam, gray)
            bad = self.window.observe(kf, tr.ids, tr.uv_px)
            self.frontend.drop(bad)
            new = self.frontend.detect(gray)
            self.map.add_many(new.ids, kf.kf_id, new.uv_px)
            self._snapshot_kf_tracks()
        if self._worker is not None:
            self._worker.request()
            self._solve_requested = True
        else:
            self.window.optimize_and_marginalize()
