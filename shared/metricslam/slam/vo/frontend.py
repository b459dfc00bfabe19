"""KLT frontend: Shi-Tomasi corners, pyramidal Lucas-Kanade, forward-backward check, grid
spreading and essential-matrix RANSAC on normalized coordinates (paper §III-C.1).

Tracks carry an integer id; new corners get fresh ids. The frontend knows nothing about poses
or landmarks: :class:`~metricslam.slam.vo.local_vo.LocalVO` maps track ids to landmarks.
Pixels follow ``docs/conventions.md`` (OpenCV's centre-of-pixel origin).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.slam.vo.config import VOConfig


@dataclass(frozen=True)
class Tracks:
    """Currently tracked corners. ``ids`` (N,) int64, ``uv_px`` (N, 2) float64."""

    ids: np.ndarray
    uv_px: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


class KLTFrontend:
    """Frame-to-frame corner tracker for one camera."""

    def __init__(self, config: VOConfig, camera: PinholeCamera) -> None:
        self.config = config
        self.camera = camera
        self._next_id = 0
        self._prev_pyr: np.ndarray | None = None
        self.ids = np.zeros(0, dtype=np.int64)
        self.uv_px = np.zeros((0, 2))
        self._before: tuple | None = None  # (prev image, ids, uv_px) of the last track(), for retrack()
        self._win = (config.klt_window_px, config.klt_window_px)
        self._criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, config.klt_max_iterations,
                          0.03)

    @property
    def tracks(self) -> Tracks:
        return Tracks(self.ids.copy(), self.uv_px.copy())

    def reset(self) -> None:
        """Forget every track (ids keep increasing)."""
        self._prev_pyr = None
        self.ids = np.zeros(0, dtype=np.int64)
        self.uv_px = np.zeros((0, 2))

    def track(self, gray: np.ndarray, uv_guess_px: np.ndarray | None = None) -> Tracks:
        """Track the current corners into ``gray`` (H, W) uint8; drop failures and FB outliers.

        Args:
            uv_guess_px: optional (N, 2) predicted positions of the current tracks (NaN = no
                guess), e.g. from the motion model; large motions of near points need it.
        """
        pyr = gray  # OpenCV 5's Python binding takes images, not prebuilt pyramids
        self._before = None
        if self._prev_pyr is None or len(self.ids) == 0:
            self._prev_pyr = pyr
            return self.tracks
        self._before = (self._prev_pyr, self.ids, self.uv_px)
        p0 = self.uv_px.astype(np.float32).reshape(-1, 1, 2)
        lv = self.config.klt_levels
        if uv_guess_px is not None and len(uv_guess_px) == len(p0):
            guess = np.where(np.isfinite(uv_guess_px), uv_guess_px, self.uv_px)
            p1 = guess.astype(np.float32).reshape(-1, 1, 2)
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._prev_pyr, pyr, p0, p1, winSize=self._win,
                                                  maxLevel=lv, criteria=self._criteria,
                                                  flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        else:
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._prev_pyr, pyr, p0, None,
                                                  winSize=self._win, maxLevel=lv,
                                                  criteria=self._criteria)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(pyr, self._prev_pyr, p1, p0.copy(),
                                               winSize=self._win,
                                               maxLevel=min(lv, self.config.klt_back_levels),
                                               criteria=self._criteria,
                                               flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        p1 = p1.reshape(-1, 2).astype(np.float64)
        fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < self.config.fb_max_error_px)
        ok &= self.camera.in_image(p1, margin_px=self.config.border_px * 0.5)
        self.ids, self.uv_px = self.ids[ok], p1[ok]
        self._prev_pyr = pyr
        return self.tracks

    def retrack(self, gray: np.ndarray) -> Tracks | None:
        """Track the last :meth:`track` call's corners into ``gray`` again, each started at its
        previous pixel moved by the global image shift (phase correlation at 1/4 resolution)
        instead of the motion guess; the tracks that call produced are replaced. None when that
        call tracked nothing (:mod:`~metricslam.slam.vo.aliasing`)."""
        if self._before is None:
            return None
        prev, ids, uv_px = self._before
        h, w = gray.shape
        small = [cv2.resize(g, (w // 4, h // 4), interpolation=cv2.INTER_AREA).astype(np.float32) for g in (prev, gray)]
        (dx, dy), _ = cv2.phaseCorrelate(*small)
        self._prev_pyr, self.ids, self.uv_px = prev, ids, uv_px
        return self.track(gray, uv_px + 4.0 * np.array([dx, dy]))

    def restore(self, tracks: Tracks) -> None:
        """Make ``tracks`` (a :attr:`tracks` snapshot of this frame) the current tracks again."""
        self.ids, self.uv_px = tracks.ids.copy(), tracks.uv_px.copy()

    def reject_by_essential(self, ids_ref: np.ndarray, uv_ref_px: np.ndarray) -> tuple[np.ndarray, int]:
        """Drop tracks that violate the epipolar geometry w.r.t. reference pixels.

        Args:
            ids_ref, uv_ref_px: pixels of (some) current tracks in a reference frame (the last
                keyframe). Tracks without a reference pixel are kept.

        Returns:
            (K,) ids that were rejected, and how many tracks were checked (0: too few common
            tracks or too little motion to check).
        """
        common, i_cur, i_ref = np.intersect1d(self.ids, ids_ref, return_indices=True)
        none = np.zeros(0, dtype=np.int64)
        if len(common) < 8:
            return none, 0
        a = self.camera.normalized(uv_ref_px[i_ref])
        b = self.camera.normalized(self.uv_px[i_cur])
        motion_px = np.median(np.linalg.norm(uv_ref_px[i_ref] - self.uv_px[i_cur], axis=1))
        if motion_px < 2.0:  # no baseline: E is undetermined, nothing to check against
            return none, 0
        thr = self.config.ransac_threshold_px / self.camera.fx_px
        E, mask = cv2.findEssentialMat(a, b, np.eye(3), method=cv2.RANSAC, prob=0.999,
                                       threshold=thr)
        if E is None or mask is None:
            return none, 0
        bad = common[mask.ravel() == 0]
        self.drop(bad)
        return bad, len(common)

    def drop(self, ids: np.ndarray) -> None:
        """Stop tracking the given ids."""
        if len(ids) == 0:
            return
        keep = ~np.isin(self.ids, ids)
        self.ids, self.uv_px = self.ids[keep], self.uv_px[keep]

    def detect(self, gray: np.ndarray) -> Tracks:
        """Add Shi-Tomasi corners in empty grid cells up to ``max_features``; returns the new ones."""
        cfg = self.config
        h, w = gray.shape
        need = cfg.max_features - len(self.ids)
        if need <= 0:
            return Tracks(np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
        # detect at 1/ds resolution: corner localization precision does not matter for KLT
        # (a track is wherever its first patch was), and it is ds² cheaper
        ds = cfg.detect_downsample
        small = gray if ds == 1 else cv2.resize(gray, (w // ds, h // ds), interpolation=cv2.INTER_AREA)
        sh, sw = small.shape
        mask = np.zeros((sh, sw), dtype=np.uint8)
        b = int(np.ceil(cfg.border_px / ds))
        mask[b:sh - b, b:sw - b] = 255
        r = max(int(cfg.min_corner_distance_px / ds), 1)
        for u, v in self.uv_px:
            cv2.circle(mask, (int(round((u + 0.5) / ds - 0.5)), int(round((v + 0.5) / ds - 0.5))), r, 0, -1)
        pts = cv2.goodFeaturesToTrack(small, maxCorners=3 * cfg.max_features,
                                      qualityLevel=cfg.corner_quality,
                                      minDistance=cfg.min_corner_distance_px / ds, mask=mask,
                                      blockSize=3)
        if pts is None:
            return Tracks(np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
        pts = (pts.reshape(-1, 2).astype(np.float64) + 0.5) * ds - 0.5
        # grid spreading: each cell takes at most its share, strongest corners first
        gx = np.clip((pts[:, 0] * cfg.grid_cols / w).astype(int), 0, cfg.grid_cols - 1)
        gy = np.clip((pts[:, 1] * cfg.grid_rows / h).astype(int), 0, cfg.grid_rows - 1)
        cell = gy * cfg.grid_cols + gx
        quota = int(np.ceil(cfg.max_features / (cfg.grid_cols * cfg.grid_rows)))
        ex = self.uv_px
        ex_cell = (np.clip((ex[:, 1] * cfg.grid_rows / h).astype(int), 0, cfg.grid_rows - 1)
                   * cfg.grid_cols
                   + np.clip((ex[:, 0] * cfg.grid_cols / w).astype(int), 0, cfg.grid_cols - 1))
        count = np.bincount(ex_cell, minlength=cfg.grid_cols * cfg.grid_rows)
        chosen = []
        for k, c in enumerate(cell):  # goodFeaturesToTrack returns strongest first
            if count[c] < quota:
                count[c] += 1
                chosen.append(k)
                if len(chosen) >= need:
                    break
        new_uv = pts[chosen]
        new_ids = np.arange(self._next_id, self._next_id + len(chosen), dtype=np.int64)
        self._next_id += len(chosen)
        self.ids = np.concatenate([self.ids, new_ids])
        self.uv_px = np.concatenate([self.uv_px, new_uv])
        if self._prev_pyr is None:
            self._prev_pyr = gray
        return Tracks(new_ids, new_uv)
