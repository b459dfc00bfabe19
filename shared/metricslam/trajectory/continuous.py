"""A continuous metric odometry stream beside the SLAM's live poses (REP 105's map → odom split).

The live pose of a frame (``PoseEstimate.T_world_cam``) jumps by metres when the back end's
warp lands or the scale state changes (the whole VO world is moved by a Sim(3) ``S_new_old``). A
controller cannot use that. :class:`ContinuousOdometry` is an *observer* of the live stream that
gives, for every frame::

    T_world_cam_cont = T_world_odom · T_odom_cam

* ``T_odom_cam`` — odometry: the camera in a frame ``odom`` that moves only by the frame-to-frame
  motion of the live poses. Between corrections ``T_odom_cam = D⁻¹ · T_world_cam_live`` for a
  fixed rigid ``D`` (so it is exactly the live pose re-anchored, with no drift of its own). When
  a correction ``S_new_old`` lands between frames ``k-1`` and ``k``, the motion ``k-1 → k`` is
  taken from the pair ``(S_new_old ⊙ T_{k-1}, T_k)``: the pre-correction pair with its
  translation in the corrected units (``⊙``: the rigid part of ``S·T``, positions scaled, as the
  pipeline re-warps poses), and ``D`` is re-anchored so that motion is kept. A new tracking
  segment (its relative motion is unknown) re-anchors ``D`` with zero motion for that frame.
* ``T_world_odom`` — the correction: it moves from where it was to the target ``D`` along the
  SE(3) geodesic, linearly in time, reaching it ``horizon_s`` after the latest re-anchoring. So
  the output converges to the live pose within ``horizon_s`` of the last correction, and it is
  *identical* to the live pose (bit for bit) when no correction ever happens (``D = I``).

The correction's per-frame share is its size · ``dt / horizon``: a 5 m jump blended over 2 s
at 10 Hz adds at most 0.25 m to one frame's step. A correction too large for that (the first
metric scale can move a camera by tens of metres) is blended more slowly, no faster than
``max_correction_share`` of the camera's own speed (at most ``max_horizon_s``), so the stream's
steps stay within ``1 + max_correction_share`` times the odometry's
(``docs/history/rule_continuous_rate_limit_session19.md``). Frames without a tracked pose of their own
(initializing, lost, invalid) hold the odometry (zero twist); the correction keeps blending.

Corrections are learned from the back end's typed events (:meth:`ContinuousOdometry.attach`:
:class:`~metricslam.slam.events.WarpApplied` and
:class:`~metricslam.slam.events.InitialScaleApplied`, both emitted on the tracking thread inside
``process`` before it returns the pose they moved), never by wrapping the estimator: observing
changes nothing it estimates. Frames, tangents and units: ``docs/conventions.md`` (tangent
``[ω, v]``, right perturbation); positions and linear velocities are in the live stream's world
units (metres once the scale state is ``metric``).

Example::

    session = build_session(camera, config)
    odom = ContinuousOdometry(ContinuousOdometryConfig(horizon_s=2.0))
    odom.attach(session)
    for frame in frames:
        cont = odom.update(session.process(frame))   # cont.T_world_cam, cont.twist_cam
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from metricslam.geometry import se3, sim3, so3
from metricslam.slam.events import InitialScaleApplied, WarpApplied
from metricslam.slam.types import PoseEstimate, ScaleState, TrackingState


class ContinuousOdometryConfig(BaseModel):
    """Options of :class:`ContinuousOdometry`.

    Attributes:
        horizon_s: a correction is fully blended in this long after it landed (s), at least.
        max_correction_share: a large correction is blended no faster than this share of the
            odometry's own speed at the frame it landed, so a step of the stream stays within
            ``1 + share`` times the odometry's step; the blend then takes longer than ``horizon_s``.
        max_horizon_s: the longest a blend may take (s); a camera standing still gets this.
        nominal_dt_s: frame period assumed when two frames' ``t_ns`` do not increase (s).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    horizon_s: float = Field(default=2.0, gt=0)
    max_correction_share: float = Field(default=0.5, gt=0)
    max_horizon_s: float = Field(default=10.0, gt=0)
    nominal_dt_s: float = Field(default=0.1, gt=0)


@dataclass(frozen=True)
class ContinuousPose:
    """One frame of the continuous stream.

    Attributes:
        frame_index, t_ns, state, segment_id, scale_state, scale_factors: those of the live pose.
        T_world_cam: (4, 4) continuous camera-to-world (``T_world_odom · T_odom_cam``).
        T_world_odom: (4, 4) the blended correction (rigid; identity while none happened).
        T_odom_cam: (4, 4) the odometry pose (rigid).
        twist_cam: (6,) ``[ω rad/s, v units/s]`` of the odometry motion since the previous frame,
            in the camera frame (``Log(T_odom_cam_prev⁻¹ T_odom_cam) / dt``); zeros when held.
        correction_m, correction_rad: what is still to blend in at the camera: the distance and
            angle between this pose and the live one (0 once converged).
        blend_until_t_ns: when the current correction will be fully in (the live ``t_ns`` clock).
    """

    frame_index: int
    t_ns: int
    state: TrackingState
    segment_id: int
    scale_state: ScaleState
    scale_factors: int
    T_world_cam: np.ndarray
    T_world_odom: np.ndarray
    T_odom_cam: np.ndarray
    twist_cam: np.ndarray
    correction_m: float
    correction_rad: float
    blend_until_t_ns: int


def apply_sim3_rigid(S_new_old: np.ndarray, T_old_cam: np.ndarray) -> np.ndarray:
    """The rigid pose ``T_new_cam`` a world warp ``S_new_old`` (4, 4 Sim(3)) gives ``T_old_cam``:
    rotation ``R_S · R``, position ``S · t`` (what the pipeline does to the live pose)."""
    S = np.asarray(S_new_old, dtype=float)
    s = sim3.scale(S)
    R_S = so3.project_to_so3(S[:3, :3] / s)
    T = np.asarray(T_old_cam, dtype=float)
    out = np.eye(4)
    out[:3, :3] = R_S @ T[:3, :3]
    out[:3, 3] = s * (R_S @ T[:3, 3]) + S[:3, 3]
    return out


def _rigid(T: np.ndarray) -> np.ndarray:
    out = np.array(T, dtype=float)
    out[:3, :3] = so3.project_to_so3(out[:3, :3])
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


class ContinuousOdometry:
    """The continuous stream's state for one camera (module docstring). Not a thread pool: feed
    it from the thread that runs ``process`` (events arrive there too); a lock guards it anyway."""

    def __init__(self, config: ContinuousOdometryConfig | None = None) -> None:
        self.config = config or ContinuousOdometryConfig()
        self._lock = threading.Lock()
        self._started = False
        self._D = np.eye(4)                 # T_world_odom target: live = D · T_odom_cam
        self._B0 = np.eye(4)                # T_world_odom when the current blend started
        self._xi_blend = np.zeros(6)        # Log(B0⁻¹ D)
        self._t0_ns = 0                     # blend start
        self._blend_end_ns = 0
        self._T_world_odom = np.eye(4)
        self._T_odom_cam = np.eye(4)
        self._T_last_live: np.ndarray | None = None  # latest tracked live pose, warped since
        self._last_t_ns: int | None = None
        self._last_segment: int | None = None
        self._speed = 0.0                   # odometry speed at the latest tracked frame (units/s)
        self._pending = False               # a correction landed since the latest tracked pose
        self._outer: Any = None             # session whose T_world_origin maps inner warps
        self.corrections = 0
        self.reanchors = 0

    # -- corrections ------------------------------------------------------------------------
    def attach(self, session: Any) -> bool:
        """Subscribe to ``session.backend.events`` (warps and the initial scale); False when the
        session has no back end (VO only: nothing ever corrects it). A session that maps its
        inner world into an earlier one (``T_world_origin``, the SLAM service's continued
        sessions) has its inner warps conjugated into the outer world."""
        backend = getattr(session, "backend", None)
        events = getattr(backend, "events", None)
        if events is None:
            return False
        self._outer = session if getattr(session, "T_world_origin", None) is not None else None
        events.subscribe(self._on_event, WarpApplied, InitialScaleApplied)
        return True

    def _on_event(self, event: Any) -> None:
        if isinstance(event, WarpApplied):
            S = np.asarray(event.S_new_vo, dtype=float)
        else:  # InitialScaleApplied: the VO world is scaled about its origin
            S = np.eye(4)
            S[:3, :3] *= float(event.scale)
        if self._outer is not None:
            T_wo = np.asarray(self._outer.T_world_origin, dtype=float)
            S = T_wo @ S @ se3.inverse(T_wo)
        self.on_correction(S)

    def on_correction(self, S_new_old: np.ndarray) -> None:
        """The live world was just warped by ``S_new_old`` (4, 4 Sim(3), old world -> new); the
        next pose given to :meth:`update` is in the new world."""
        with self._lock:
            self.corrections += 1
            if self._T_last_live is not None:
                self._T_last_live = apply_sim3_rigid(S_new_old, self._T_last_live)
                self._pending = True

    # -- the stream -------------------------------------------------------------------------
    def update(self, est: PoseEstimate) -> ContinuousPose:
        """The continuous pose of the live pose ``est`` (call once per processed frame, in order)."""
        with self._lock:
            return self._update(est)

    def _update(self, est: PoseEstimate) -> ContinuousPose:
        t_ns = int(est.t_ns)
        dt_s = self.config.nominal_dt_s
        if self._last_t_ns is not None and t_ns > self._last_t_ns:
            dt_s = (t_ns - self._last_t_ns) / 1e9
        tracked = est.state is TrackingState.TRACKING and est.pose_valid
        T_live = np.array(est.T_world_cam, dtype=np.float64)  # as is: no correction -> bit for bit
        twist = np.zeros(6)
        if not self._started:
            if not tracked:  # nothing to be continuous with yet: the live pose, as it is
                self._last_t_ns = t_ns
                return self._emit(est, T_live, np.eye(4), T_live, twist, 0.0, 0.0, t_ns)
            self._started = True
            self._T_odom_cam = T_live  # D = I: the output IS the live pose until a correction
        elif tracked:
            T_prev_odom = self._T_odom_cam
            if est.segment_id != self._last_segment or self._T_last_live is None:
                # relative motion unknown across a new segment: hold for this frame
                self._reanchor(T_live @ se3.inverse(T_prev_odom), t_ns)
            elif self._pending:
                T_rel = se3.inverse(self._T_last_live) @ T_live
                self._T_odom_cam = _rigid(T_prev_odom @ T_rel)
                self._speed = float(np.linalg.norm(T_rel[:3, 3])) / dt_s  # in the corrected units
                self._reanchor(T_live @ se3.inverse(self._T_odom_cam), t_ns)
            else:
                self._T_odom_cam = se3.inverse(self._D) @ T_live if self.reanchors else T_live
            twist = se3.log(_rigid(se3.inverse(T_prev_odom) @ self._T_odom_cam)) / dt_s
            self._speed = float(np.linalg.norm(twist[3:]))
        if tracked:
            self._T_last_live = T_live
            self._last_segment = est.segment_id
            self._pending = False
        self._T_world_odom = self._blend(t_ns)
        self._last_t_ns = t_ns
        T_cont = self._T_world_odom @ self._T_odom_cam
        # what is left to blend in, at the camera (the live pose is D · T_odom_cam)
        E = se3.inverse(T_cont) @ (self._D @ self._T_odom_cam)
        return self._emit(est, T_cont, self._T_world_odom, self._T_odom_cam, twist,
                          float(np.linalg.norm(E[:3, 3])), so3.angle(so3.project_to_so3(E[:3, :3])),
                          self._blend_end_ns)

    def _reanchor(self, D_new: np.ndarray, t_ns: int) -> None:
        """New target ``D``; the blend restarts from the current ``T_world_odom`` at the previous
        frame's time, so this frame already moves by one frame's share."""
        self.reanchors += 1
        self._D = _rigid(D_new)
        self._B0 = self._T_world_odom
        self._t0_ns = self._last_t_ns if self._last_t_ns is not None else t_ns
        self._blend_end_ns = self._t0_ns + int(round(self._horizon_s() * 1e9))
        self._xi_blend = se3.log(_rigid(se3.inverse(self._B0) @ self._D))

    def _horizon_s(self) -> float:
        """How long the new correction takes: ``horizon_s``, or longer for a correction that would
        otherwise add more than ``max_correction_share`` of the camera's speed to a frame."""
        cfg = self.config
        E = se3.inverse(self._B0 @ self._T_odom_cam) @ (self._D @ self._T_odom_cam)
        rate_per_s = cfg.max_correction_share * self._speed
        needed_s = float(np.linalg.norm(E[:3, 3])) / rate_per_s if rate_per_s > 0 else cfg.max_horizon_s
        return max(cfg.horizon_s, min(needed_s, cfg.max_horizon_s))

    def _blend(self, t_ns: int) -> np.ndarray:
        if not self.reanchors or t_ns >= self._blend_end_ns:
            return self._D
        alpha = max(0.0, (t_ns - self._t0_ns) / (self._blend_end_ns - self._t0_ns))
        return self._B0 @ se3.exp(alpha * self._xi_blend)

    def _emit(self, est: PoseEstimate, T_world_cam: np.ndarray, T_world_odom: np.ndarray,
              T_odom_cam: np.ndarray, twist: np.ndarray, corr_m: float, corr_rad: float,
              blend_until_t_ns: int) -> ContinuousPose:
        return ContinuousPose(
            frame_index=int(est.frame_index), t_ns=int(est.t_ns), state=est.state,
            segment_id=int(est.segment_id), scale_state=ScaleState(est.scale_state),
            scale_factors=int(est.scale_factors), T_world_cam=np.array(T_world_cam, dtype=np.float64),
            T_world_odom=np.array(T_world_odom, dtype=np.float64),
            T_odom_cam=np.array(T_odom_cam, dtype=np.float64), twist_cam=np.asarray(twist, dtype=np.float64),
            correction_m=corr_m, correction_rad=corr_rad, blend_until_t_ns=int(blend_until_t_ns))
