"""Training pairs: rectified stereo from KITTI-layout folders, with block-matching supervision.

A *KITTI-layout sequence folder* holds ``image_0/`` (left), ``image_1/`` (right), ``calib.txt``
(``P0``/``P1`` 3x4; baseline = ``-P1[0,3] / P1[0,0]``). KITTI odometry sequences and the
output of ``metricslam synth`` share it.

:func:`build_cache` turns sequences into one compact ``.npz`` per sequence:

* ``left``, ``right``: (N, H, W) uint8 gray at the network's base size (L0, 256x512 by default),
  the whole image resized (no crop);
* ``bm_left``, ``bm_right``: (N, H, W) float16 block-matching disparity as a **fraction of image
  width** (0 = invalid), computed by OpenCV StereoSGBM on the **full-resolution** pair with a
  left-right check (the right map from the mirrored, swapped pair);
* ``baseline_ratio``: this rig's baseline / the model's training baseline. The network predicts
  ``d_frac`` for the training baseline; photometric warps on this pair use ``d_frac·ratio``.

:class:`StereoPairs` serves (left, right, bm_left, bm_right, ratio) tensors and
:func:`augment` applies flip-with-swap, gamma and brightness on a batch; :func:`zoom` magnifies a
batch about its centre row with the labels scaled to match (scale augmentation); :func:`pad_window`
pads all but a centred window, as contract v2 pads a narrower camera (field-of-view augmentation).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from metricslam.datasets._common import IMAGE_EXTS
from metricslam.depth.canonical import PAD_VALUE_U8
from metricslam.errors import TrainingError
from metricslam.stereo import block_matching_pair


@dataclass(frozen=True)
class StereoSequence:
    """Paths and calibration of one KITTI-layout stereo sequence (full resolution)."""

    name: str
    left_paths: tuple[Path, ...]
    right_paths: tuple[Path, ...]
    fx_px: float
    baseline_m: float
    #: ``depth_0/*.png`` of a synthetic sequence (uint16, metres x 256, 0 = none), else empty
    depth_paths: tuple[Path, ...] = ()


def _read_calib(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise TrainingError(f"{path} is missing: a stereo sequence folder needs calib.txt with P0 and P1")
    out: dict[str, np.ndarray] = {}
    for line in path.read_text().splitlines():
        if ":" not in line or line.lstrip().startswith("#"):
            continue
        key, values = line.split(":", 1)
        try:
            out[key.strip()] = np.array([float(v) for v in values.split()])
        except ValueError:
            continue
    return out


def read_stereo_sequence(folder: str | Path, frame_step: int = 1) -> StereoSequence:
    """Read a KITTI-layout folder (``image_0``, ``image_1``, ``calib.txt``)."""
    root = Path(folder)
    calib = _read_calib(root / "calib.txt")
    if "P0" not in calib or "P1" not in calib or calib["P1"].size != 12:
        raise TrainingError(f"{root / 'calib.txt'} needs P0 and P1 lines with 12 numbers each")
    P1 = calib["P1"].reshape(3, 4)
    fx_px = float(P1[0, 0])
    baseline_m = float(-P1[0, 3] / P1[0, 0])
    if not baseline_m > 0:
        raise TrainingError(f"{root}: P1 gives baseline {baseline_m} m; expected the right camera at +x")
    lefts = sorted(p for p in (root / "image_0").glob("*") if p.suffix.lower() in IMAGE_EXTS)
    rights = [root / "image_1" / p.name for p in lefts]
    if not lefts or not all(p.is_file() for p in rights):
        raise TrainingError(f"{root}: needs matching image_0/ and image_1/ frames "
                            f"({'/'.join(IMAGE_EXTS)}, same names)")
    lefts, rights = lefts[::frame_step], rights[::frame_step]
    depths = [root / "depth_0" / (p.stem + ".png") for p in lefts]
    depths = depths if all(p.is_file() for p in depths) else []
    name = root.name if not re.fullmatch(r"\d+", root.name) else f"kitti{root.name}"
    return StereoSequence(name, tuple(lefts), tuple(rights), fx_px, baseline_m, tuple(depths))


def read_gray(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise TrainingError(f"cannot read image {path}")
    return image


def exact_disparity_pair(depth_left_m: np.ndarray, fx_px: float,
                         baseline_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact disparities (px, float32, 0 = invalid) of a rendered rectified pair from its left
    depth map (metres, 0 = sky/none).

    The left map is ``fx·B/z``. The right map splats every left pixel to ``u − d`` keeping the
    largest disparity (the nearest surface); right pixels no left pixel lands on are 0 (seen by
    the right camera only), except one-pixel rounding gaps between two similar neighbours, which
    take the smaller neighbour.
    """
    depth = np.asarray(depth_left_m, np.float32)
    d_left = np.where(depth > 0, fx_px * baseline_m / np.maximum(depth, 1e-6), 0.0).astype(np.float32)
    h, w = depth.shape
    rows, cols = np.nonzero(d_left > 0)
    u_r = np.rint(cols - d_left[rows, cols]).astype(int)
    ok = (u_r >= 0) & (u_r < w)
    d_right = np.zeros_like(d_left)
    np.maximum.at(d_right, (rows[ok], u_r[ok]), d_left[rows[ok], cols[ok]])
    lft = np.pad(d_right, ((0, 0), (1, 0)))[:, :-1]
    rgt = np.pad(d_right, ((0, 0), (0, 1)))[:, 1:]
    gap = (d_right == 0) & (lft > 0) & (rgt > 0) & (np.abs(lft - rgt) <= 1.0)
    d_right[gap] = np.minimum(lft, rgt)[gap]
    return d_left, d_right


def _resize_sparse(d_frac: np.ndarray, height: int, width: int, min_valid_fraction: float = 0.5) -> np.ndarray:
    """Masked area-resize of a sparse map (0 = invalid): mean of the valid source pixels per cell,
    0 where at most ``min_valid_fraction`` of the cell is valid (0 keeps every cell with one)."""
    valid = (d_frac > 0).astype(np.float32)
    num = cv2.resize(d_frac * valid, (width, height), interpolation=cv2.INTER_AREA)
    den = cv2.resize(valid, (width, height), interpolation=cv2.INTER_AREA)
    out = np.where(den > min_valid_fraction, num / np.maximum(den, 1e-6), 0.0)
    return out.astype(np.float32)


def correct_disparity_offset(right: np.ndarray, offset_px: float) -> np.ndarray:
    """Shift a rectified right image so that a pair whose observed disparities are ``true +
    offset_px`` (a rectification/calibration error of the pair) shows the true ones:
    ``right'(u) = right(u − offset_px)`` (bilinear, border replicated)."""
    if offset_px == 0:
        return right
    shift = np.float32([[1, 0, offset_px], [0, 1, 0]])
    return cv2.warpAffine(right, shift, (right.shape[1], right.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)


def build_cache(sequence: StereoSequence, out_path: str | Path, train_baseline_m: float,
                height: int = 256, width: int = 512, num_disparities: int = 128,
                exact_synthetic: bool = False, disparity_offset_px: float = 0.0) -> Path:
    """Write the compact training cache of one sequence (see module docstring).

    ``exact_synthetic``: a sequence with ``depth_paths`` (rendered) is supervised with its exact
    disparity (:func:`exact_disparity_pair`) instead of SGBM — dense, also on untextured surfaces
    (truck sides, walls) where block matching has nothing to match.

    ``disparity_offset_px``: the pair's measured disparity offset (observed − true, full-resolution
    pixels; ``TrainConfig.disparity_offsets_px``); the right image is shifted by it
    (:func:`correct_disparity_offset`) before block matching and caching, so the SGBM labels and
    the photometric terms both see the corrected pair.
    """
    from tqdm import tqdm

    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    n = len(sequence.left_paths)
    left = np.empty((n, height, width), np.uint8)
    right = np.empty((n, height, width), np.uint8)
    bm_left = np.empty((n, height, width), np.float16)
    bm_right = np.empty((n, height, width), np.float16)
    for i in tqdm(range(n), desc=f"cache {sequence.name}", leave=False):
        full_l = read_gray(sequence.left_paths[i])
        full_r = correct_disparity_offset(read_gray(sequence.right_paths[i]), disparity_offset_px)
        if full_l.shape != full_r.shape:
            raise TrainingError(f"{sequence.left_paths[i]} and its right image differ in size")
        w_full = full_l.shape[1]
        if exact_synthetic and sequence.depth_paths:
            depth_m = cv2.imread(str(sequence.depth_paths[i]), cv2.IMREAD_UNCHANGED)
            if depth_m is None or depth_m.shape != full_l.shape:
                raise TrainingError(f"{sequence.depth_paths[i]}: missing or not the size of its image")
            d_l, d_r = exact_disparity_pair(depth_m.astype(np.float32) / 256.0, sequence.fx_px,
                                            sequence.baseline_m)
        else:
            d_l, d_r = block_matching_pair(full_l, full_r, num_disparities)
        left[i] = cv2.resize(full_l, (width, height), interpolation=cv2.INTER_AREA)
        right[i] = cv2.resize(full_r, (width, height), interpolation=cv2.INTER_AREA)
        bm_left[i] = _resize_sparse(d_l / w_full, height, width)
        bm_right[i] = _resize_sparse(d_r / w_full, height, width)
    np.savez_compressed(out, left=left, right=right, bm_left=bm_left, bm_right=bm_right,
                        baseline_ratio=np.float32(sequence.baseline_m / train_baseline_m),
                        name=sequence.name, fx_px=np.float32(sequence.fx_px))
    return out


#: a depth-frames cache keeps a target cell when any LiDAR point falls in it (projected LiDAR
#: covers a few per cent of the pixels, so the stereo caches' "half the cell valid" rule would
#: keep almost none)
DEPTH_MIN_VALID_FRACTION = 0.0


def build_depth_cache(folder: str | Path, out_path: str | Path, train_baseline_m: float, first: int = 0,
                      stop: int | None = None, height: int = 256, width: int = 512) -> Path:
    """Cache single images with metric depth (KITTI-raw layout, e.g. projected LiDAR) as
    supervision-only "pairs": no ``right`` (:class:`StereoPairs` serves ``left`` in its place; never
    used, ``stereo`` is False), ``bm_left``
    = the depth as training-rig ``d_frac = fx·B_train / (depth·W)``, ``bm_right`` = 0.

    Frames ``first <= i < stop`` of the folder; colour images are converted to gray.
    """
    from metricslam.datasets.kitti_depth import KittiRawDepth
    from metricslam.errors import MetricSlamError

    try:
        seq = KittiRawDepth(folder)
    except MetricSlamError as exc:
        raise TrainingError(f"depth_frames folder {folder}: {exc}") from exc
    indices = list(range(first, min(stop if stop is not None else len(seq), len(seq))))
    if not indices:
        raise TrainingError(f"depth_frames folder {folder}: no frames in [{first}, {stop})")
    n = len(indices)
    left = np.empty((n, height, width), np.uint8)
    target = np.empty((n, height, width), np.float16)
    for k, i in enumerate(indices):
        frame = seq[i]
        if frame.depth_m is None:
            raise TrainingError(f"depth_frames folder {folder}: frame {i} has no depth image")
        gray = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)
        w_full = gray.shape[1]
        d_frac = np.where(frame.depth_m > 0, frame.camera.fx_px * train_baseline_m
                          / (np.maximum(frame.depth_m, 1e-6) * w_full), 0.0).astype(np.float32)
        left[k] = cv2.resize(gray, (width, height), interpolation=cv2.INTER_AREA)
        target[k] = _resize_sparse(d_frac, height, width, DEPTH_MIN_VALID_FRACTION)
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, left=left, bm_left=target, bm_right=np.zeros_like(target),
                        baseline_ratio=np.float32(1.0), stereo=np.bool_(False), name=Path(folder).name,
                        fx_px=np.float32(seq.camera.fx_px))
    return out


class StereoPairs(torch.utils.data.Dataset):
    """All pairs of several cache files; items are float tensors in [0, 1] / d_frac.

    Item: ``(left (1,H,W), right (1,H,W), bm_left (1,H,W), bm_right (1,H,W), ratio (), stereo ())``;
    ``stereo`` is 1.0 for a stereo pair and 0.0 for a supervision-only image (:func:`build_depth_cache`).
    """

    def __init__(self, cache_paths: list[str | Path], label_scales: list[float] | None = None) -> None:
        """``label_scales`` (one per cache, default 1): the pair's ``ratio`` is divided by it. The
        labels are this pair's own disparities and the loss compares them with ``output · ratio``
        (the warp uses the same product), so dividing ``ratio`` by ``k`` asks the network for ``k``
        times the training-baseline d_frac — contract v2's disparity at the canonical focal length,
        ``k = fx_canonical / fx_input`` — while the pair is still warped by its true disparity."""
        if not cache_paths:
            raise TrainingError("no training caches given: list at least one sequence in the config")
        parts = []
        for path in cache_paths:
            p = Path(path)
            if not p.is_file():
                raise TrainingError(f"cache {p} does not exist: build it with `metricslam train` (prepare step)")
            with np.load(p) as z:
                part = {k: z[k] for k in ("left", "bm_left", "bm_right", "baseline_ratio")}
                part["right"] = z["right"] if "right" in z.files else part["left"]  # depth frames: none
                part["stereo"] = bool(z["stereo"]) if "stereo" in z.files else True
            label_scale = 1.0 if label_scales is None else float(label_scales[len(parts)])
            part["baseline_ratio"] = np.float32(part["baseline_ratio"] / label_scale)
            parts.append(part)
        self.left = np.concatenate([p["left"] for p in parts])
        self.right = np.concatenate([p["right"] for p in parts])
        self.bm_left = np.concatenate([p["bm_left"] for p in parts])
        self.bm_right = np.concatenate([p["bm_right"] for p in parts])
        self.ratio = np.concatenate([np.full(len(p["left"]), p["baseline_ratio"], np.float32) for p in parts])
        self.stereo = np.concatenate([np.full(len(p["left"]), p["stereo"], np.float32) for p in parts])

    def __len__(self) -> int:
        return len(self.left)

    def __getitem__(self, i: int):
        as_t = lambda a, s=1.0: torch.from_numpy(a[i].astype(np.float32) * s)[None]  # noqa: E731
        return (as_t(self.left, 1 / 255), as_t(self.right, 1 / 255), as_t(self.bm_left), as_t(self.bm_right),
                torch.tensor(self.ratio[i]), torch.tensor(self.stereo[i]))


def augment(left: torch.Tensor, right: torch.Tensor, bm_left: torch.Tensor, bm_right: torch.Tensor,
            generator: torch.Generator | None = None, p_flip: float = 0.5,
            gamma_range: tuple[float, float] = (0.8, 1.2), brightness_range: tuple[float, float] = (0.5, 2.0)):
    """Batch augmentation (B,1,H,W) in [0,1]: flip-with-swap, gamma, brightness.

    Flip-with-swap: mirroring a rectified pair turns the left image into a valid *right* image,
    so the mirrored pair is (mirror(right), mirror(left)) and the block-matching maps swap too.
    Gamma and brightness are drawn once per pair (both images alike, so photoconsistency holds).
    Colour shifts reduce to brightness for one gray channel.
    """
    b = left.shape[0]
    flip = (torch.rand(b, generator=generator) < p_flip).view(b, 1, 1, 1)
    new_left = torch.where(flip, right.flip(-1), left)
    new_right = torch.where(flip, left.flip(-1), right)
    new_bm_left = torch.where(flip, bm_right.flip(-1), bm_left)
    new_bm_right = torch.where(flip, bm_left.flip(-1), bm_right)
    lo, hi = gamma_range
    gamma = (lo + (hi - lo) * torch.rand(b, generator=generator)).view(b, 1, 1, 1)
    lo, hi = brightness_range
    bright = (lo + (hi - lo) * torch.rand(b, generator=generator)).view(b, 1, 1, 1)
    new_left = (new_left.clamp(0, 1) ** gamma * bright).clamp(0, 1)
    new_right = (new_right.clamp(0, 1) ** gamma * bright).clamp(0, 1)
    return new_left, new_right, new_bm_left, new_bm_right


def zoom(left: torch.Tensor, right: torch.Tensor, bm_left: torch.Tensor, bm_right: torch.Tensor,
         generator: torch.Generator | None = None, p_zoom: float = 0.0,
         zoom_range: tuple[float, float] = (1.0, 1.0)):
    """Scale augmentation (B,1,H,W): magnify a pair by ``s`` and multiply its d_frac labels by ``s``.

    For each sample, with probability ``p_zoom``, ``s`` is drawn log-uniformly from ``zoom_range``
    (>= 1) and the central ``1/s`` of both images is resampled to the full size (bilinear; labels
    nearest, 0 stays invalid). The window keeps the centre row (the horizon, i.e. the camera's
    pitch and height cues, stays where the contract's camera has it) and moves sideways at random
    within the image (a yaw, harmless). Why the labels scale by ``s``: a camera of focal ``s·f``
    sees a point ``(X, Y, Z)`` where a camera of focal ``f`` sees ``(X, Y, Z/s)`` (u = s·f·X/Z =
    f·X/(Z/s)); the magnified image is therefore exactly the original camera's view of a scene whose
    depths are divided by ``s`` — same ground-plane geometry (camera height), disparities ×s. Both
    images of the pair use the same window, so in-image disparities scale by ``s`` like the labels
    and the photometric warp stays consistent. ``s = 1`` returns the inputs unchanged.
    """
    b = left.shape[0]
    lo, hi = zoom_range
    if p_zoom <= 0 or hi <= 1.0:
        return left, right, bm_left, bm_right
    u = torch.rand(b, generator=generator)
    s = torch.exp(np.log(lo) + (np.log(hi) - np.log(lo)) * u)
    s = torch.where(torch.rand(b, generator=generator) < p_zoom, s, torch.ones_like(s))
    shift = (torch.rand(b, generator=generator) * 2 - 1) * (1 - 1 / s)
    theta = torch.zeros(b, 2, 3, dtype=left.dtype)
    theta[:, 0, 0] = 1 / s
    theta[:, 1, 1] = 1 / s
    theta[:, 0, 2] = shift
    grid = F.affine_grid(theta, list(left.shape), align_corners=False)
    warp = lambda x, mode: F.grid_sample(x, grid, mode=mode, padding_mode="border", align_corners=False)  # noqa: E731
    scale = s.view(b, 1, 1, 1).to(left.dtype)
    return (warp(left, "bilinear"), warp(right, "bilinear"),
            warp(bm_left, "nearest") * scale, warp(bm_right, "nearest") * scale)


def pad_window(left: torch.Tensor, right: torch.Tensor, bm_left: torch.Tensor, bm_right: torch.Tensor,
               generator: torch.Generator | None = None, p_pad: float = 0.0,
               width_range: tuple[float, float] = (0.35, 1.0), height_range: tuple[float, float] = (0.5, 1.0),
               pad_value: float = PAD_VALUE_U8 / 255.0):
    """Field-of-view augmentation (B,1,H,W) for the canonical camera (contract v2).

    With probability ``p_pad`` per pair, only a centred window (width and height fractions drawn
    uniformly from the ranges; the centre jittered by up to 2 % of the size, as principal points
    are) keeps its pixels: outside it both images take ``pad_value`` (what
    :func:`metricslam.depth.canonical.to_canonical` pads with, in [0, 1]) and the labels 0
    (no supervision). That is exactly what inference feeds the network for a camera with a
    narrower field of view at the canonical focal length; the disparities inside are unchanged.
    """
    b, _, h, w = left.shape
    if p_pad <= 0:
        return left, right, bm_left, bm_right
    rand = lambda: torch.rand(b, generator=generator)  # noqa: E731
    apply = rand() < p_pad
    fw = width_range[0] + (width_range[1] - width_range[0]) * rand()
    fh = height_range[0] + (height_range[1] - height_range[0]) * rand()
    cx = w / 2 + (rand() * 2 - 1) * 0.02 * w
    cy = h / 2 + (rand() * 2 - 1) * 0.02 * h
    u = torch.arange(w, dtype=left.dtype).view(1, 1, 1, w) + 0.5
    v = torch.arange(h, dtype=left.dtype).view(1, 1, h, 1) + 0.5
    inside = ((u - cx.view(b, 1, 1, 1)).abs() <= (fw * w / 2).view(b, 1, 1, 1)) & \
        ((v - cy.view(b, 1, 1, 1)).abs() <= (fh * h / 2).view(b, 1, 1, 1))
    keep = inside | ~apply.view(b, 1, 1, 1)
    pad = torch.full_like(left, pad_value)
    return (torch.where(keep, left, pad), torch.where(keep, right, pad),
            torch.where(keep, bm_left, torch.zeros_like(bm_left)), torch.where(keep, bm_right, torch.zeros_like(bm_right)))
