"""All-corner loop verification: ORB corners of both keyframes with a depth per corner.

A keyframe carries only ~30–80 VO landmarks and two visits of one place share few of them, so
verification uses *all* ORB corners of both keyframes. Each corner gets a 3-D point in its
keyframe's own VO units (what the keyframe's Sim(3) variable measures):

* scale mode: the network's metric inverse-depth map sampled at the corner, converted to
  keyframe units by the keyframe's metres-per-unit — the robust M-estimate of ``ξ_j / z_j`` over
  its landmarks, i.e. the same measurement its scale factor carries;
* ``--no-scale`` mode (no learned depth at all): triangulation of the corner against the
  previous keyframe with the VO's own ``T_prevkf_kf`` (keyframe units).

Verification: Hamming ratio-test matching, essential-matrix RANSAC on the matches
(``cv2.findEssentialMat``: the geometric check that the two images see one rigid scene), then
PnP-RANSAC (EPnP, refined by Levenberg-Marquardt) of the new camera against the old keyframe's
3-D corners: rotation and translation (old units) rest on the new image's bearings, so only one
side's depth noise enters (a 3-D–3-D Umeyama fit on network depth was off by 3–7° in rotation
on the synthetic loop). The scale ``s_old_new`` is the median ratio of the inliers' distances
from the new camera centre measured with the old and with the new keyframe's depths.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.geometry import sim3
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.loop.geometric_sim3 import measure_loop
from metricslam.slam.loop.verification import VerifiedLoop, match_descriptors

#: metric inverse depths outside this range (1/m) are not used (sky, hood, too near).
INV_DEPTH_RANGE_PER_M = (1.0 / 60.0, 1.0 / 1.5)


@dataclass(frozen=True)
class CornerFeatures:
    """ORB corners of one keyframe: pixels (N, 2), descriptors (N, 32) uint8 and 3-D points
    (N, 3) in the keyframe camera frame, keyframe VO units (NaN rows: no depth). ``points``
    verify a loop (network depth in scale mode); ``points_geo`` (triangulated) measure it."""

    uv_px: np.ndarray
    descriptors: np.ndarray
    points: np.ndarray
    points_geo: np.ndarray | None = None  # (N, 3) triangulated, keyframe VO units (NaN: none)

    @property
    def geometric_points(self) -> np.ndarray:
        """Triangulated points (N, 3) for the loop measurement (``points`` when they are)."""
        return self.points if self.points_geo is None else self.points_geo

    @property
    def n_with_depth(self) -> int:
        return int(np.isfinite(self.points).all(axis=1).sum())


#: bytes of one stored row index (:class:`PackedCorners`)
_ROW_INDEX_BYTES = np.dtype(np.int32).itemsize


@dataclass(frozen=True)
class PackedCorners:
    """A keyframe's :class:`CornerFeatures` as the place-recognition database holds them, in
    half the memory and losslessly (:meth:`unpack` gives back equal arrays):

    * pixels as float32 — ORB keypoints are float32, so nothing is rounded (float64 is kept
      for pixels that are not);
    * the network's ``points`` (~90 % of the corners have one) as their depth along z only,
      when ``camera.unproject(uv, z)`` gives back exactly the stored points (it does: that is
      how :func:`network_points` made them; checked bit for bit at packing, else kept whole);
    * a 3-D point array as its rows that are not all NaN plus their row indices, when that is
      smaller — the triangulated ``points_geo`` has a point for ~7 % of the corners.

    Rendered loop, ~950 corners a keyframe: 96 -> ~48 bytes per corner (pixels 8, descriptor
    32, network depth 8; triangulated points for 0-7 % of the corners, 0-2), ~45 KiB per
    database entry (``tests/test_slam_service_soak.py``).

    Attributes:
        n_corners: N.
        n_with_depth: :attr:`CornerFeatures.n_with_depth`, without unpacking.
        camera: the keyframe's intrinsics, when ``points`` is held as depth (else None).
    """

    n_corners: int
    n_with_depth: int
    uv_px: np.ndarray  # (N, 2) float32 (float64 when not exact)
    descriptors: np.ndarray  # (N, 32) uint8
    # (row indices (K,) int32 or None: every row, rows (K, 3) points or (K,) depth when ``camera``)
    points: tuple[np.ndarray | None, np.ndarray]
    points_geo: tuple[np.ndarray | None, np.ndarray] | None
    camera: PinholeCamera | None = None

    @classmethod
    def pack(cls, features: CornerFeatures, camera: PinholeCamera | None = None) -> PackedCorners:
        """Pack ``features``; with ``camera``, network points that are ``camera.unproject(uv,
        z)`` are held as ``z``."""
        uv = np.asarray(features.uv_px)
        uv32 = uv.astype(np.float32)
        points = _pack_rows(features.points)
        as_depth = camera is not None and _is_unprojection(points, uv, camera)
        if as_depth:
            points = (points[0], np.ascontiguousarray(points[1][:, 2]))
        return cls(len(uv), features.n_with_depth, uv32 if np.array_equal(uv32, uv) else uv,
                   features.descriptors, points,
                   None if features.points_geo is None else _pack_rows(features.points_geo),
                   camera if as_depth else None)

    def unpack(self) -> CornerFeatures:
        """The :class:`CornerFeatures` this was packed from (equal arrays, float64 pixels)."""
        uv = self.uv_px.astype(np.float64)
        rows, values = self.points
        if self.camera is not None:
            values = self.camera.unproject(uv if rows is None else uv[rows], values)
        return CornerFeatures(uv, self.descriptors, _unpack_rows(self.n_corners, rows, values),
                              None if self.points_geo is None else _unpack_rows(self.n_corners, *self.points_geo))

    @property
    def nbytes(self) -> int:
        """Bytes of array data held."""
        arrays = [self.uv_px, self.descriptors, *self.points, *(self.points_geo or ())]
        return sum(a.nbytes for a in arrays if a is not None)


def _is_unprojection(points: tuple[np.ndarray | None, np.ndarray], uv_px: np.ndarray,
                     camera: PinholeCamera) -> bool:
    """Whether packed 3-D rows are exactly ``camera.unproject`` of their pixels and z (NaN rows
    included: a NaN z gives a NaN row)."""
    rows, values = points
    uv = np.asarray(uv_px, dtype=np.float64)
    uv = uv if rows is None else uv[rows]
    if values.ndim != 2 or values.shape[1] != 3 or len(values) != len(uv):
        return False
    return bool(np.array_equal(camera.unproject(uv, values[:, 2]), values, equal_nan=True))


def _pack_rows(points: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """``(rows, points[rows])`` for the rows of (N, 3) ``points`` that are not all NaN, when
    smaller than ``points``; else ``(None, points)``."""
    keep = ~np.isnan(points).all(axis=1)
    n_keep = int(keep.sum())
    if n_keep * (points.shape[1] * points.itemsize + _ROW_INDEX_BYTES) >= points.nbytes:
        return None, points
    return np.flatnonzero(keep).astype(np.int32), points[keep]


def _unpack_rows(n: int, rows: np.ndarray | None, values: np.ndarray) -> np.ndarray:
    if rows is None:
        return values
    out = np.full((n, values.shape[1]), np.nan, dtype=values.dtype)
    out[rows] = values
    return out


def detect_corners(orb: cv2.ORB, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ORB corners of a full-resolution gray image -> (uv_px (N, 2), descriptors (N, 32))."""
    kps, desc = orb.detectAndCompute(gray, None)
    if desc is None or not kps:
        return np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
    return np.array([k.pt for k in kps], dtype=float), desc


def metres_per_unit(landmarks_inv_depth: np.ndarray, net_inv_depth_at_landmarks: np.ndarray,
                    min_landmarks: int = 5) -> float | None:
    """Median of ``ξ_j / z_j`` (metres per keyframe unit) over valid landmarks, or None."""
    xi = np.asarray(landmarks_inv_depth, float).reshape(-1)
    z = np.asarray(net_inv_depth_at_landmarks, float).reshape(-1)
    lo, hi = INV_DEPTH_RANGE_PER_M
    ok = np.isfinite(xi) & np.isfinite(z) & (xi > 0) & (z >= lo) & (z <= hi)
    if ok.sum() < min_landmarks:
        return None
    return float(np.exp(np.median(np.log(xi[ok] / z[ok]))))


def network_points(uv_px: np.ndarray, net_inv_depth_per_m: np.ndarray, m_per_unit: float,
                   camera: PinholeCamera) -> np.ndarray:
    """3-D points (N, 3) in keyframe units from metric inverse depth (N,) at the corners."""
    z = np.asarray(net_inv_depth_per_m, float).reshape(-1)
    lo, hi = INV_DEPTH_RANGE_PER_M
    ok = np.isfinite(z) & (z >= lo) & (z <= hi)
    pts = np.full((len(z), 3), np.nan)
    if ok.any():
        pts[ok] = camera.unproject(uv_px[ok], (1.0 / z[ok]) / m_per_unit)
    return pts


def triangulated_points(uv_px: np.ndarray, desc: np.ndarray, prev_uv_px: np.ndarray,
                        prev_desc: np.ndarray, T_prev_k: np.ndarray, camera: PinholeCamera,
                        hamming_ratio: float = 0.8, max_reproj_px: float = 2.0,
                        min_parallax_deg: float = 1.0) -> np.ndarray:
    """3-D points (N, 3) of keyframe k's corners triangulated against the previous keyframe.

    Args:
        uv_px / desc: keyframe k's corners (N, 2) and descriptors.
        prev_uv_px / prev_desc: the previous keyframe's corners and descriptors.
        T_prev_k: (4, 4) pose of k in the previous keyframe (VO's ``T_prevkf_kf``; its
            translation is in k's VO units, so the points are too).
    Returns:
        (N, 3) in k's camera frame, NaN where no match, bad reprojection or low parallax.
    """
    pts = np.full((len(uv_px), 3), np.nan)
    pairs = match_descriptors(desc, prev_desc, hamming_ratio)
    if len(pairs) < 8:
        return pts
    R, t = np.asarray(T_prev_k, float)[:3, :3], np.asarray(T_prev_k, float)[:3, 3]
    if np.linalg.norm(t) <= 0:
        return pts
    K = camera.K
    P_k = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P_prev = K @ np.hstack([R, t[:, None]])
    a, b = uv_px[pairs[:, 0]], prev_uv_px[pairs[:, 1]]
    X = cv2.triangulatePoints(P_k, P_prev, a.T.astype(np.float64), b.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (X[:3] / X[3]).T
    X_prev = X @ R.T + t
    c_prev_in_k = -R.T @ t
    ray_k, ray_p = X, X - c_prev_in_k
    cosang = np.sum(ray_k * ray_p, axis=1) / (np.linalg.norm(ray_k, axis=1) * np.linalg.norm(ray_p, axis=1))
    with np.errstate(invalid="ignore"):
        e_k = np.linalg.norm(camera.project(X) - a, axis=1)
        e_p = np.linalg.norm(camera.project(X_prev) - b, axis=1)
        ok = ((X[:, 2] > 0) & (X_prev[:, 2] > 0) & (e_k < max_reproj_px) & (e_p < max_reproj_px)
              & (cosang < np.cos(np.radians(min_parallax_deg))))
    ok &= np.isfinite(X).all(axis=1)
    pts[pairs[ok, 0]] = X[ok]
    return pts


def verify_corners(new: CornerFeatures, old: CornerFeatures, camera: PinholeCamera,
                   config: LoopConfig, rng: np.random.Generator) -> VerifiedLoop | None:
    """Essential-matrix check, then RANSAC Sim(3) ``S_old_new`` (new's units -> old's), or None."""
    pairs = match_descriptors(new.descriptors, old.descriptors, config.hamming_ratio)
    if len(pairs) < max(config.min_matches, 2 * config.min_depth_inliers):
        return None  # a true revisit matches hundreds of corners; wrong places a few dozen
    uv_new, uv_old = new.uv_px[pairs[:, 0]], old.uv_px[pairs[:, 1]]
    E, mask = cv2.findEssentialMat(uv_new, uv_old, camera.K, method=cv2.RANSAC, prob=0.999,
                                   threshold=config.essential_threshold_px,
                                   maxIters=config.ransac_iterations)
    if E is None or mask is None:
        return None
    e_inl = mask.ravel().astype(bool)
    if e_inl.sum() < config.min_inliers or e_inl.sum() < config.min_inlier_ratio * len(pairs):
        return None
    p_new, p_old = new.points[pairs[:, 0]], old.points[pairs[:, 1]]
    idx = np.flatnonzero(e_inl & np.isfinite(p_old).all(axis=1))
    if len(idx) < config.min_depth_inliers:
        return None
    # pose of the new camera from the old keyframe's 3-D corners (old units) and the new pixels:
    # rotation and translation direction rest on bearings, only one side's depth noise enters
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        p_old[idx].astype(np.float64), uv_new[idx].astype(np.float64), camera.K, None,
        iterationsCount=config.ransac_iterations, reprojectionError=config.corner_reprojection_threshold_px,
        confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < config.min_depth_inliers:
        return None
    inl = idx[inl.ravel()]
    if len(inl) < config.min_depth_inlier_ratio * len(idx):
        return None
    rvec, tvec = cv2.solvePnPRefineLM(p_old[inl].astype(np.float64), uv_new[inl].astype(np.float64),
                                      camera.K, None, rvec, tvec)
    R_new_old = cv2.Rodrigues(rvec)[0]
    R_old_new = R_new_old.T
    t_old_new = -R_old_new @ tvec.ravel()
    if config.measurement == "geometric":
        return _geometric(new, old, pairs, inl, np.flatnonzero(e_inl), R_old_new, t_old_new, camera, config)
    # scale (old units per new unit): distances from the new camera centre on both sides
    both = inl[np.isfinite(p_new[inl]).all(axis=1)]
    if len(both) < config.min_depth_inliers // 2:
        return None
    d_old = np.linalg.norm(p_old[both] - t_old_new, axis=1)
    d_new = np.linalg.norm(p_new[both], axis=1)
    s_old_new = float(np.exp(np.median(np.log(d_old / d_new))))
    if not np.isfinite(s_old_new) or s_old_new <= 0:
        return None
    return VerifiedLoop(sim3.from_rts(R_old_new, t_old_new, s_old_new), len(pairs), len(inl))


def _geometric(new: CornerFeatures, old: CornerFeatures, pairs: np.ndarray, inl: np.ndarray,
               e_inl: np.ndarray, R_old_new: np.ndarray, t_old_new: np.ndarray, camera: PinholeCamera,
               config: LoopConfig) -> VerifiedLoop | None:
    """Translation and scale of a verified loop from triangulated corners only
    (:mod:`metricslam.slam.loop.geometric_sim3`) among the essential-matrix inliers ``e_inl``
    (indices into ``pairs``; ``inl``: the PnP inliers)."""
    g_old, g_new = old.geometric_points[pairs[:, 1]], new.geometric_points[pairs[:, 0]]
    # the verification translation is in the verification points' units: rescale it to the old
    # keyframe's triangulated units where both kinds of depth exist (1 when they are the same)
    v_old = old.points[pairs[inl, 1]]
    both = np.isfinite(v_old).all(axis=1) & np.isfinite(g_old[inl]).all(axis=1)
    k = 1.0
    if both.sum() >= 3:
        k = float(np.exp(np.median(np.log(np.linalg.norm(g_old[inl][both], axis=1)
                                          / np.linalg.norm(v_old[both], axis=1)))))
    res = measure_loop(R_old_new, k * t_old_new, new.uv_px[pairs[e_inl, 0]], g_old[e_inl], g_new[e_inl],
                       camera, sigma_rot_rad=config.rotation_sigma_rad,
                       reprojection_px=config.geometric_reprojection_px,
                       min_translation_points=config.min_geometric_points,
                       min_scale_points=config.min_geometric_scale_points)
    if res is None:
        return None
    return VerifiedLoop(res.S_old_new, len(pairs), len(inl), res.sigmas)
