"""Geometric verification of a loop candidate and its relative Sim(3).

Each keyframe carries ORB descriptors computed *at its VO landmarks* (pixels with known
inverse depth ξ in the keyframe's own units), so a descriptor match is a 3-D–3-D
correspondence between the two keyframes. RANSAC over minimal 3-point Umeyama fits finds
``S_old_new`` (new keyframe's units/frame -> old keyframe's), with inliers decided by the
reprojection error in *both* images; the final estimate is Umeyama on all inliers. Works
without learned depth, so the ``--no-scale`` ablation closes loops too.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.errors import AlignmentError
from metricslam.geometry import sim3
from metricslam.geometry.align import umeyama
from metricslam.slam.graph.config import LoopConfig


@dataclass(frozen=True)
class LandmarkFeatures:
    """ORB descriptors at a keyframe's landmarks and their 3-D points (keyframe units)."""

    uv_px: np.ndarray  # (K, 2)
    points: np.ndarray  # (K, 3) in the keyframe camera frame, keyframe units
    descriptors: np.ndarray  # (K, 32) uint8
    exact: np.ndarray | None = None  # (K,) True for VO landmarks, False for borrowed depths


def landmark_features(orb: cv2.ORB, image_gray: np.ndarray, camera: PinholeCamera,
                      uv_px: np.ndarray, inv_depth: np.ndarray,
                      extra_uv_px: np.ndarray | None = None,
                      radius_px: float | None = None) -> LandmarkFeatures:
    """Describe landmarks (M, 2) with ORB (upright, 31 px patch); drops border/invalid ones.

    ``extra_uv_px`` (K, 2): more corners (e.g. FAST) that borrow the median ξ of the landmarks
    within ``radius_px`` (default 3 % of the image width); those without a landmark nearby are
    dropped. Two keyframes at one place rarely share many VO corners, but they share FAST
    corners; a wrong borrowed depth is just an outlier for the RANSAC below.
    """
    uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    xi = np.asarray(inv_depth, dtype=float).reshape(-1)
    ok = np.isfinite(uv).all(axis=1) & np.isfinite(xi) & (xi > 0)
    uv, xi = uv[ok], xi[ok]
    n_exact = len(uv)
    if extra_uv_px is not None and len(extra_uv_px) and len(uv):
        from scipy.spatial import cKDTree

        r = radius_px if radius_px is not None else max(8.0, 0.03 * camera.width_px)
        extra = np.asarray(extra_uv_px, dtype=float).reshape(-1, 2)
        neigh = cKDTree(uv).query_ball_point(extra, r)
        got = [(e, float(np.median(xi[n]))) for e, n in zip(extra, neigh) if n]
        if got:
            uv = np.vstack([uv, np.array([g[0] for g in got])])
            xi = np.concatenate([xi, np.array([g[1] for g in got])])
    kps = [cv2.KeyPoint(float(uv[i, 0]), float(uv[i, 1]), 31.0, 0.0, 0.0, 0, int(i)) for i in range(len(uv))]
    kps, desc = orb.compute(image_gray, kps)
    if desc is None or not kps:
        return LandmarkFeatures(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 32), np.uint8))
    keep = np.array([kp.class_id for kp in kps], dtype=int)
    pts = camera.unproject(uv[keep], 1.0 / xi[keep])
    return LandmarkFeatures(uv[keep], pts, desc, keep < n_exact)


@dataclass(frozen=True)
class VerifiedLoop:
    """``S_old_new`` (4, 4), match / inlier counts and, when measured from geometry, the
    tangent sigmas (7,) ``[ω, u, λ]`` of the measurement (else None: configured sigmas)."""

    S_old_new: np.ndarray
    n_matches: int
    n_inliers: int
    sigmas: np.ndarray | None = None


def match_descriptors(d_new: np.ndarray, d_old: np.ndarray, ratio: float) -> np.ndarray:
    """(K, 2) index pairs ``(i_new, i_old)`` of binary descriptors (N, 32) / (M, 32) uint8 that pass
    Lowe's ratio test on Hamming distance (``ratio``) and are under 64 bits apart; shared by the
    loop and relocalization code."""
    if len(d_new) < 2 or len(d_old) < 2:
        return np.zeros((0, 2), dtype=int)
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(d_new, d_old, k=2)
    pairs = [(m.queryIdx, m.trainIdx) for m, n in (p for p in knn if len(p) == 2)
             if m.distance < ratio * n.distance and m.distance < 64]
    if not pairs:
        return np.zeros((0, 2), dtype=int)
    pairs = np.array(pairs, dtype=int)
    _, first = np.unique(pairs[:, 1], return_index=True)  # one-to-one on the old side
    return pairs[np.sort(first)]


def _two_way_errors(S_old_new, p_new, p_old, uv_new, uv_old, camera) -> np.ndarray:
    q_old = sim3.transform_points(S_old_new, p_new)
    q_new = sim3.transform_points(sim3.inverse(S_old_new), p_old)
    e1 = np.linalg.norm(camera.project(q_old) - uv_old, axis=1)
    e2 = np.linalg.norm(camera.project(q_new) - uv_new, axis=1)
    e = np.maximum(e1, e2)
    return np.where(np.isfinite(e), e, np.inf)


def verify(new: LandmarkFeatures, old: LandmarkFeatures, camera: PinholeCamera, config: LoopConfig,
           rng: np.random.Generator) -> VerifiedLoop | None:
    """RANSAC Sim(3) between two keyframes' landmarks, or None when it does not verify."""
    pairs = match_descriptors(new.descriptors, old.descriptors, config.hamming_ratio)
    if len(pairs) < config.min_matches:
        return None
    p_new, p_old = new.points[pairs[:, 0]], old.points[pairs[:, 1]]
    uv_new, uv_old = new.uv_px[pairs[:, 0]], old.uv_px[pairs[:, 1]]
    best = np.zeros(len(pairs), dtype=bool)
    for _ in range(config.ransac_iterations):
        sample = rng.choice(len(pairs), size=3, replace=False)
        try:
            S = umeyama(p_new[sample], p_old[sample], with_scale=True)
        except AlignmentError:
            continue
        inl = _two_way_errors(S, p_new, p_old, uv_new, uv_old, camera) < config.reprojection_threshold_px
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < max(config.min_inliers, 3):
        return None
    # final fit on pairs whose depths are both VO landmarks when there are enough of them
    # (borrowed depths verify the place; they are too coarse to measure the Sim(3))
    fit = best
    if new.exact is not None and old.exact is not None:
        both = best & new.exact[pairs[:, 0]] & old.exact[pairs[:, 1]]
        if both.sum() >= 6:
            fit = both
    try:
        S = umeyama(p_new[fit], p_old[fit], with_scale=True)
    except AlignmentError:
        return None
    inl = _two_way_errors(S, p_new, p_old, uv_new, uv_old, camera) < config.reprojection_threshold_px
    n_inl = int(inl.sum())
    if n_inl < config.min_inliers or n_inl < config.min_inlier_ratio * len(pairs):
        return None
    return VerifiedLoop(S, len(pairs), n_inl)
