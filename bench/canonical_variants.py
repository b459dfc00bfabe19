"""Crops and rescales of one frame, and how a variant's depth map compares with the full frame's.

The pure half of :mod:`bench.canonical_invariance` (numpy + OpenCV, no files, no models).

A **variant** is an image made from a frame by a centre crop of its width (full height) or a
rescale, with the camera of that image: a crop keeps ``fx, fy, cy`` and shifts ``cx`` by the
crop's left edge; a rescale uses :meth:`PinholeCamera.resized` (pixel-centre convention,
``u → (u + 0.5)·s − 0.5``, ``docs/conventions.md``). Both images look along the same rays, so a
variant pixel maps to the full image's pixel on the same ray (:func:`same_ray_px`) through the
two cameras; a wrong camera (e.g. a crop whose ``cx`` was not shifted) maps it to the wrong
pixel, and :func:`depth_ratios` then compares different scene points.

Maps are (h, w) metric inverse depth (1/m) on grids spanning their own image, cell ``(i, j)``
centred at pixel ``((j + 0.5)·W/w − 0.5, (i + 0.5)·H/h − 0.5)`` (:mod:`metricslam.depth.sample`),
NaN where the model saw nothing (contract v2).

Example::

    >>> for var in make_variants(frame.image, frame.camera):
    ...     inv_var = model.predict_inv_depth(var.image, camera=var.camera).inv_depth_per_m
    ...     ratios, valid = depth_ratios(inv_full, frame.camera, inv_var, var.camera)
    ...     ratio_stats(ratios)["median"]          # 1.0 for a model that is crop/scale invariant
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.depth.sample import sample_map

#: (name, kind, factor): centre crops keeping a fraction of the width, rescales by a factor
VARIANT_SPECS: tuple[tuple[str, str, float], ...] = (
    ("crop_w1/2", "crop", 1 / 2),
    ("crop_w2/3", "crop", 2 / 3),
    ("scale_0.5x", "scale", 0.5),
    ("scale_2x", "scale", 2.0),
)
#: an exact-depth cell needs at least this fraction of its pixels with depth (sky has none)
EXACT_MIN_FRACTION = 0.5


@dataclass(frozen=True)
class Variant:
    """An image made from a frame and the camera of that image.

    Attributes:
        name: e.g. ``"crop_w1/2"``.
        image: (H', W') uint8, gray or RGB as the frame.
        camera: intrinsics of ``image`` (its own size, pixel centres at integers).
    """

    name: str
    image: np.ndarray
    camera: PinholeCamera


def centre_crop_width(image: np.ndarray, camera: PinholeCamera, keep: float, name: str = "crop") -> Variant:
    """The centre ``keep`` (0, 1] of the width, full height; ``cx`` shifts by the left edge ``x0``."""
    height, width = image.shape[:2]
    new_width = max(1, round(width * keep))
    x0 = (width - new_width) // 2
    cam = PinholeCamera(fx_px=camera.fx_px, fy_px=camera.fy_px, cx_px=camera.cx_px - x0,
                        cy_px=camera.cy_px, width_px=new_width, height_px=height)
    return Variant(name, np.ascontiguousarray(image[:, x0:x0 + new_width]), cam)


def rescale(image: np.ndarray, camera: PinholeCamera, factor: float, name: str = "scale") -> Variant:
    """``cv2.resize`` by ``factor`` (area when shrinking, bilinear when growing);
    the camera from :meth:`PinholeCamera.resized` at the rounded size."""
    height, width = image.shape[:2]
    size = (max(1, round(width * factor)), max(1, round(height * factor)))
    interpolation = cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR
    return Variant(name, cv2.resize(image, size, interpolation=interpolation), camera.resized(*size))


def make_variants(image: np.ndarray, camera: PinholeCamera,
                  specs: tuple[tuple[str, str, float], ...] = VARIANT_SPECS) -> list[Variant]:
    """The variants of :data:`VARIANT_SPECS` of one frame."""
    out = []
    for name, kind, factor in specs:
        make = centre_crop_width if kind == "crop" else rescale
        out.append(make(image, camera, factor, name))
    return out


def cell_centres_px(out_hw: tuple[int, int], width_px: int, height_px: int) -> np.ndarray:
    """(h·w, 2) pixel coordinates (u, v) of the cell centres of an (h, w) grid over a W x H image,
    row-major (cell ``(i, j)`` is row ``i·w + j``)."""
    h, w = out_hw
    u = (np.arange(w) + 0.5) * width_px / w - 0.5
    v = (np.arange(h) + 0.5) * height_px / h - 0.5
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def same_ray_px(uv_px: np.ndarray, camera_from: PinholeCamera, camera_to: PinholeCamera) -> np.ndarray:
    """Pixels (N, 2) of ``camera_from`` -> the pixels of ``camera_to`` on the same rays (N, 2)."""
    return camera_to.project(camera_from.unproject(uv_px, 1.0))


def depth_ratios(inv_full: np.ndarray, camera_full: PinholeCamera, inv_variant: np.ndarray,
                 camera_variant: PinholeCamera) -> tuple[np.ndarray, float]:
    """``depth_variant / depth_full`` at every valid cell of the variant's map.

    Each finite cell of ``inv_variant`` (its centre in the variant's pixels) is mapped to the full
    image's pixels on the same ray and ``inv_full`` is sampled there bilinearly
    (:func:`~metricslam.depth.sample.sample_map`; a NaN neighbour gives NaN and the cell is
    dropped). Inverse depth is what the network predicts, so it is what gets interpolated.

    Args:
        inv_full: (h, w) inverse depth (1/m) over the full image of ``camera_full``.
        camera_full: the full frame's camera.
        inv_variant: (h', w') inverse depth over the variant's image.
        camera_variant: the variant image's camera.

    Returns:
        ``ratios`` (N,) float64, finite and > 0, and the fraction of the variant's cells that
        are valid (finite).
    """
    inv_var = np.asarray(inv_variant, dtype=np.float64)
    valid = np.isfinite(inv_var)
    uv_var = cell_centres_px(inv_var.shape, camera_variant.width_px, camera_variant.height_px)[valid.ravel()]
    uv_full = same_ray_px(uv_var, camera_variant, camera_full)
    z_full = sample_map(inv_full, uv_full, (camera_full.width_px, camera_full.height_px))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = z_full / inv_var[valid]
    keep = np.isfinite(ratios) & (ratios > 0)
    return ratios[keep], float(valid.mean())


def ratio_stats(ratios: np.ndarray) -> dict:
    """Median, quartiles, IQR and count of ``ratios`` (None when there are none)."""
    r = np.asarray(ratios, dtype=np.float64)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return {"median": None, "q25": None, "q75": None, "iqr": None, "n": 0}
    q25, med, q75 = np.percentile(r, [25, 50, 75])
    return {"median": float(med), "q25": float(q25), "q75": float(q75), "iqr": float(q75 - q25), "n": int(r.size)}


def exact_depth_cells(depth_m: np.ndarray, out_hw: tuple[int, int],
                      min_fraction: float = EXACT_MIN_FRACTION) -> np.ndarray:
    """Per-cell median of an exact depth image on an (h, w) grid spanning it.

    A pixel belongs to the cell its centre falls in (cell ``j`` spans ``[j·W/w, (j+1)·W/w)`` in
    pixel-corner coordinates, the layout of the model's output grid for this image).

    Args:
        depth_m: (H, W) metres, 0 (or non-finite) = no depth.
        out_hw: (h, w) grid.
        min_fraction: a cell needs at least this fraction of its pixels with depth.

    Returns:
        (h, w) float64 median depth (m) of the cell's pixels with depth; NaN for too few.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    big_h, big_w = depth.shape
    h, w = out_hw
    rows = np.minimum(((np.arange(big_h) + 0.5) * h / big_h).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(big_w) + 0.5) * w / big_w).astype(np.int64), w - 1)
    label = (rows[:, None] * w + cols[None, :]).ravel()
    values = depth.ravel()
    ok = np.isfinite(values) & (values > 0)
    counts = np.bincount(label, minlength=h * w)
    out = np.full(h * w, np.nan)
    order = np.lexsort((values[ok], label[ok]))  # by cell, then by depth
    lab, val = label[ok][order], values[ok][order]
    starts = np.searchsorted(lab, np.arange(h * w), side="left")
    ends = np.searchsorted(lab, np.arange(h * w), side="right")
    for cell in np.flatnonzero((ends - starts) >= np.maximum(min_fraction * counts, 1)):
        out[cell] = np.median(val[starts[cell]:ends[cell]])
    return out.reshape(h, w)


def net_over_exact(inv_net: np.ndarray, exact_depth: np.ndarray) -> tuple[np.ndarray, float]:
    """``depth_net / depth_exact`` at cells valid in both maps (same grid), and the fraction of
    the network's cells that are valid (finite)."""
    inv = np.asarray(inv_net, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = (1.0 / inv) / np.asarray(exact_depth, dtype=np.float64)
    keep = np.isfinite(ratios) & (ratios > 0)
    return ratios[keep], float(np.isfinite(inv).mean())
