"""The messages of one camera's stream: what comes in (a frame, the calibration) and what the SLAM
service answers per frame (pose), per keyframe (keyframe), periodically (status) and on request or
change (trajectory). Encoded by :mod:`metricslam.wire.codec` like every message; frames, keys and
units follow ``docs/conventions.md``.
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from metricslam.camera import PinholeCamera
from metricslam.slam.types import ScaleState, TrackingState
from metricslam.wire.base import FrameId, Message, as_array, finite_pose
from metricslam.wire.scale_status import ScaleHealthStatus

#: tracking states as compact codes (index in this tuple) inside trajectory arrays.
STATE_CODES: tuple[TrackingState, ...] = tuple(TrackingState)


class FrameMessage(Message):
    """One camera image with its intrinsics (``metricslam/<id>/frame``).

    ``image``: (H, W) uint8 gray or (H, W, 3) uint8 RGB, H x W = camera height x width.
    ``t_sent_ns``: sender's wall clock at publish time (ns), echoed in the pose for latency.
    """

    KIND: ClassVar[str] = "frame"
    ARRAYS: ClassVar[tuple[str, ...]] = ("image",)

    frame_index: int = Field(ge=0)
    t_ns: int = Field(ge=0)
    camera: PinholeCamera
    t_sent_ns: int | None = None
    image: np.ndarray

    @field_validator("image")
    @classmethod
    def _image(cls, image: Any) -> np.ndarray:
        image = as_array(image, "uint8", "image")
        if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
            raise ValueError(f"image must be (H, W) or (H, W, 3) uint8, got shape {image.shape}")
        return image

    @model_validator(mode="after")
    def _image_matches_camera(self) -> "FrameMessage":
        h, w = self.image.shape[:2]
        if (w, h) != (self.camera.width_px, self.camera.height_px):
            raise ValueError(
                f"image is {w}x{h} but the camera says {self.camera.width_px}x{self.camera.height_px}"
            )
        return self


class CalibrationMessage(Message):
    """A camera's intrinsics (``metricslam/<id>/calibration``); frames carry them as well."""

    KIND: ClassVar[str] = "calibration"

    camera: PinholeCamera
    baseline_m: float | None = Field(default=None, gt=0)


class PoseMessage(Message):
    """The pose of one input frame (``metricslam/<id>/pose``), published for every frame.

    ``T_world_cam``: (4, 4) float64 camera-to-world, metres once ``scale_established``.
    ``processing_ms``: service time from frame receipt to this publish.
    ``scale_state``: what the pose's scale rests on (``unscaled`` / ``provisional`` / ``metric``,
    :class:`~metricslam.slam.types.ScaleState`) and ``scale_factors`` the learned scale
    measurements behind it; both optional (None from senders that predate them: then read
    ``scale_established`` alone, :meth:`effective_scale_state`).
    ``frame_id``: the frame of ``T_world_cam`` (:data:`~metricslam.wire.base.FrameId`: ``"map"``
    once the session relocalized into the service's saved map, which makes it ``T_map_cam``).
    """

    KIND: ClassVar[str] = "pose"
    ARRAYS: ClassVar[tuple[str, ...]] = ("T_world_cam",)

    frame_index: int = Field(ge=0)
    t_ns: int = Field(ge=0)
    state: TrackingState
    is_keyframe: bool = False
    segment_id: int = Field(default=0, ge=0)
    scale_established: bool = False
    processing_ms: float = Field(default=0.0, ge=0)
    t_sent_ns: int | None = None
    scale_state: ScaleState | None = None
    scale_factors: int | None = Field(default=None, ge=0)
    frame_id: FrameId = "world"
    T_world_cam: np.ndarray

    @field_validator("T_world_cam")
    @classmethod
    def _pose(cls, T: Any) -> np.ndarray:
        return finite_pose(T, "T_world_cam")

    def effective_scale_state(self) -> ScaleState:
        """``scale_state``, or for an older sender ``metric`` if ``scale_established`` else
        ``unscaled`` (it had no provisional scale)."""
        if self.scale_state is not None:
            return self.scale_state
        return ScaleState.METRIC if self.scale_established else ScaleState.UNSCALED


class KeyframeMessage(Message):
    """A new keyframe (``metricslam/<id>/keyframe``): its pose (in ``frame_id``, as
    :class:`PoseMessage`) and, optionally, its image."""

    KIND: ClassVar[str] = "keyframe"
    ARRAYS: ClassVar[tuple[str, ...]] = ("T_world_cam", "image")

    frame_index: int = Field(ge=0)
    t_ns: int = Field(ge=0)
    segment_id: int = Field(default=0, ge=0)
    scale_established: bool = False
    frame_id: FrameId = "world"
    T_world_cam: np.ndarray
    image: np.ndarray | None = None

    @field_validator("T_world_cam")
    @classmethod
    def _pose(cls, T: Any) -> np.ndarray:
        return finite_pose(T, "T_world_cam")

    @field_validator("image")
    @classmethod
    def _image(cls, image: Any) -> np.ndarray | None:
        return None if image is None else FrameMessage._image(image)


class StatusMessage(Message):
    """Health of one camera's SLAM session (``metricslam/<id>/status``), published periodically.

    ``depth_reachable``: None until the depth service was tried (or when scale is off); False
    means keyframes get NO learned scale factors until it answers (``depth_error`` says why).
    ``depth_outages``: times the depth service became unreachable since the service started.
    ``scale_state``: the latest pose's (optional; ``unscaled`` while no depth source answers).
    ``latency_ms_*``: frame receipt -> pose publish inside the service, over a recent window.
    ``event`` / ``event_detail``: set on one-off statuses about the camera's session
    (refused, closed, restarted or rolled over; docs/deployment.md "Bounds and state"), or its
    saved map (``relocalized``: poses are in the map frame from now on; ``map_refused``: the
    service's map does not fit this camera, which runs without it; docs/maps.md), or its VO
    (``vo_suspect``: once per run of frames whose tracks may be aliased on repeating texture, so
    the poses from there may be wrong; docs/vo.md "Aliased tracks"), or a tracking loss
    (``segment_relocalized``: the new segment was placed in the session's own map, off its
    coasting link; its poses jump there; docs/maps.md).
    ``scale_health``: scale sources, mounting height, scale σ, health (optional; :mod:`~metricslam.wire.scale_status`).
    """

    KIND: ClassVar[str] = "status"

    t_ns: int = Field(ge=0)
    frames_received: int = Field(ge=0)
    frames_processed: int = Field(ge=0)
    queue_drops: int = Field(ge=0)
    malformed: int = Field(ge=0)
    queue_depth: int = Field(ge=0)
    fps: float = Field(ge=0)
    latency_ms_p50: float | None = None
    latency_ms_p99: float | None = None
    tracking_state: TrackingState | None = None
    scale_established: bool = False
    keyframes: int = Field(default=0, ge=0)
    depth_url: str | None = None
    depth_reachable: bool | None = None
    depth_error: str | None = None
    depth_outages: int = Field(default=0, ge=0)
    scale_state: ScaleState | None = None
    session_stats: dict[str, float | int | str | bool | None] = Field(default_factory=dict)
    event: Literal["camera_refused", "camera_closed", "session_restarted", "session_rolled_over",
                   "relocalized", "map_refused", "vo_suspect", "segment_relocalized"] | None = None
    event_detail: str | None = Field(default=None, max_length=1000)
    scale_health: ScaleHealthStatus | None = None


class TrajectoryMessage(Message):
    """The whole current (optimized) trajectory of a camera, answer of ``…/trajectory``.

    ``frame_index`` (N,) int64, ``t_ns`` (N,) int64, ``T_world_cam`` (N, 4, 4) float64,
    ``state_code`` (N,) uint8 index into :data:`STATE_CODES`. ``frame_id``: the frame of the
    poses (as :class:`PoseMessage`; after relocalization into a map, only its frames from the first
    localized one on).
    """

    KIND: ClassVar[str] = "trajectory"
    ARRAYS: ClassVar[tuple[str, ...]] = ("frame_index", "t_ns", "T_world_cam", "state_code")

    scale_established: bool = False
    frame_id: FrameId = "world"
    frame_index: np.ndarray
    t_ns: np.ndarray
    T_world_cam: np.ndarray
    state_code: np.ndarray

    @model_validator(mode="after")
    def _consistent(self) -> "TrajectoryMessage":
        n = len(self.frame_index) if isinstance(self.frame_index, np.ndarray) and self.frame_index.ndim == 1 else -1
        object.__setattr__(self, "frame_index", as_array(self.frame_index, "int64", "frame_index", (None,)))
        object.__setattr__(self, "t_ns", as_array(self.t_ns, "int64", "t_ns", (n,)))
        object.__setattr__(self, "T_world_cam", as_array(self.T_world_cam, "float64", "T_world_cam", (n, 4, 4)))
        codes = as_array(self.state_code, "uint8", "state_code", (n,))
        if np.any(codes >= len(STATE_CODES)):
            raise ValueError(f"state_code values must be < {len(STATE_CODES)}")
        object.__setattr__(self, "state_code", codes)
        return self

    @property
    def states(self) -> list[TrackingState]:
        return [STATE_CODES[c] for c in self.state_code]

    @staticmethod
    def state_codes(states: list[TrackingState]) -> np.ndarray:
        return np.array([STATE_CODES.index(TrackingState(s)) for s in states], dtype=np.uint8)
