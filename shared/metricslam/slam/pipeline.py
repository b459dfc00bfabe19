"""``SlamPipeline``: local VO + optional global back end, as one :class:`SlamSession`.

The pipeline only orchestrates: frames go to :class:`~metricslam.slam.vo.local_vo.LocalVO`;
marginalized keyframes go to the back end; after every frame the back end's correction (a Sim(3)
"warp", paper §III-D) is applied to the VO so the newest pose is metric. Every frame is anchored
to a keyframe (``T_kf_cam``) so :meth:`SlamPipeline.trajectory` gives each frame its current best
pose: ``S_world_kf`` from the back end for marginalized keyframes (rotation ``R_world_kf·R_kf_cam``,
position ``S_world_kf · t_kf_cam``, ``docs/conventions.md``), else the VO's keyframe pose.
The scale estimate over time (live warp scale, optimized per-keyframe scale) is recorded in a
:class:`~metricslam.slam.scale_history.ScaleHistory` (:meth:`SlamPipeline.scale_history`).

With ``InitialScaleConfig.enabled`` (the live service), the frame on which the VO first has a map
waits (bounded) for the depth source's answer on the initial keyframe and the VO is warped to the
provisional metric scale it gives (:mod:`metricslam.slam.initial_scale`), so the first published
pose is already metric-ish. Every pose says what its scale rests on (``PoseEstimate.scale_state``:
unscaled / provisional / metric, and the graph's scale factor count).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import Counter, defaultdict

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets.base import Frame
from metricslam.geometry import sim3, so3
from metricslam.slam.events import InitialScaleApplied, KeyframeMarginalized, KeyframeSettled
from metricslam.slam.initial_scale import InitialScale, InitialScaleConfig, measure_initial_scale
from metricslam.slam.pose_gaps import fill_pose_gaps
from metricslam.slam.scale_history import ScaleHistory
from metricslam.slam.timing import TimingSummary
from metricslam.slam.types import Backend, MarginalizedKeyframe, PoseEstimate, ScaleState, TrackingState
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.local_vo import LocalVO

log = logging.getLogger(__name__)


class SlamPipeline:
    """Implements :class:`metricslam.slam.types.SlamSession`.

    Args:
        camera: intrinsics of the incoming frames.
        vo_config: local VO parameters.
        backend: the global back end (``metricslam.slam.backend_factory.make_backend``), or
            None for VO only (poses in the VO's arbitrary monocular scale).
        scale_history: recorder of the scale estimate (a fresh one when None); attach it to
            the back end's events (:meth:`~metricslam.slam.scale_history.ScaleHistory.attach`)
            to also record each keyframe's learned scale measurements (``build_session`` does).
        initial_scale: the initial scale step (off when None or not ``enabled``); it asks the
            back end's ``depth_source`` and uses its ``config`` (a ``GraphConfig``) filters.
    """

    def __init__(self, camera: PinholeCamera, vo_config: VOConfig | None = None,
                 backend: Backend | None = None, scale_history: ScaleHistory | None = None,
                 initial_scale: InitialScaleConfig | None = None) -> None:
        self.camera = camera
        self.backend = backend
        #: the scale sources in use and the mounting height (``build_session`` sets it; stats)
        self.scale_info: dict | None = None
        self.vo = LocalVO(vo_config or VOConfig(), camera, consumer=self)
        self._lock = threading.Lock()
        self._estimates: list[PoseEstimate] = []
        # frame_index -> [kf_frame_index, T_kf_cam (4, 4) in the VO units of that keyframe]
        self._anchors: dict[int, list] = {}
        self._marginalized: set[int] = set()
        # frame_index -> (S_world_kf bytes, T_kf_cam, T_world_cam) of the last trajectory() call:
        # a live caller asks after every keyframe, and most keyframes have not moved since
        self._composed: dict[int, tuple[bytes, np.ndarray, np.ndarray]] = {}
        self._timings_ms: dict[str, TimingSummary] = defaultdict(TimingSummary)
        self._corrections = 0
        self._scale_history = scale_history if scale_history is not None else ScaleHistory()
        self._closed = False
        self._initial_config = initial_scale or InitialScaleConfig()
        self._initial_pending = backend is not None and self._initial_config.enabled
        self._initial: InitialScale | None = None
        self._scale_states: Counter = Counter()
        self._first_metric_frame: int | None = None
        self._frame_now = -1  # the frame being processed (KeyframeMarginalized events)
        self._settled_kf_id = -1  # the newest keyframe a KeyframeSettled event was emitted for

    @property
    def frame_now(self) -> int:
        """Index of the frame being processed (or the last one; -1 before the first)."""
        return self._frame_now

    # -- KeyframeConsumer (called by the VO from this pipeline's thread) -----------------------
    def on_keyframe_marginalized(self, kf: MarginalizedKeyframe) -> None:
        self._marginalized.add(kf.frame_index)
        self._scale_history.on_keyframe(kf)
        if self.backend is not None:
            events = getattr(self.backend, "events", None)
            if events is not None:
                events.emit(KeyframeMarginalized(kf, self._frame_now))
            t0 = time.perf_counter()
            self.backend.on_keyframe_marginalized(kf)
            self._timings_ms["backend_handoff"].append(1e3 * (time.perf_counter() - t0))

    def _emit_settled(self) -> None:
        events = getattr(self.backend, "events", None)
        if events is None or not events.wants(KeyframeSettled):
            return
        snapshots, generation = self.vo.window.settled_after(self._settled_kf_id)
        for kf in snapshots:
            self._settled_kf_id = kf.kf_id
            events.emit(KeyframeSettled(kf, self._frame_now, generation))

    # -- SlamSession --------------------------------------------------------------------------
    def process(self, frame: Frame) -> PoseEstimate:
        """Track one frame, feed the back end, apply its correction. Never raises on bad input."""
        t0 = time.perf_counter()
        self._frame_now = int(frame.index)
        est = self.vo.process(frame)
        self._collect_anchors()
        self._emit_settled()
        scale_ok, n_factors = False, 0
        if self.backend is not None:
            try:
                if self._initial_pending and est.state is TrackingState.TRACKING:
                    est = self._initial_scale_step(est)
                S_new_vo = self.backend.take_correction()
                if S_new_vo is not None:
                    self._apply_correction(S_new_vo)
                    self._scale_history.on_correction(frame.index, frame.t_ns, sim3.scale(S_new_vo))
                    est = self._rewarp(est, S_new_vo)
                scale_ok = bool(self.backend.scale_established)
                n_factors = int(getattr(self.backend, "scale_factors_solved", 0))
            except Exception:  # noqa: BLE001 -- a back-end failure must not stop tracking
                log.exception("back end failed after frame %d", frame.index)
                scale_ok = False
        est = dataclasses.replace(est, scale_established=scale_ok,
                                  scale_state=self._scale_state(scale_ok, n_factors),
                                  scale_factors=n_factors)
        self._scale_states[est.scale_state.value] += 1
        if est.scale_state is ScaleState.METRIC and self._first_metric_frame is None:
            self._first_metric_frame = int(est.frame_index)
        with self._lock:
            self._estimates.append(est)
        self._timings_ms["total"].append(1e3 * (time.perf_counter() - t0))
        return est

    def trajectory(self) -> list[PoseEstimate]:
        """Best pose of every processed frame, in frame order (see module docstring).

        A frame the VO anchored to a keyframe has a pose of its own. One without (invalid or
        unreadable input, a tracking loss, an initialization attempt given up) would otherwise
        keep the VO's pose of the moment, in a VO frame that later warps left behind; instead
        it is interpolated at its ``t_ns`` between the nearest frames before and after it that
        have a pose (``interpolated=True``), when both poses are in one world frame: the same
        segment, or both from the global graph (which links each new segment to the previous
        one). Otherwise it gets a placeholder and ``pose_valid=False``: before the first frame
        with a pose, the VO's pose of the moment (the VO world's origin, where the first
        keyframe sits); after the last one, that frame's pose; between two unrelated segments,
        the neighbour in its own segment.
        """
        self._collect_anchors()
        kf_vo = self.vo.keyframe_poses()
        kf_global = self.backend.optimized_keyframe_poses() if self.backend is not None else {}
        out = []
        own: list[bool] = []  # has a pose of its own (an anchor)
        in_graph: list[bool] = []  # ... and it comes from the global graph
        with self._lock:
            for est in self._estimates:
                anchor = self._anchors.get(est.frame_index)
                T = est.T_world_cam
                from_graph = False
                if anchor is not None:
                    kf_index, T_kf_cam = anchor
                    if kf_index in kf_global:
                        T = self._compose_cached(est.frame_index, kf_global[kf_index], T_kf_cam)
                        from_graph = True
                    elif kf_index in kf_vo:
                        T = kf_vo[kf_index] @ T_kf_cam
                out.append(dataclasses.replace(est, T_world_cam=T))
                own.append(anchor is not None)
                in_graph.append(from_graph)
        return fill_pose_gaps(out, own, in_graph, getattr(self.backend, "relinked_segments", frozenset()))

    def stats(self) -> dict:
        """Frames, keyframes, tracking losses and mean ms per frame of each stage."""
        c = dict(self.vo.counters)
        n = max(c["frames"], 1)
        per_frame, per_call = {}, {}
        for k, v in {**self.vo.timings_ms, **self._timings_ms}.items():
            per_frame[k] = v.total_ms / n
            if len(v):
                per_call[k] = v.mean_ms
        out = {"frames": c["frames"], "keyframes": c["keyframes"],
               "tracking_losses": c["tracking_losses"], "invalid_frames": c["invalid_frames"],
               "marginalized_keyframes": c["marginalized"], "ba_solves": c["ba_solves"],
               "retracks": c["retracks"], "retracks_kept": c["retracks_kept"],
               "vo_suspect_frames": self.vo.suspect.count,
               "vo_suspect_ranges": [list(r) for r in self.vo.suspect.ranges],
               "corrections_applied": self._corrections,
               "scale_states": {s.value: self._scale_states.get(s.value, 0) for s in ScaleState},
               "first_metric_frame": self._first_metric_frame,
               "initial_scale": None if self._initial is None else self._initial.as_dict(),
               "ms_per_frame": per_frame, "ms_per_call": per_call}
        if self.scale_info is not None:
            out["scale"] = dict(self.scale_info)
        if self.backend is not None and hasattr(self.backend, "stats"):
            try:
                out["backend"] = self.backend.stats()
            except Exception:  # noqa: BLE001
                log.exception("back end stats failed")
        return out

    def window_landmarks_world(self) -> np.ndarray:
        """(N, 3) depth-known landmarks of the local window in the VO world frame (which the
        warps keep metric) — what the viewers and the ROS 2 / MCAP outputs draw."""
        with self.vo.window.lock:
            lm_ids = np.array(list(self.vo.map.landmarks), dtype=np.int64)
            _, points = self.vo.map.points_world(lm_ids, self.vo.keyframe_poses())
        return np.asarray(points, dtype=np.float64).reshape(-1, 3)

    def scale_history(self) -> dict:
        """The scale estimate over time (JSON-ready; units in :mod:`metricslam.slam.scale_history`).

        Returns:
            ``{"scale_history": [...], "scale_corrections": [...]}``: one dict per marginalized
            keyframe (``frame_index``, ``t_ns``, live warp scale ``scale_live`` when it was
            marginalized, final optimized ``scale_kf_optimized`` / ``scale_optimized``, learned
            ``scale_factors`` count and ``scale_measured_median`` ξ/z, VO ``step_vo``) and one
            per applied warp (``frame_index``, ``t_ns``, ``s``, running product ``scale_live``).
            Scales are world units per VO unit: metres in metric mode, the first keyframe's VO
            units with ``--no-scale``/``--vo-only``.
        """
        kf_global = self.backend.optimized_keyframe_poses() if self.backend is not None else None
        return {"scale_history": self._scale_history.keyframes(kf_global),
                "scale_corrections": self._scale_history.corrections()}

    def close(self) -> None:
        """Marginalize the remaining window into the back end, finish it, stop workers."""
        if self._closed:
            return
        self._closed = True
        self.vo.close()
        self._collect_anchors()
        if self.backend is not None:
            self.backend.close()

    # -- internals ----------------------------------------------------------------------------
    def _compose_cached(self, frame_index: int, S_world_kf: np.ndarray, T_kf_cam: np.ndarray) -> np.ndarray:
        """:func:`_compose_sim3_rigid`, reused from the previous :meth:`trajectory` call while
        the frame's keyframe pose and anchor are unchanged (same bytes, same anchor array): a
        live session asks after every keyframe, and its cost was O(frames) SVDs (~40 ms at
        1,100 frames, on the tracking thread). Exactly the same result either way."""
        key = np.ascontiguousarray(S_world_kf).tobytes()
        hit = self._composed.get(frame_index)
        if hit is not None and hit[1] is T_kf_cam and hit[0] == key:
            return hit[2]
        T = _compose_sim3_rigid(S_world_kf, T_kf_cam)
        T.flags.writeable = False  # shared with the caller of every later call that reuses it
        self._composed[frame_index] = (key, T_kf_cam, T)
        return T

    def _collect_anchors(self) -> None:
        for a in self.vo.take_anchor_updates():
            self._anchors[a.frame_index] = [a.kf_frame_index, a.T_kf_cam]

    def _apply_correction(self, S_new_vo: np.ndarray) -> None:
        self._warp_vo(S_new_vo)
        self._corrections += 1

    def _warp_vo(self, S_new_vo: np.ndarray) -> None:
        self.vo.apply_similarity(S_new_vo)
        s = sim3.scale(S_new_vo)
        # anchors to keyframes still in the VO are in VO units, which just changed by s
        for anchor in self._anchors.values():
            if anchor[0] not in self._marginalized:
                T = anchor[1].copy()
                T[:3, 3] *= s
                anchor[1] = T

    def _scale_state(self, scale_ok: bool, n_factors: int) -> ScaleState:
        if scale_ok:
            return ScaleState.METRIC
        if n_factors > 0 or (self._initial is not None and self._initial.scale is not None):
            return ScaleState.PROVISIONAL
        return ScaleState.UNSCALED

    def _initial_scale_step(self, est: PoseEstimate) -> PoseEstimate:
        """The VO has its first map (this frame): measure the initial keyframe's metric scale and
        warp the VO to it (:mod:`metricslam.slam.initial_scale`). Only before any keyframe has
        reached the back end, whose units must not change behind its back."""
        self._initial_pending = False
        source = getattr(self.backend, "depth_source", None)
        kf = self._initial_keyframe() if not self._marginalized else None
        if kf is None:
            self._initial = InitialScale(int(est.frame_index), None, 0, 0.0,
                                         "no initial keyframe left in the VO window")
        else:
            graph_config = getattr(self.backend, "config", None)
            if graph_config is None:
                from metricslam.slam.graph.config import GraphConfig

                graph_config = GraphConfig()
            kf_frame, image, uv, xi = kf
            self._initial = measure_initial_scale(source, image, self.camera, uv, xi, kf_frame,
                                                  self._initial_config, graph_config)
        if self._initial.scale is None:
            log.warning("no initial metric scale at frame %d (%s): poses stay unscaled until the "
                        "global graph has learned scale factors", est.frame_index, self._initial.error)
            return est
        S = np.eye(4)
        S[:3, :3] *= self._initial.scale
        self._warp_vo(S)
        self._scale_history.on_correction(est.frame_index, est.t_ns, self._initial.scale)
        events = getattr(self.backend, "events", None)
        if events is not None:
            events.emit(InitialScaleApplied(self._initial.frame_index, int(est.frame_index),
                                            self._initial.scale, self._initial.n_landmarks,
                                            self._initial.wait_ms))
        log.info("initial metric scale %.4g m per VO unit from %d landmarks of frame %d (waited "
                 "%.0f ms)", self._initial.scale, self._initial.n_landmarks,
                 self._initial.frame_index, self._initial.wait_ms)
        return self._rewarp(est, S)

    def _initial_keyframe(self) -> tuple[int, np.ndarray, np.ndarray, np.ndarray] | None:
        """``(frame_index, image, landmark pixels (M, 2), VO inverse depths (M,))`` of the VO
        window's oldest keyframe (the initialization's reference), or None."""
        window = self.vo.window
        with window.lock:
            if not window.keyframes:
                return None
            kf = window.keyframes[0]
            kids = [lm for lm in self.vo.map.children(kf.kf_id) if lm.has_depth and lm.rho > 0]
            uv = np.array([lm.uv_host_px for lm in kids], dtype=float).reshape(-1, 2)
            xi = np.array([lm.rho for lm in kids], dtype=float)
            return int(kf.frame_index), kf.image, uv, xi

    @staticmethod
    def _rewarp(est: PoseEstimate, S_new_vo: np.ndarray) -> PoseEstimate:
        return dataclasses.replace(est, T_world_cam=_compose_sim3_rigid(S_new_vo, est.T_world_cam))


def _compose_sim3_rigid(S_world_kf: np.ndarray, T_kf_cam: np.ndarray) -> np.ndarray:
    """Rigid ``T_world_cam``: rotation ``R_world_kf·R_kf_cam``, position ``S_world_kf·t_kf_cam``."""
    A = np.asarray(S_world_kf, dtype=float)
    s = sim3.scale(A)
    R, t = so3.project_to_so3(A[:3, :3] / s), A[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R @ T_kf_cam[:3, :3]
    out[:3, 3] = s * R @ T_kf_cam[:3, 3] + t
    return out


def window_landmarks_world(session: object) -> np.ndarray | None:
    """:meth:`SlamPipeline.window_landmarks_world` of any session that has a local window, else None
    (e.g. the service's identity sessions)."""
    method = getattr(session, "window_landmarks_world", None)
    return method() if method is not None else None
