"""``RoadImage`` and ``RoadPatch``: the images and pixels the road-height aligner works on.

A :class:`RoadImage` is one gray keyframe image prepared once — its pyramid and, per level, the
intensity and its x / y gradients stacked as one 3-channel float32 image, so one ``cv2.remap``
samples all three at the warped pixels. A keyframe is the "current" image of one measurement and
the "previous" one of the next, so the ground meter keeps the prepared image instead of
rebuilding it.

A :class:`RoadPatch` is one pyramid level of one measurement: the textured road pixels of the
current image, their rays, and the parts of the plane-induced warp that do not depend on the
plane (``K R q`` and ``K t``), so that each Gauss-Newton step costs one (N, 3) product, one remap
and a few vector operations. Frames and units: :mod:`.plane`, docs/conventions.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.slam.ground.plane import road_rays, tilt_normal, tilt_normal_derivatives

_NAN4 = (float("nan"),) * 4
_MAP_COLS = 8192


@dataclass(frozen=True)
class RoadImage:
    """One gray image prepared for the road aligner (module docstring).

    Attributes:
        shape: (H, W) of the full-resolution image, px.
        levels: per pyramid level ``L`` (0 = full resolution) an (H_L, W_L, 3) float32 image of
            intensity (gray levels), d/du and d/dv (gray levels per px at that level); None for
            levels below the finest one aligned (never sampled).
    """

    shape: tuple[int, int]
    levels: tuple[np.ndarray | None, ...]


def prepare_road_image(img: np.ndarray, levels: int, finest_level: int = 0) -> RoadImage:
    """:class:`RoadImage` of an (H, W) gray image (uint8 or float) with ``levels`` pyramid levels."""
    gray = np.asarray(img, dtype=np.float32)
    out: list[np.ndarray | None] = []
    for lv in range(levels):
        if lv:
            gray = cv2.pyrDown(gray)
        if lv < finest_level:
            out.append(None)
            continue
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        out.append(cv2.merge([gray, gx, gy]))
    return RoadImage((int(img.shape[0]), int(img.shape[1])), tuple(out))


def level_K(K: np.ndarray, level: int) -> np.ndarray:
    """(3, 3) intrinsics at pyramid ``level`` (pixel centres at integers: u_L = (u + 0.5)/2^L − 0.5)."""
    f = 0.5 ** level
    K_L = np.array(K, dtype=float)
    K_L[0, 0] *= f
    K_L[1, 1] *= f
    K_L[0, 2] = (K[0, 2] + 0.5) * f - 0.5
    K_L[1, 2] = (K[1, 2] + 0.5) * f - 0.5
    return K_L


def _sample(stack: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 3) float32 bilinear samples of a 3-channel image at pixels ``(u, v)`` (N,) each; NaN
    outside it."""
    n = len(u)
    cols = min(max(n, 1), _MAP_COLS)  # cv2.remap wants maps under 32767 rows and columns
    rows = -(-n // cols) if n else 1
    m = np.empty((rows * cols, 2), dtype=np.float32)
    m[:n, 0] = u
    m[:n, 1] = v
    m[n:] = -10.0  # padding: outside the image
    out = cv2.remap(stack, m.reshape(rows, cols, 2), None, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=_NAN4)
    return out.reshape(-1, 3)[:n]


@dataclass(frozen=True)
class RoadRegion:
    """The expected road patch at one pyramid level (:func:`~.plane.road_rays`).

    Attributes:
        flat: (N,) int64 pixel indices ``v·W_L + u`` into the level's image.
        rays: (3, N) rays ``K_L⁻¹ [u, v, 1]`` (one row per coordinate: the aligner's vector
            operations run on contiguous rows).
    """

    flat: np.ndarray
    rays: np.ndarray


def road_region(K_L: np.ndarray, shape: tuple[int, int], n0: np.ndarray, lateral_half_width: float,
                forward_range: tuple[float, float]) -> RoadRegion:
    """:class:`RoadRegion` of an (H_L, W_L) level (arguments as :func:`~.plane.road_rays`)."""
    uv, rays = road_rays(K_L, shape[1], shape[0], n0, lateral_half_width, forward_range)
    flat = uv[:, 1].astype(np.int64) * int(shape[1]) + uv[:, 0].astype(np.int64)
    return RoadRegion(flat, np.ascontiguousarray(rays.T))


class RoadPatch:
    """The textured road pixels of one level and the plane-independent part of their warp.

    Args:
        prev, cur: the level's (H_L, W_L, 3) stacks of the previous and current image.
        K_L: (3, 3) intrinsics at the level.
        region: the level's :class:`RoadRegion`.
        T_prev_cur: (4, 4) current camera in the previous one.
        n0: (3,) nominal down direction the tilt is measured from.
        min_gradient: current-image pixels with a weaker gradient (gray levels / px) are skipped.
        max_pixels: at most this many pixels (an even subsample).
    """

    def __init__(self, prev: np.ndarray, cur: np.ndarray, K_L: np.ndarray, region: RoadRegion,
                 T_prev_cur: np.ndarray, n0: np.ndarray, min_gradient: float, max_pixels: int) -> None:
        self.prev = prev
        self.n0 = np.asarray(n0, dtype=float)
        g = np.take(cur.reshape(-1, 3), region.flat, axis=0)  # (N, 3) intensity, d/du, d/dv (current)
        sel = np.flatnonzero(g[:, 1] * g[:, 1] + g[:, 2] * g[:, 2] >= np.float32(min_gradient) ** 2)
        if len(sel) > max_pixels:
            sel = sel[np.linspace(0, len(sel) - 1, max_pixels).round().astype(int)]
        self.rays = np.take(region.rays, sel, axis=1)
        self.i_cur = g[sel, 0].astype(float)
        # A = K (R q + t (n·q) / h): K R q and K t are fixed while the plane changes
        self.KRq = (K_L @ T_prev_cur[:3, :3]) @ self.rays
        self.Kt = K_L @ T_prev_cur[:3, 3]

    def __len__(self) -> int:
        return self.rays.shape[1]

    def warp(self, p: np.ndarray, with_jacobian: bool = True
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """The patch's previous-image pixels for ``p = [log h, tilt_x, tilt_z]``.

        Returns:
            ``(u_prev_px (N,), v_prev_px (N,), A_z (N,), dc (3, N) or None)`` with ``A_z > 0`` in
            front of the previous camera and ``duv/dp_k = dc_k (K t_xy − uv K t_z) / A_z``,
            ``dc = (−n·q, ∂n/∂tilt_x·q, ∂n/∂tilt_z·q) / h`` (:func:`~.height.plane_warp`'s, factored).
        """
        h = float(np.exp(p[0]))
        if with_jacobian:
            dc = (tilt_normal_derivatives(self.n0, p[1:]) / h).T @ self.rays  # (n·q, ∂n/∂tilt·q) / h
            c = dc[0].copy()
            dc[0] = -c
        else:
            dc, c = None, (tilt_normal(self.n0, p[1:]) / h) @ self.rays
        Kt, KRq = self.Kt, self.KRq
        Az = KRq[2] + c * Kt[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (KRq[0] + c * Kt[0]) / Az
            v = (KRq[1] + c * Kt[1]) / Az
        return u, v, Az, dc

    def residuals(self, p: np.ndarray, with_jacobian: bool
                  ) -> tuple[np.ndarray, np.ndarray | None]:
        """Photometric residuals of the valid pixels for ``p = [log h, tilt_x, tilt_z]``.

        Returns:
            ``(r (M,), J_t (3, M) or None)`` over the M pixels whose warp lands inside the previous
            image in front of it (gray levels, after an affine brightness fit), ``J_t`` the
            Jacobian's transpose (rows: d r / d p_k); None when not asked for or when M < 10.
        """
        u, v, Az, dc = self.warp(p, with_jacobian)
        s = _sample(self.prev, u, v)
        iw = s[:, 0].astype(float)
        valid = np.isfinite(iw) & (Az > 0)
        i_cur = self.i_cur
        if not valid.all():  # usually all are: index only when needed
            idx = np.flatnonzero(valid)
            s, iw, u, v, Az, i_cur = s[idx], iw[idx], u[idx], v[idx], Az[idx], i_cur[idx]
            dc = None if dc is None else dc[:, idx]
        r, gain = _affine_residuals(iw, i_cur)
        if not with_jacobian or len(r) < 10:
            return r, None
        Kt = self.Kt
        g = (s[:, 1].astype(float) * (Kt[0] - u * Kt[2]) + s[:, 2].astype(float) * (Kt[1] - v * Kt[2])) / Az
        J = dc * (gain * g)
        finite = np.isfinite(g)
        if not finite.all():
            r, J = r[finite], J[:, finite]
        return r, J

    def grid_costs(self, heights: np.ndarray, max_pixels: int) -> np.ndarray:
        """Median absolute residual (gray levels) of the level plane ``n0`` at each of
        ``heights`` (K,), over an even subsample of at most ``max_pixels`` pixels; ``inf``
        where under half of them (or under 10) warp validly."""
        step = -(-len(self) // max_pixels)
        rays, KRq, i_cur = self.rays[:, ::step], self.KRq[:, ::step], self.i_cur[::step]
        c = (1.0 / np.asarray(heights, float))[:, None] * (self.n0 @ rays)[None, :]  # (K, N)
        Kt = self.Kt
        Az = KRq[2] + c * Kt[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (KRq[0] + c * Kt[0]) / Az
            v = (KRq[1] + c * Kt[1]) / Az
        iw = _sample(self.prev, u.ravel(), v.ravel())[:, 0].astype(float).reshape(u.shape)
        valid = np.isfinite(iw) & (Az > 0)
        n_valid = valid.sum(axis=1)
        nv = np.maximum(n_valid, 1)
        x = np.where(valid, iw, 0.0)
        y = np.where(valid, i_cur[None, :], 0.0)
        mx, my = x.sum(axis=1) / nv, y.sum(axis=1) / nv
        xc = np.where(valid, x - mx[:, None], 0.0)
        gain = (xc * (y - my[:, None])).sum(axis=1) / np.maximum((xc * xc).sum(axis=1), 1e-9)
        bias = my - gain * mx
        a = np.where(valid, np.abs(gain[:, None] * x + bias[:, None] - y), np.inf)
        # the median of each row's valid residuals (np.median's: the mean of the middle two)
        lo, hi = np.maximum((n_valid - 1) // 2, 0), n_valid // 2
        a = np.partition(a, np.unique(np.concatenate([lo, hi])), axis=1)
        rows = np.arange(len(a))
        cost = 0.5 * (a[rows, lo] + a[rows, hi])
        ok = (n_valid >= 0.5 * len(i_cur)) & (n_valid >= 10)
        return np.where(ok, cost, np.inf)


def _affine_residuals(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """``gain·x + bias − y`` (M,) with gain and bias fit by least squares, and the gain."""
    if len(x) < 10:
        return np.empty(0), 1.0
    mx, my = x.mean(), y.mean()
    x_c = x - mx
    gain = float(x_c @ (y - my) / max(float(x_c @ x_c), 1e-9))
    bias = float(my - gain * mx)
    return gain * x + bias - y, gain
