"""The paper's four loss terms (Eq. 3–7), at every scale, fine to coarse.

Disparities are fractions of image width (``d_frac``), so one value means the same thing at
every scale: a shift of ``d_frac·W_s`` pixels at width ``W_s``, i.e. ``2·d_frac`` in
``grid_sample``'s normalized coordinates. Convention (positive disparities, right camera at +x):
``I_l(u) = I_r(u − D_l(u))`` and ``I_r(u) = I_l(u + D_r(u))``. ``ratio`` (B,) rescales the
predicted training-rig disparity to the pair's own rig (baseline / training baseline).

Scales: the network gives D3..D6; D0..D2 are bilinear upsamplings of D3 (as in the paper). Each
scale ``s`` compares images area-downsampled to ``H/2**s × W/2**s`` — so the photometric errors
visible only at fine scales (D0..D2) still teach the coarse D3 ("fine-to-coarse").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

TERMS = ("photo", "lr", "smooth", "sup")


@dataclass(frozen=True)
class LossWeights:
    """λp, λlr, λr, λs of Eq. 3 (paper: 1, 1, 0.1, 10)."""

    photo: float = 1.0
    lr: float = 1.0
    smooth: float = 0.1
    sup: float = 10.0


def warp_horizontal(image: torch.Tensor, shift_frac: torch.Tensor) -> torch.Tensor:
    """Sample ``image`` (B,C,H,W) at ``u + shift_frac·W`` (shift (B,1,H,W), fraction of width).

    Out-of-image samples replicate the border.
    """
    b, _, h, w = image.shape
    ys = torch.linspace(-1 + 1 / h, 1 - 1 / h, h, device=image.device, dtype=image.dtype)
    xs = torch.linspace(-1 + 1 / w, 1 - 1 / w, w, device=image.device, dtype=image.dtype)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    grid_x = gx.expand(b, h, w) + 2.0 * shift_frac[:, 0]
    grid = torch.stack([grid_x, gy.expand(b, h, w)], dim=-1)
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=False)


def ssim_distance(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(1 − SSIM)/2 per pixel with 3x3 means (Godard et al.), in [0, 1]."""
    c1, c2 = 0.01**2, 0.03**2
    mu_x, mu_y = F.avg_pool2d(x, 3, 1, 1), F.avg_pool2d(y, 3, 1, 1)
    sigma_x = F.avg_pool2d(x * x, 3, 1, 1) - mu_x**2
    sigma_y = F.avg_pool2d(y * y, 3, 1, 1) - mu_y**2
    sigma_xy = F.avg_pool2d(x * y, 3, 1, 1) - mu_x * mu_y
    ssim = ((2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sigma_x + sigma_y + c2))
    return ((1 - ssim) / 2).clamp(0, 1)


def weighted_mean(per_pixel: torch.Tensor, sample_weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of (B,C,H,W) values; with ``sample_weight`` (B,) the weighted mean of the per-sample
    means (0 when every weight is 0). Equal weights give the plain mean."""
    if sample_weight is None:
        return per_pixel.mean()
    per_sample = per_pixel.mean(dim=tuple(range(1, per_pixel.dim())))
    w = sample_weight.to(per_sample.dtype)
    return (per_sample * w).sum() / w.sum().clamp_min(1e-6)


def photometric(image: torch.Tensor, reconstruction: torch.Tensor, alpha: float = 0.85,
                sample_weight: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 4: mean of α·(1−SSIM)/2 + (1−α)·|I − Î| (``sample_weight``: see :func:`weighted_mean`)."""
    per_pixel = alpha * ssim_distance(image, reconstruction) + (1 - alpha) * (image - reconstruction).abs()
    return weighted_mean(per_pixel, sample_weight)


def lr_consistency(d_left: torch.Tensor, d_right: torch.Tensor,
                   sample_weight: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 5: |D_l(u) − D_r(u − D_l(u))| + |D_r(u) − D_l(u + D_r(u))|, mean."""
    right_in_left = warp_horizontal(d_right, -d_left)
    left_in_right = warp_horizontal(d_left, d_right)
    return (weighted_mean((d_left - right_in_left).abs(), sample_weight)
            + weighted_mean((d_right - left_in_right).abs(), sample_weight))


def edge_aware_smoothness(disp: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Eq. 6 on the mean-normalized disparity (scale-free, so it does not pull depth far)."""
    d = disp / (disp.mean(dim=(2, 3), keepdim=True) + 1e-7)
    dx, dy = (d[..., :, 1:] - d[..., :, :-1]).abs(), (d[..., 1:, :] - d[..., :-1, :]).abs()
    ix = (image[..., :, 1:] - image[..., :, :-1]).abs()
    iy = (image[..., 1:, :] - image[..., :-1, :]).abs()
    total = disp.new_zeros(())
    for grad_d, grad_i in ((dx, ix), (dy, iy)):
        if grad_d.numel():  # a 1-pixel-high/wide map has no gradient in that direction
            total = total + (grad_d * torch.exp(-grad_i)).mean()
    return total


def supervision(disp: torch.Tensor, target: torch.Tensor, huber_delta: float, log_space: bool = False,
                per_sample: bool = False) -> torch.Tensor:
    """Eq. 7: Huber(D − B) over pixels where the block-matching target is valid (> 0).

    ``log_space`` compares ``log D`` with ``log B`` instead (``huber_delta`` then is a relative
    error, 0.05 = 5 %): every depth counts by its *relative* error, as in the scale factors
    (s = ξ/z, eq. 12) and in abs-rel. In d_frac space a 50 % error at 40 m weighs about as much
    as a 4 % error at 3 m, so far depth is barely taught.

    ``per_sample``: average each sample over its own valid pixels, then over the samples that have
    any, so a sparse target (LiDAR: ~10 % of the cells) counts as much as a dense one; otherwise
    all valid pixels of the batch are averaged together.
    """
    valid = target > 0
    if not bool(valid.any()):
        return disp.sum() * 0.0
    if log_space:
        err = torch.log(disp.clamp_min(1e-5)) - torch.log(target.clamp_min(1e-12))
    else:
        err = disp - target
    per_pixel = F.huber_loss(err, torch.zeros_like(err), delta=huber_delta, reduction="none") / huber_delta
    if not per_sample:
        return per_pixel[valid].mean()
    dims = tuple(range(1, per_pixel.dim()))
    count = valid.sum(dim=dims)
    per = (per_pixel * valid).sum(dim=dims) / count.clamp_min(1)
    has = count > 0
    return per[has].mean()


def _down(x: torch.Tensor, factor: int) -> torch.Tensor:
    return x if factor == 1 else F.avg_pool2d(x, factor)


def _down_sparse(target: torch.Tensor, factor: int, min_valid: float | torch.Tensor = 0.5,
                 pooling: str = "mean") -> torch.Tensor:
    """Mean (or median) of the valid (> 0) values per ``factor``² cell; 0 where fewer than
    ``min_valid`` of the cell are valid (a number, or (B,1,1,1) per sample; a tiny value keeps
    every cell with one valid value).

    ``median`` is what the SGBM oracle of ``bench/landmark_depth.py`` scores (within 4 % at the
    SLAM's corners): a cell straddling a depth edge takes the majority surface's disparity, where
    the mean of disparities leans to the nearer surface (far cells beside near ones read near).
    """
    if factor == 1:
        return target
    valid = (target > 0).to(target.dtype)
    den = F.avg_pool2d(valid, factor)
    if pooling == "median":
        b, c, h, w = target.shape
        cells = target.reshape(b, c, h // factor, factor, w // factor, factor).permute(0, 1, 2, 4, 3, 5)
        cells = cells.reshape(b, c, h // factor, w // factor, factor * factor)
        value = torch.nanmedian(torch.where(cells > 0, cells, torch.full_like(cells, float("nan"))), dim=-1).values
        value = torch.nan_to_num(value, nan=0.0)
    else:
        value = F.avg_pool2d(target * valid, factor) / den.clamp_min(1e-6)
    return torch.where((den >= min_valid) & (den > 0), value, torch.zeros_like(value))


def disparity_pyramid(outputs: list[torch.Tensor], scales: tuple[int, ...], base_hw: tuple[int, int]
                      ) -> dict[int, torch.Tensor]:
    """Map scale s -> (B,2,H/2**s,W/2**s): D3..D6 from the net, D0..D2 upsampled from D3."""
    h, w = base_hw
    pyramid: dict[int, torch.Tensor] = {}
    for s in scales:
        if s >= 3:
            pyramid[s] = outputs[s - 3]
        else:
            pyramid[s] = F.interpolate(outputs[0], size=(h >> s, w >> s), mode="bilinear", align_corners=False)
    return pyramid


def total_loss(outputs: list[torch.Tensor], left: torch.Tensor, right: torch.Tensor, bm_left: torch.Tensor,
               bm_right: torch.Tensor, ratio: torch.Tensor, weights: LossWeights = LossWeights(),
               scales: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6), huber_delta: float = 0.005,
               sup_log_space: bool = False, stereo: torch.Tensor | None = None,
               label_pooling: str = "mean") -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 3 summed over ``scales``. Returns (loss, per-term sums for logging).

    ``stereo`` (B,): 1 for a stereo pair, 0 for a supervision-only image (LiDAR depth, no right
    image): the photometric and left-right terms average over the stereo pairs only, a
    supervision-only target keeps every coarse cell with one valid value (LiDAR is sparse), and
    the supervision term averages per sample (``supervision(per_sample=True)``).
    ``label_pooling``: how the block-matching target is reduced to coarse scales (:func:`_down_sparse`).
    """
    pyramid = disparity_pyramid(outputs, scales, left.shape[-2:])
    r = ratio.view(-1, 1, 1, 1).to(left.dtype)
    min_valid: float | torch.Tensor = 0.5
    if stereo is not None:
        min_valid = torch.where(stereo.view(-1, 1, 1, 1) > 0, 0.5, 1e-6).to(left.dtype)
    sums = {t: left.new_zeros(()) for t in TERMS}
    for s, disp in pyramid.items():
        f = 2**s
        il, ir = _down(left, f), _down(right, f)
        dl, dr = disp[:, :1], disp[:, 1:]
        dl_pair, dr_pair = dl * r, dr * r
        left_hat = warp_horizontal(ir, -dl_pair)
        right_hat = warp_horizontal(il, dr_pair)
        sums["photo"] = (sums["photo"] + photometric(il, left_hat, sample_weight=stereo)
                         + photometric(ir, right_hat, sample_weight=stereo))
        sums["lr"] = sums["lr"] + lr_consistency(dl_pair, dr_pair, stereo)
        sums["smooth"] = sums["smooth"] + (edge_aware_smoothness(dl, il) + edge_aware_smoothness(dr, ir)) / f
        if weights.sup > 0:
            bl = _down_sparse(bm_left, f, min_valid, label_pooling)
            br = _down_sparse(bm_right, f, min_valid, label_pooling)
            per_sample = stereo is not None
            sums["sup"] = (sums["sup"] + supervision(dl_pair, bl, huber_delta, sup_log_space, per_sample)
                           + supervision(dr_pair, br, huber_delta, sup_log_space, per_sample))
    loss = (weights.photo * sums["photo"] + weights.lr * sums["lr"] + weights.smooth * sums["smooth"]
            + weights.sup * sums["sup"])
    return loss, {t: float(v.detach()) for t, v in sums.items()}
