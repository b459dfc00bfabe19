"""Plain message types that pass between the SLAM core's parts and its adapters.

The local VO hands :class:`MarginalizedKeyframe` to a :class:`KeyframeConsumer` (the global
graph); every processed frame yields a :class:`PoseEstimate`. Frames and units are in the names.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets.base import Frame


class TrackingState(str, enum.Enum):
    """Per-frame tracking state."""

    INITIALIZING = "initializing"  # no map yet (waiting for parallax)
    TRACKING = "tracking"
    LOST = "lost"  # this frame could not be tracked; a new segment starts after re-init
    INVALID_FRAME = "invalid_frame"  # corrupt/blank/unreadable input; live pose: the last known one


class ScaleState(str, enum.Enum):
    """What a pose's scale rests on (docs/global_graph.md, "Metric from the first pose").

    ``UNSCALED``: nothing metric yet — no depth source, it failed, or the VO has no map; the
    pose is in the VO's arbitrary monocular units. ``PROVISIONAL``: metric from the initial
    estimate at VO initialization and/or fewer learned scale factors than
    ``GraphConfig.min_scale_factors_established``. ``METRIC``: the global graph's scale factors
    have established the scale (``scale_established``).
    """

    UNSCALED = "unscaled"
    PROVISIONAL = "provisional"
    METRIC = "metric"


@dataclass(frozen=True)
class PoseEstimate:
    """The pose of one input frame.

    Attributes:
        frame_index: index of the input frame.
        t_ns: its timestamp (ns).
        T_world_cam: (4, 4) camera-to-world; metric once ``scale_established``.
        state: tracking state of this frame.
        is_keyframe: whether this frame became a keyframe.
        segment_id: increments after each tracking loss (each segment has its own world frame
            until something relates them).
        scale_established: True when learned scale factors have fixed the metric scale
            (``scale_state`` is then ``METRIC``).
        scale_state: what the pose's scale rests on (:class:`ScaleState`), at processing time.
        scale_factors: learned scale measurements in the global graph's latest solve when the
            frame was processed (0 without learned scale).
        interpolated: the frame had no pose of its own (invalid input, tracking loss, a given-up
            initialization) and ``T_world_cam`` was interpolated at ``t_ns`` between the nearest
            frames before and after it that have one (only :meth:`SlamSession.trajectory` sets it).
        vo_suspect: the VO's tracks on this frame (and the one before) may be aliased on repeating
            texture, or the frame starts the map on a two-view start the frames between its views
            do not confirm: its pose may be wrong (:mod:`metricslam.slam.vo.aliasing`,
            :func:`metricslam.slam.vo.initializer.start_confirmed`).
        pose_valid: False when the frame has no pose of its own and none could be interpolated
            (no such frame on one side, or the two sides in unrelated world frames);
            ``T_world_cam`` is then a placeholder (:meth:`SlamPipeline.trajectory` says which).
    """

    frame_index: int
    t_ns: int
    T_world_cam: np.ndarray
    state: TrackingState
    is_keyframe: bool = False
    segment_id: int = 0
    scale_established: bool = False
    interpolated: bool = False
    pose_valid: bool = True
    scale_state: ScaleState = ScaleState.UNSCALED
    scale_factors: int = 0
    vo_suspect: bool = False


@dataclass(frozen=True)
class MarginalizedKeyframe:
    """A keyframe leaving the local window, with what the global graph needs.

    Attributes:
        kf_id: unique increasing keyframe id.
        frame_index: index of the input frame that became this keyframe.
        t_ns: its timestamp (ns).
        segment_id: tracking segment.
        T_vo_kf: (4, 4) keyframe pose in the local VO's world frame (VO scale) at marginalization.
        T_prevkf_kf: (4, 4) pose relative to the previously marginalized keyframe of the same
            segment (VO scale), or None for a segment's first keyframe.
        landmarks_uv_px: (M, 2) pixels of the keyframe's child landmarks in this keyframe.
        landmarks_inv_depth: (M,) their VO inverse depths ξ_j (1/VO-units), > 0.
        image: the keyframe image (H, W) uint8 gray (for depth and place recognition).
        camera: intrinsics of ``image``.
        information: optional (6, 6) information of ``T_prevkf_kf`` in tangent ``[ω, v]``.
    """

    kf_id: int
    frame_index: int
    t_ns: int
    segment_id: int
    T_vo_kf: np.ndarray
    T_prevkf_kf: np.ndarray | None
    landmarks_uv_px: np.ndarray
    landmarks_inv_depth: np.ndarray
    image: np.ndarray
    camera: PinholeCamera
    information: np.ndarray | None = field(default=None)


class KeyframeConsumer(Protocol):
    """Receives marginalized keyframes (the global graph implements this)."""

    def on_keyframe_marginalized(self, kf: MarginalizedKeyframe) -> None: ...


class SlamSession(Protocol):
    """One camera's SLAM: the object services and the offline runner drive.

    ``process`` never raises on bad input: a corrupt frame yields a pose with
    ``state=INVALID_FRAME`` and tracking failures yield ``LOST`` (then re-initialization).
    """

    def process(self, frame: Frame) -> PoseEstimate: ...

    def trajectory(self) -> list[PoseEstimate]:
        """The current best pose of every frame processed so far, in frame order."""
        ...

    def stats(self) -> dict:
        """Counters and per-stage timings (ms) for reporting."""
        ...

    def close(self) -> None:
        """Stop background workers and flush pending work (e.g. the last keyframes)."""
        ...


class Backend(KeyframeConsumer, Protocol):
    """The global back end the pipeline feeds (the Sim(3) graph implements it).

    The pipeline hands it every marginalized keyframe; after each global solve the back end
    offers a correction that the pipeline applies to the local VO (the paper's "warp"), so the
    newest pose is metric.
    """

    def take_correction(self) -> np.ndarray | None:
        """A Sim(3) ``S_new_vo`` (4, 4) to apply to the local VO's world frame, once; None if
        no new solve happened since the last call."""
        ...

    def optimized_keyframe_poses(self) -> dict[int, np.ndarray]:
        """``frame_index -> S_world_kf`` (4, 4 Sim(3); its scale maps VO units of that keyframe
        to metres) for every keyframe in the global graph, after the latest finished solve (a
        threaded back end does not wait for a running one; idle, it is the current one)."""
        ...

    @property
    def scale_established(self) -> bool: ...

    def close(self) -> None:
        """Finish pending work (depth requests, last solve) and stop workers."""
        ...
