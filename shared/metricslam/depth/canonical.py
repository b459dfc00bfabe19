"""The canonical camera of depth contract version 2: every image is warped to one virtual camera.

A version-2 network sees every image as if taken by one fixed pinhole camera, the **canonical
camera** (:class:`CanonicalCamera`: focal lengths ``fx_px``/``fy_px`` at the network input's
resolution, principal point at the input's centre). The caller's image (intrinsics ``fx, fy,
cx, cy`` of a :class:`~metricslam.camera.PinholeCamera`) is scaled by ``sx = fx_c / fx``,
``sy = fy_c / fy`` (anisotropic when the two differ) and shifted so that its principal point lands
on the input's centre; what falls outside the input is cropped, what the image does not cover is
padded with :data:`PAD_VALUE_U8` and marked invalid. The network therefore never has to guess the
field of view: a pixel of the input always looks along the same ray.

Pixel convention (``docs/conventions.md``): ``(u, v)`` with the origin at the **centre** of the
top-left pixel, as in :class:`~metricslam.camera.PinholeCamera` and OpenCV's ``warpAffine``. The
input's centre is ``((W_in − 1)/2, (H_in − 1)/2)`` and the warp (caller -> input) is::

    u_in = sx·u + tx,   tx = (W_in − 1)/2 − sx·cx        (likewise v_in with sy, ty, cy)

which is ``u'_in = sx·(u' − cx') + W_in/2`` in corner coordinates (``u' = u + 0.5``), and agrees
with ``cv2.resize`` (``u → (u + 0.5)·s − 0.5``).

Metric meaning (written once, :func:`inv_depth_from_canonical`): the network's ``d_frac`` is the
left disparity as a fraction of the **input** width for the training baseline ``baseline_m`` at the
canonical focal length, so::

    inv_depth_per_m = d_frac · W_in / (fx_c · baseline_m)

independent of the caller's camera. :func:`to_caller_grid` then resamples that inverse depth
(bilinearly, over valid cells only) onto an (h, w) grid spanning the **caller's** image, the grid
of contract version 1, with NaN where the caller's image lies outside the canonical field of view.

Pure numpy + OpenCV (no onnxruntime, no torch): inference (:mod:`metricslam.depth.model`) and
training (the label helpers :func:`warp_depth_labels`, :func:`canonical_d_frac`) share it.

Example::

    >>> canonical = CanonicalCamera(fx_px=300.0, fy_px=300.0, width_px=512, height_px=256)
    >>> warp = canonical_warp(PinholeCamera(fx_px=718.9, fy_px=718.9, cx_px=607.2, cy_px=185.2,
    ...                                     width_px=1226, height_px=370), canonical)
    >>> image_in, valid_in = to_canonical(gray_u8, warp)        # (256, 512) uint8, bool
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.disparity import inv_depth_from_width_fraction
from metricslam.errors import DepthModelError, ImageError

#: gray value of input pixels the caller's image does not cover: ≈ 0.45·255, the normalization
#: mean of the shipped models, so padding reads as ≈ 0 to the network. Such pixels are also
#: marked invalid (``valid_in``) and the output cells they back are dropped (:func:`cells_valid`).
PAD_VALUE_U8 = 115
#: label kinds :func:`warp_depth_labels` knows: metric depth and inverse depth are unchanged by
#: scaling the image; a horizontal disparity in pixels scales with ``sx``.
LabelKind = Literal["depth_m", "inv_depth_per_m", "disparity_px"]


@dataclass(frozen=True)
class CanonicalCamera:
    """The network input's virtual pinhole camera (contract version 2).

    Attributes:
        fx_px / fy_px: focal lengths in pixels at the input resolution.
        width_px / height_px: the network input size (``input_width`` / ``input_height``).
    The principal point is the input's centre (:attr:`cx_px`, :attr:`cy_px`).
    """

    fx_px: float
    fy_px: float
    width_px: int
    height_px: int

    def __post_init__(self) -> None:
        for name in ("fx_px", "fy_px"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float, np.floating)) and math.isfinite(value) and value > 0):
                raise DepthModelError(f"canonical {name} must be a finite number > 0 px, got {value!r}")
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and value >= 1):
                raise DepthModelError(f"canonical {name} must be an integer >= 1 px, got {value!r}")

    @property
    def cx_px(self) -> float:
        """Principal point column: the input's centre, ``(W_in − 1)/2`` (pixel-centre convention)."""
        return (self.width_px - 1) / 2.0

    @property
    def cy_px(self) -> float:
        """Principal point row: ``(H_in − 1)/2``."""
        return (self.height_px - 1) / 2.0


@dataclass(frozen=True)
class CanonicalWarp:
    """The axis-aligned affine map from a caller's image to the canonical input.

    Attributes:
        camera: the caller's camera (its ``width_px × height_px`` is the caller image size).
        canonical: the network's :class:`CanonicalCamera`.
        scale_x / scale_y: ``sx = fx_c / fx``, ``sy = fy_c / fy`` (input px per caller px).
        offset_x_px / offset_y_px: ``tx``, ``ty`` of ``u_in = sx·u + tx`` (pixel-centre convention).
    """

    camera: PinholeCamera
    canonical: CanonicalCamera
    scale_x: float
    scale_y: float
    offset_x_px: float
    offset_y_px: float

    @property
    def matrix(self) -> np.ndarray:
        """(2, 3) float64 affine matrix caller pixel -> input pixel (``cv2.warpAffine`` form)."""
        return np.array([[self.scale_x, 0.0, self.offset_x_px], [0.0, self.scale_y, self.offset_y_px]])

    def to_input(self, uv_px: np.ndarray) -> np.ndarray:
        """Caller pixels (N, 2) -> input pixels (N, 2) float64."""
        uv = np.atleast_2d(np.asarray(uv_px, dtype=np.float64))
        return np.stack([self.scale_x * uv[:, 0] + self.offset_x_px,
                         self.scale_y * uv[:, 1] + self.offset_y_px], axis=1)

    def to_caller(self, uv_in_px: np.ndarray) -> np.ndarray:
        """Input pixels (N, 2) -> caller pixels (N, 2) float64 (the inverse of :meth:`to_input`)."""
        uv = np.atleast_2d(np.asarray(uv_in_px, dtype=np.float64))
        return np.stack([(uv[:, 0] - self.offset_x_px) / self.scale_x,
                         (uv[:, 1] - self.offset_y_px) / self.scale_y], axis=1)


def canonical_warp(camera: PinholeCamera, canonical: CanonicalCamera) -> CanonicalWarp:
    """The warp that shows ``camera``'s image as ``canonical`` sees it (module docstring)."""
    sx = canonical.fx_px / camera.fx_px
    sy = canonical.fy_px / camera.fy_px
    return CanonicalWarp(camera=camera, canonical=canonical, scale_x=float(sx), scale_y=float(sy),
                         offset_x_px=float(canonical.cx_px - sx * camera.cx_px),
                         offset_y_px=float(canonical.cy_px - sy * camera.cy_px))


def _covered(n_in: int, scale: float, offset: float, n_caller: int) -> np.ndarray:
    """(n_in,) bool: input pixel centres whose caller coordinate lies on the caller image,
    ``[-0.5, n_caller − 0.5]`` (its outer pixel edges)."""
    caller = (np.arange(n_in, dtype=np.float64) - offset) / scale
    return (caller >= -0.5) & (caller <= n_caller - 0.5)


def valid_input_mask(warp: CanonicalWarp) -> np.ndarray:
    """(H_in, W_in) bool: input pixels backed by the caller's image (False where padded)."""
    cam, can = warp.camera, warp.canonical
    cols = _covered(can.width_px, warp.scale_x, warp.offset_x_px, cam.width_px)
    rows = _covered(can.height_px, warp.scale_y, warp.offset_y_px, cam.height_px)
    return rows[:, None] & cols[None, :]


def to_canonical(gray_u8: np.ndarray, warp: CanonicalWarp) -> tuple[np.ndarray, np.ndarray]:
    """The caller's gray image as the canonical camera sees it.

    Axes that shrink are first reduced with ``cv2.INTER_AREA`` (no aliasing) to about their final
    size; the remaining scale and the sub-pixel shift are one ``cv2.warpAffine`` (bilinear, edge
    replicated). Pixels the image does not cover get :data:`PAD_VALUE_U8`.

    Args:
        gray_u8: (H, W) uint8, the size of ``warp.camera``.
        warp: from :func:`canonical_warp`.

    Returns:
        ``image_in`` (H_in, W_in) uint8 and ``valid_in`` (H_in, W_in) bool (False where padded).
    """
    img = np.asarray(gray_u8)
    cam, can = warp.camera, warp.canonical
    if img.dtype != np.uint8 or img.shape != (cam.height_px, cam.width_px):
        raise ImageError(f"expected an ({cam.height_px}, {cam.width_px}) uint8 gray image for a "
                         f"{cam.width_px}x{cam.height_px} camera, got {img.dtype} {img.shape}: pass the "
                         "camera of this image (PinholeCamera.resized for a resized one)")
    matrix = warp.matrix
    width1 = max(1, round(cam.width_px * warp.scale_x)) if warp.scale_x < 1 else cam.width_px
    height1 = max(1, round(cam.height_px * warp.scale_y)) if warp.scale_y < 1 else cam.height_px
    if (width1, height1) != (cam.width_px, cam.height_px):
        img = cv2.resize(img, (width1, height1), interpolation=cv2.INTER_AREA)
        # caller u = (u1 + 0.5)·W/W1 − 0.5 for a pixel u1 of the reduced image
        for axis, (n, n1) in enumerate(((cam.width_px, width1), (cam.height_px, height1))):
            r = n / n1
            matrix[axis, 2] += matrix[axis, axis] * 0.5 * (r - 1.0)
            matrix[axis, axis] *= r
    image_in = cv2.warpAffine(img, matrix, (can.width_px, can.height_px), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)
    valid_in = valid_input_mask(warp)
    image_in[~valid_in] = PAD_VALUE_U8
    return image_in, valid_in


def cells_valid(valid_in: np.ndarray, out_hw: tuple[int, int], min_fraction: float) -> np.ndarray:
    """(h, w) bool: output cells at least ``min_fraction`` of whose input pixels are valid.

    Args:
        valid_in: (H_in, W_in) bool from :func:`to_canonical`.
        out_hw: the network's output grid (h, w), e.g. (H_in/8, W_in/8).
        min_fraction: in (0, 1] (the contract's ``valid_min_fraction``).
    """
    if not 0.0 < min_fraction <= 1.0:
        raise DepthModelError(f"valid_min_fraction must be in (0, 1], got {min_fraction}")
    valid = np.asarray(valid_in, dtype=bool)
    h, w = out_hw
    big_h, big_w = valid.shape
    if big_h % h == 0 and big_w % w == 0:
        fraction = valid.reshape(h, big_h // h, w, big_w // w).mean(axis=(1, 3))
    else:
        fraction = cv2.resize(valid.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    return fraction >= min_fraction - 1e-9


def _axis_weights(pos: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cell coordinates ``pos`` on an axis of ``n`` cells -> (inside, nearest, i0, i1, a)."""
    inside = np.isfinite(pos) & (pos >= -0.5) & (pos <= n - 0.5)
    p = np.clip(np.nan_to_num(pos), 0.0, n - 1.0)
    nearest = np.clip(np.floor(p + 0.5), 0, n - 1).astype(np.int64)
    i0 = np.minimum(np.floor(p).astype(np.int64), max(n - 2, 0))
    i1 = np.minimum(i0 + 1, n - 1)
    return inside, nearest, i0, i1, p - i0


def to_caller_grid(map_in: np.ndarray, valid_cells: np.ndarray, warp: CanonicalWarp,
                   out_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Resample a map on the network's output grid onto a grid spanning the caller's image.

    Cell ``(i, j)`` of the (h, w) caller grid is centred at caller pixel ``((j + 0.5)·W/w − 0.5,
    (i + 0.5)·H/h − 0.5)`` (:mod:`metricslam.depth.sample`'s convention); that point is mapped into
    the input and the map is interpolated bilinearly there, over valid cells only (the weights of
    invalid neighbours are dropped and the rest renormalized; the border is edge-replicated).
    Resample inverse depth (or ``d_frac``), never depth: it is what the network predicts.

    Args:
        map_in: (h_in, w_in) e.g. the network's inverse depth, 1/m.
        valid_cells: (h_in, w_in) bool from :func:`cells_valid`.
        warp: the warp the input was made with; ``W × H`` is ``warp.camera``'s size.
        out_hw: (h, w) of the caller grid; default ``map_in.shape`` (the grid of contract v1).

    Returns:
        (h, w) float32; NaN where the cell centre maps outside the input or its nearest input
        cell is invalid.
    """
    grid = np.asarray(map_in, dtype=np.float64)
    valid = np.asarray(valid_cells, dtype=bool)
    if grid.ndim != 2 or valid.shape != grid.shape:
        raise ImageError(f"map_in (h, w) and valid_cells must have one shape, got {grid.shape} and {valid.shape}")
    h_in, w_in = grid.shape
    h, w = grid.shape if out_hw is None else out_hw
    cam, can = warp.camera, warp.canonical
    u = (np.arange(w) + 0.5) * cam.width_px / w - 0.5
    v = (np.arange(h) + 0.5) * cam.height_px / h - 0.5
    x = (warp.scale_x * u + warp.offset_x_px + 0.5) * w_in / can.width_px - 0.5
    y = (warp.scale_y * v + warp.offset_y_px + 0.5) * h_in / can.height_px - 0.5
    in_x, near_x, x0, x1, ax = _axis_weights(x, w_in)
    in_y, near_y, y0, y1, ay = _axis_weights(y, h_in)
    values = np.where(valid, grid, 0.0)
    weight = valid.astype(np.float64)
    num = np.zeros((h, w))
    den = np.zeros((h, w))
    for yi, wy in ((y0, 1.0 - ay), (y1, ay)):
        for xi, wx in ((x0, 1.0 - ax), (x1, ax)):
            wgt = wy[:, None] * wx[None, :] * weight[yi[:, None], xi[None, :]]
            num += wgt * values[yi[:, None], xi[None, :]]
            den += wgt
    ok = in_y[:, None] & in_x[None, :] & valid[near_y[:, None], near_x[None, :]] & (den > 0)
    out = np.full((h, w), np.nan)
    out[ok] = num[ok] / den[ok]
    return out.astype(np.float32)


def inv_depth_from_canonical(d_frac: np.ndarray, canonical: CanonicalCamera, baseline_m: float) -> np.ndarray:
    """Contract v2's metric conversion: ``inv_depth_per_m = d_frac · W_in / (fx_c · baseline_m)``.

    ``d_frac`` (any shape) is disparity as a fraction of the input width at the canonical focal
    length for the training baseline; the result (same shape, float64, 1/m) does not depend on
    the caller's camera. Non-positive ``d_frac`` gives 0.
    """
    return inv_depth_from_width_fraction(d_frac, canonical.fx_px, float(canonical.width_px), baseline_m)


# ----- training labels (pure numpy: the trainer turns them into tensors) -----

def warp_depth_labels(labels: np.ndarray, warp: CanonicalWarp, kind: LabelKind = "depth_m") -> np.ndarray:
    """A full-resolution label map of the caller's image, placed exactly on the input canvas.

    Nearest neighbour: each input pixel takes the caller pixel its centre falls in (no blending
    across depth edges); invalid labels (``<= 0`` or non-finite) and uncovered input pixels are 0.
    Depth and inverse depth are unchanged by the warp (a pixel's ray, hence its depth, does not
    depend on the image scale); a horizontal disparity in caller pixels is multiplied by ``sx``
    (the canonical focal length is ``sx·fx``).

    Args:
        labels: (H, W) float, the size of ``warp.camera``; 0 = no label.
        warp: from :func:`canonical_warp`.
        kind: ``"depth_m"``, ``"inv_depth_per_m"`` or ``"disparity_px"``.

    Returns:
        (H_in, W_in) float32 labels on the input canvas, 0 where there is none.
    """
    src = np.asarray(labels, dtype=np.float64)
    cam, can = warp.camera, warp.canonical
    if src.shape != (cam.height_px, cam.width_px):
        raise ImageError(f"labels must be ({cam.height_px}, {cam.width_px}) for this camera, got {src.shape}")
    if kind not in ("depth_m", "inv_depth_per_m", "disparity_px"):
        raise ImageError(f"kind must be depth_m, inv_depth_per_m or disparity_px, got {kind!r}")
    u = (np.arange(can.width_px) - warp.offset_x_px) / warp.scale_x
    v = (np.arange(can.height_px) - warp.offset_y_px) / warp.scale_y
    cols = np.clip(np.floor(u + 0.5), 0, cam.width_px - 1).astype(np.int64)
    rows = np.clip(np.floor(v + 0.5), 0, cam.height_px - 1).astype(np.int64)
    out = src[rows[:, None], cols[None, :]]
    out = np.where(valid_input_mask(warp) & np.isfinite(out) & (out > 0), out, 0.0)
    if kind == "disparity_px":
        out = out * warp.scale_x
    return out.astype(np.float32)


def canonical_d_frac(labels_in: np.ndarray, kind: LabelKind, canonical: CanonicalCamera,
                     baseline_m: float) -> np.ndarray:
    """Input-canvas labels (from :func:`warp_depth_labels`) -> contract-v2 ``d_frac`` targets.

    ``d_frac = fx_c · baseline_m / (depth_m · W_in)`` (the inverse of
    :func:`inv_depth_from_canonical`); for ``"disparity_px"`` labels (canvas pixels, rig of
    ``baseline_m``) simply ``disparity_px / W_in``. Returns float32, 0 where there is no label.
    """
    values = np.asarray(labels_in, dtype=np.float64)
    ok = np.isfinite(values) & (values > 0)
    if not (math.isfinite(baseline_m) and baseline_m > 0):
        raise DepthModelError(f"baseline_m must be finite and > 0, got {baseline_m}")
    safe = np.where(ok, values, 1.0)
    if kind == "depth_m":
        d = canonical.fx_px * baseline_m / (safe * canonical.width_px)
    elif kind == "inv_depth_per_m":
        d = safe * canonical.fx_px * baseline_m / canonical.width_px
    elif kind == "disparity_px":
        d = safe / canonical.width_px
    else:
        raise ImageError(f"kind must be depth_m, inv_depth_per_m or disparity_px, got {kind!r}")
    return np.where(ok, d, 0.0).astype(np.float32)
