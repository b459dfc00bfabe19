"""Which of a keyframe's landmarks lie on the ground plane (scale-free, from VO geometry alone).

The learned scale factors (eq. 12) can be restricted to landmarks on the road
(``GraphConfig.scale_landmarks = "ground"``): on validation data the network's depth there is
far less scene-dependent than on buildings, trees and vehicles (``docs/global_graph.md``,
"Ground landmarks"). Nothing metric is used here — no camera height, no ground truth: the plane
is found among the keyframe's own landmarks in VO units.

Method: the landmarks below the principal point, as 3-D points ``X_j = K⁻¹[u, v, 1] / ξ_j`` in
the keyframe's camera frame (x right, y down, z forward; VO units), vote in a RANSAC for a plane
``n·X = h`` whose normal is within ``ground_max_tilt_deg`` of the camera's down axis and which
lies below the camera (``h > 0``). A landmark is on it when the plane's depth along its ray,
``h / (n·r_j)``, agrees with its own depth ``1/ξ_j`` to within ``ground_depth_tol_log`` in log —
a relative test, so it is independent of the VO's arbitrary scale. The RANSAC is seeded, so the
result is deterministic.
"""

from __future__ import annotations

import numpy as np

from metricslam.camera import PinholeCamera

#: RANSAC hypotheses per keyframe (3-point planes); cheap: ~50 landmarks, vectorized scoring
RANSAC_ITERATIONS = 200


def ground_landmarks(uv_px: np.ndarray, inv_depth: np.ndarray, camera: PinholeCamera,
                     max_tilt_deg: float = 25.0, depth_tol_log: float = 0.1,
                     min_inliers: int = 12, seed: int = 0) -> np.ndarray:
    """Boolean mask (M,) of the landmarks on the dominant ground plane; all False when no plane
    with at least ``min_inliers`` landmarks is found.

    Args:
        uv_px: (M, 2) landmark pixels in the keyframe.
        inv_depth: (M,) VO inverse depths ξ_j (1 / VO units), > 0 for usable landmarks.
        camera: the keyframe's intrinsics.
        max_tilt_deg: largest angle between the plane normal and the camera's down axis.
        depth_tol_log: a landmark is on the plane when |log(plane depth / its depth)| is below.
        min_inliers: fewer landmarks on the best plane means "no ground seen".
        seed: RANSAC seed (fixed: the same keyframe always gives the same answer).
    """
    uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    xi = np.asarray(inv_depth, dtype=float).reshape(-1)
    mask = np.zeros(xi.size, dtype=bool)
    usable = np.isfinite(xi) & (xi > 0) & np.isfinite(uv).all(axis=1)
    rays = camera.unproject(uv, 1.0)  # (M, 3), z = 1
    below = usable & (uv[:, 1] > camera.cy_px)
    cand = np.flatnonzero(below)
    if cand.size < max(min_inliers, 3):
        return mask
    points = rays[cand] / xi[cand, None]
    rng = np.random.default_rng(seed)
    cos_tilt = np.cos(np.radians(max_tilt_deg))
    best: np.ndarray | None = None
    for _ in range(RANSAC_ITERATIONS):
        p = points[rng.choice(cand.size, 3, replace=False)]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n = n / norm
        if n[1] < 0:
            n = -n  # point the normal down (camera y axis)
        h = float(n @ p[0])
        if n[1] < cos_tilt or h <= 0:
            continue
        inliers = _on_plane(n, h, rays[cand], xi[cand], depth_tol_log)
        if best is None or inliers.sum() > best.sum():
            best = inliers
    if best is None or best.sum() < min_inliers:
        return mask
    # refit on the inliers (least squares, normal from the smallest singular vector) and re-score
    pts = points[best]
    centroid = pts.mean(axis=0)
    n = np.linalg.svd(pts - centroid)[2][-1]
    n = n if n[1] >= 0 else -n
    h = float(n @ centroid)
    if n[1] >= cos_tilt and h > 0:
        refined = _on_plane(n, h, rays[cand], xi[cand], depth_tol_log)
        if refined.sum() >= best.sum():
            best = refined
    mask[cand[best]] = True
    return mask


def _on_plane(n: np.ndarray, h: float, rays: np.ndarray, xi: np.ndarray, tol_log: float) -> np.ndarray:
    """Landmarks whose depth ``1/ξ`` agrees with the plane ``n·X = h`` along their ray."""
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        plane_depth = np.where(denom > 1e-9, h / denom, np.inf)
        err = np.abs(np.log(plane_depth * xi))
    return np.isfinite(err) & (err < tol_log)
