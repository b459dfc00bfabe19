"""Frozen configuration of the local visual odometry, with per-dataset presets.

One model, :class:`VOConfig`; every field documents its unit. ``extra="forbid"`` makes a stale
or misspelled key an error (:class:`metricslam.errors.ConfigError` via :meth:`VOConfig.from_dict`).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from metricslam.errors import ConfigError, validation_problems

PresetName = Literal["kitti", "euroc", "tum", "synth"]


class VOConfig(BaseModel):
    """Parameters of the KLT frontend, initializer, sliding-window BA and marginalization."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    # --- frontend: detection and tracking ---
    max_features: int = Field(400, ge=20, description="target number of tracked corners")
    grid_cols: int = Field(12, ge=1, description="detection grid columns (spreads corners)")
    grid_rows: int = Field(4, ge=1, description="detection grid rows")
    min_corner_distance_px: float = Field(12.0, gt=0, description="Shi-Tomasi minimum distance")
    corner_quality: float = Field(0.005, gt=0, lt=1, description="Shi-Tomasi quality level")
    klt_window_px: int = Field(15, ge=5, description="LK window side (odd)")
    klt_max_iterations: int = Field(10, ge=1, description="LK iterations per pyramid level")
    klt_levels: int = Field(3, ge=0, le=6, description="LK pyramid levels above the base")
    klt_back_levels: int = Field(
        1, ge=0, le=6, description="pyramid levels of the backward (check) LK pass; it starts "
        "at the original corner, so coarse levels only cost time")
    fb_max_error_px: float = Field(1.0, gt=0, description="forward-backward LK error threshold")
    ransac_threshold_px: float = Field(1.0, gt=0, description="essential-matrix RANSAC threshold")
    retrack_reject_share: float = Field(
        0.22, gt=0, le=1, description="a frame whose essential check rejects more than this share of "
        "its tracks is tracked again from the global image shift; kept if that halves the share "
        "(metricslam.slam.vo.aliasing.retrack)")
    suspect_reject_share: float = Field(
        0.22, gt=0, le=1, description="a tracked frame whose essential check rejects more than this "
        "share of its tracks, as it did on the frame before, is reported suspect (tracks possibly "
        "aliased on repeating texture; metricslam.slam.vo.aliasing)")
    border_px: float = Field(8.0, ge=0, description="corners closer to the border are dropped")
    min_texture_std: float = Field(2.0, ge=0, description="image std below this is 'blank'")

    # --- keyframes ---
    keyframe_motion_px: float = Field(30.0, gt=0, description="mean pixel motion since last KF")
    keyframe_min_track_ratio: float = Field(
        0.6, gt=0, le=1, description="new KF when tracks from the last KF fall below this ratio")
    keyframe_max_frames: int = Field(10, ge=1, description="new KF at least every N frames")

    # --- initialization ---
    init_min_motion_px: float = Field(20.0, gt=0, description="median motion before trying init")
    init_min_inliers: int = Field(60, ge=8, description="essential-matrix inliers needed")
    init_min_parallax_deg: float = Field(
        0.6, gt=0, description="median triangulation angle needed (guards slow/stationary start)")
    init_max_frames: int = Field(60, ge=2, description="restart the reference after N frames")
    init_pending_min_share: float = Field(
        0.8, ge=0, le=1, description="a two-view start is reported suspect when a frame between its "
        "views has fewer than this share of the two-view points agreeing with its pose "
        "(metricslam.slam.vo.initializer.start_confirmed)")

    # --- tracking / loss ---
    min_tracked_landmarks: int = Field(20, ge=6, description="fewer pose inliers means LOST")
    pose_iterations: int = Field(8, ge=1, description="motion-only Gauss-Newton iterations")
    pose_collapse_ratio: float = Field(
        0.5, ge=0, le=1, description="pose inliers below this share of the previous frame's: the "
        "motion prediction was off (e.g. a sudden turn), also try PnP-RANSAC and keep the better")

    coast_max_s: float = Field(
        2.0, ge=0, description="after a tracking loss the new segment starts where the mean motion "
        "of the last tracked frames, kept up, would have taken the camera by then, for at most this "
        "long (s; 0: where tracking was lost)")

    # --- window BA ---
    window_size: int = Field(10, ge=3, description="keyframes kept in the sliding window")
    ba_iterations: int = Field(3, ge=1, description="LM iterations per window solve (re-solved at every keyframe)")
    huber_px: float = Field(1.5, gt=0, description="Huber threshold of reprojection residuals")
    min_landmark_parallax_deg: float = Field(
        0.3, ge=0, description="a new landmark needs this much ray angle to get a depth")
    ba_in_background: bool = Field(True, description="solve the window in a worker thread")
    keyframe_waits_for_ba: bool = Field(
        True, description="a new keyframe waits for the solve still running (at most one in "
        "flight)")
    ba_joins_next_frame: bool = Field(
        True, description="the frame after a keyframe waits for that keyframe's background "
        "solve, so every frame is tracked against the same map whatever the threads' timing "
        "(the pose of the keyframe itself is out before the solve; at 10 Hz the solve is done "
        "before the next frame arrives)")
    blas_threads: int | None = Field(
        1, ge=1, description="process-wide OpenBLAS thread cap set by LocalVO (its matrices are "
        "tiny; multi-threaded BLAS on a busy 2-core machine is ~10x slower); None = leave alone")
    detect_downsample: int = Field(2, ge=1, le=4, description="detect corners at 1/N resolution")

    @model_validator(mode="after")
    def _check(self) -> "VOConfig":
        if self.klt_window_px % 2 == 0:
            raise ValueError(f"klt_window_px must be odd, got {self.klt_window_px}")
        if self.grid_cols * self.grid_rows > self.max_features:
            raise ValueError("grid has more cells than max_features; lower grid_rows/grid_cols")
        return self

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> "VOConfig":
        """A preset for a dataset (``kitti``, ``euroc``, ``tum``, ``synth``) with overrides."""
        if name not in _PRESETS:
            raise ConfigError(f"unknown VO preset {name!r}; choose one of {sorted(_PRESETS)}")
        return cls.from_dict({**_PRESETS[name], **overrides})

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "VOConfig":
        """Validate a dict; raise :class:`ConfigError` naming the bad keys."""
        try:
            return cls(**values)
        except ValidationError as exc:
            raise ConfigError(f"invalid VO config: {validation_problems(exc)}") from exc


_PRESETS: dict[str, dict[str, Any]] = {
    # 1226x370 at 10 Hz, ~1 m/frame forward motion: many corners, wide grid.
    "kitti": dict(max_features=500, grid_cols=16, grid_rows=4, keyframe_motion_px=30.0,
                  keyframe_min_track_ratio=0.3),
    # 752x480 at 20 Hz, handheld/MAV: more rotation, fewer pixels.
    "euroc": dict(max_features=300, grid_cols=8, grid_rows=6, keyframe_motion_px=20.0,
                  init_min_motion_px=15.0),
    # 640x480 at 30 Hz handheld: slow motion, motion blur.
    "tum": dict(max_features=300, grid_cols=8, grid_rows=6, keyframe_motion_px=20.0,
                init_min_motion_px=15.0, min_texture_std=4.0),
    # metricslam synth renders: textured planes, exact pinhole.
    "synth": dict(max_features=400, grid_cols=12, grid_rows=6, keyframe_motion_px=25.0),
}
