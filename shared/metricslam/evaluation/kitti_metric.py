"""The KITTI odometry devkit metric (``evaluate_odometry.cpp``), re-implemented exactly.

For every start frame ``f = 0, 10, 20, …`` and every length ``L`` (100, 200, …, 800 m):

* ``dist`` is the cumulative ground-truth path length (sum of position steps);
* the end frame ``l`` is the **first** frame with ``dist[l] > dist[f] + L`` (strictly greater);
  a segment with no such frame is skipped;
* ``E = (P_est[f]⁻¹ P_est[l])⁻¹ (P_gt[f]⁻¹ P_gt[l])``;
* ``t_err = |trans(E)| / L`` and ``r_err = angle(E) / L`` with
  ``angle = acos(clip((trace(R_E) − 1) / 2, −1, 1))``.

``t_rel`` and ``r_rel`` are the plain means over all segments (pooled over lengths and start
frames; over sequences too when pooled). They are reported in percent and in degrees per 100 m.
When not one 100 m segment fits, lengths 10..50 m are used instead (:data:`SHORT_LENGTHS_M`) and
the result says so. Poses are ``T_world_cam`` (N, 4, 4); see ``docs/conventions.md``.
The devkit computes in float32; this module uses float64 (differences are at rounding level).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from metricslam.errors import EvaluationError

#: the devkit's segment lengths in metres.
KITTI_LENGTHS_M: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
#: lengths used when the sequence is too short for a single 100 m segment.
SHORT_LENGTHS_M: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0, 50.0)
#: the devkit's start-frame step ("every second" at 10 Hz).
STEP_FRAMES = 10


@dataclass(frozen=True)
class SegmentErrors:
    """Per-segment errors, one entry per (start frame, length) that fits.

    Attributes:
        first_frame: (M,) int start frame index.
        last_frame: (M,) int end frame index.
        length_m: (M,) segment length ``L`` in metres.
        t_err_per_m: (M,) ``|trans(E)| / L`` (dimensionless; ×100 = percent).
        r_err_rad_per_m: (M,) ``angle(E) / L`` in rad per metre.
        lengths_m: the candidate lengths that were tried.
    """

    first_frame: np.ndarray
    last_frame: np.ndarray
    length_m: np.ndarray
    t_err_per_m: np.ndarray
    r_err_rad_per_m: np.ndarray
    lengths_m: tuple[float, ...]

    def __len__(self) -> int:
        return int(self.length_m.shape[0])

    @property
    def t_rel_pct(self) -> float:
        """Mean translational error in percent (NaN with no segments)."""
        return float(np.mean(self.t_err_per_m) * 100.0) if len(self) else float("nan")

    @property
    def r_rel_deg_per_100m(self) -> float:
        """Mean rotational error in degrees per 100 m (NaN with no segments)."""
        return float(np.degrees(np.mean(self.r_err_rad_per_m)) * 100.0) if len(self) else float("nan")

    @property
    def used_lengths_m(self) -> list[float]:
        """Lengths that produced at least one segment, ascending."""
        return sorted({float(v) for v in self.length_m})

    def by_length(self) -> dict[float, tuple[float, float, int]]:
        """``L -> (t_rel_pct, r_rel_deg_per_100m, n_segments)`` for each used length."""
        out = {}
        for L in self.used_lengths_m:
            m = self.length_m == L
            out[L] = (float(np.mean(self.t_err_per_m[m]) * 100.0),
                      float(np.degrees(np.mean(self.r_err_rad_per_m[m])) * 100.0), int(m.sum()))
        return out

    @staticmethod
    def concatenate(parts: list["SegmentErrors"]) -> "SegmentErrors":
        """Pool segments of several sequences (the devkit's average over a whole benchmark)."""
        if not parts:
            raise EvaluationError("nothing to pool: no sequences were evaluated")
        cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
        lengths = tuple(sorted({L for p in parts for L in p.lengths_m}))
        return SegmentErrors(cat("first_frame"), cat("last_frame"), cat("length_m"),
                             cat("t_err_per_m"), cat("r_err_rad_per_m"), lengths)


def trajectory_distances(T_world_cam: np.ndarray) -> np.ndarray:
    """Cumulative path length (N,) in metres, ``dist[0] = 0`` (devkit ``trajectoryDistances``)."""
    p = np.asarray(T_world_cam, dtype=float)[:, :3, 3]
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def last_frame_from_segment_length(dist: np.ndarray, first_frame: int, length_m: float) -> int:
    """First frame ``i >= first_frame`` with ``dist[i] > dist[first_frame] + length_m``, or -1."""
    # dist is non-decreasing, so searchsorted(side="right") is the first index strictly greater.
    i = int(np.searchsorted(dist, dist[first_frame] + length_m, side="right"))
    return i if i < dist.shape[0] else -1


def segment_errors(
    T_world_cam_gt: np.ndarray,
    T_world_cam_est: np.ndarray,
    lengths_m: tuple[float, ...] = KITTI_LENGTHS_M,
    step_frames: int = STEP_FRAMES,
) -> SegmentErrors:
    """Devkit ``calcSequenceErrors`` for one sequence; both inputs (N, 4, 4), frame-aligned."""
    gt = np.asarray(T_world_cam_gt, dtype=float)
    est = np.asarray(T_world_cam_est, dtype=float)
    if gt.shape != est.shape or gt.ndim != 3 or gt.shape[1:] != (4, 4):
        raise EvaluationError(
            f"ground truth and estimate must both be (N, 4, 4) with the same N, got {gt.shape} "
            f"and {est.shape}; write one estimated pose per ground-truth frame"
        )
    dist = trajectory_distances(gt)
    rows = []
    for first in range(0, gt.shape[0], step_frames):
        for L in lengths_m:
            last = last_frame_from_segment_length(dist, first, L)
            if last == -1:
                continue
            delta_gt = np.linalg.inv(gt[first]) @ gt[last]
            delta_est = np.linalg.inv(est[first]) @ est[last]
            E = np.linalg.inv(delta_est) @ delta_gt
            t_err = float(np.linalg.norm(E[:3, 3]))
            c = 0.5 * (E[0, 0] + E[1, 1] + E[2, 2] - 1.0)
            r_err = float(np.arccos(max(min(c, 1.0), -1.0)))
            rows.append((first, last, L, t_err / L, r_err / L))
    arr = np.array(rows, dtype=float).reshape(-1, 5)
    return SegmentErrors(
        first_frame=arr[:, 0].astype(np.int64), last_frame=arr[:, 1].astype(np.int64),
        length_m=arr[:, 2], t_err_per_m=arr[:, 3], r_err_rad_per_m=arr[:, 4],
        lengths_m=tuple(float(L) for L in lengths_m),
    )


def kitti_segment_errors(T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray) -> SegmentErrors:
    """Devkit lengths 100..800 m; if no 100 m segment fits, lengths 10..50 m (see module doc)."""
    seg = segment_errors(T_world_cam_gt, T_world_cam_est, KITTI_LENGTHS_M)
    if len(seg) == 0:
        seg = segment_errors(T_world_cam_gt, T_world_cam_est, SHORT_LENGTHS_M)
    return seg
