"""Scale augmentation (metricslam_train.data.zoom): known answers on a synthetic rectified pair."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from metricslam_train.data import zoom  # noqa: E402

H, W = 64, 128


def _pair(disp_px: float):
    """Left = a horizontal sinusoid, right = left shifted by ``disp_px`` (rectified, constant disparity)."""
    u = np.arange(W, dtype=np.float32)
    row = 0.5 + 0.4 * np.sin(u / 3.0) * np.cos(u / 7.0)
    left = np.tile(row, (H, 1))
    right = np.tile(0.5 + 0.4 * np.sin((u + disp_px) / 3.0) * np.cos((u + disp_px) / 7.0), (H, 1))
    as_t = lambda a: torch.from_numpy(a)[None, None]  # noqa: E731
    labels = np.full((H, W), disp_px / W, np.float32)
    labels[:, :10] = 0.0  # invalid stays invalid
    return as_t(left), as_t(right), as_t(labels), as_t(labels.copy())


def _best_shift(left: np.ndarray, right: np.ndarray) -> float:
    """Disparity (px) that best maps right onto left along the central row, 0.05 px steps."""
    u = np.arange(W, dtype=np.float64)
    row_l, row_r = left[H // 2, 20:-20], right[H // 2]
    shifts = np.arange(0.0, 12.0, 0.05)
    errs = [np.mean((row_l - np.interp(u[20:-20] - d, u, row_r)) ** 2) for d in shifts]
    return float(shifts[int(np.argmin(errs))])


def test_zoom_off_returns_inputs():
    pair = _pair(3.0)
    out = zoom(*pair, torch.Generator().manual_seed(0), p_zoom=0.0, zoom_range=(1.0, 2.0))
    for a, b in zip(pair, out, strict=True):
        assert a is b


def test_zoom_scales_labels_and_image_disparity_alike():
    left, right, bl, br = _pair(3.0)
    gen = torch.Generator().manual_seed(1)
    zl, zr, zbl, zbr = zoom(left, right, bl, br, gen, p_zoom=1.0, zoom_range=(2.0, 2.0))
    valid = zbl[0, 0] > 0
    # labels: every valid value is exactly twice the original d_frac
    assert torch.allclose(zbl[0, 0][valid], torch.full_like(zbl[0, 0][valid], 2 * 3.0 / W))
    assert torch.allclose(zbr[0, 0][zbr[0, 0] > 0], torch.full_like(zbr[0, 0][zbr[0, 0] > 0], 2 * 3.0 / W))
    # the images' own disparity doubled too (the photometric warp stays consistent)
    assert _best_shift(left[0, 0].numpy(), right[0, 0].numpy()) == pytest.approx(3.0, abs=0.1)
    assert _best_shift(zl[0, 0].numpy(), zr[0, 0].numpy()) == pytest.approx(6.0, abs=0.2)


def test_zoom_keeps_the_centre_row_and_invalid_labels():
    left, right, bl, br = _pair(2.0)
    ramp = torch.linspace(0, 1, H).view(1, 1, H, 1).expand(1, 1, H, W).contiguous()
    gen = torch.Generator().manual_seed(2)
    zl, _, zbl, _ = zoom(ramp, right, bl, br, gen, p_zoom=1.0, zoom_range=(1.5, 1.5))
    # a vertical ramp magnified about the centre row: the centre value stays, spread 1.5x (slope /1.5)
    centre = zl[0, 0, :, W // 2]
    assert float(centre[H // 2 - 1: H // 2 + 1].mean()) == pytest.approx(0.5, abs=0.02)
    slope_before = float(ramp[0, 0, H // 2 + 8, 0] - ramp[0, 0, H // 2 - 8, 0])
    slope_after = float(centre[H // 2 + 8] - centre[H // 2 - 8])
    assert slope_after == pytest.approx(slope_before / 1.5, rel=0.05)
    # only zeros and scaled valid values, nothing in between (nearest sampling of a sparse map)
    values = set(np.unique(np.round(zbl.numpy() * W, 4)))
    assert values <= {0.0, 3.0}


def test_pad_window_pads_outside_a_centred_window_only():
    from metricslam.depth.canonical import PAD_VALUE_U8
    from metricslam_train.data import pad_window

    left, right, bl, br = _pair(3.0)
    gen = torch.Generator().manual_seed(3)
    pl, pr, pbl, pbr = pad_window(left, right, bl, br, gen, p_pad=1.0, width_range=(0.5, 0.5),
                                  height_range=(0.5, 0.5))
    pad = PAD_VALUE_U8 / 255.0
    padded = (pl[0, 0] == pad) & (pr[0, 0] == pad)
    # the kept window is about half the width and height (centre jitter <= 2 %), around the centre
    assert padded[H // 2, W // 2].item() is False
    assert padded[0, 0].item() and padded[-1, -1].item()
    kept = (~padded).float()
    assert float(kept.mean()) == pytest.approx(0.25, abs=0.05)
    # labels: none where padded, untouched inside
    assert torch.all(pbl[0, 0][padded] == 0) and torch.all(pbr[0, 0][padded] == 0)
    inside = ~padded & (bl[0, 0] > 0)
    assert torch.equal(pbl[0, 0][inside], bl[0, 0][inside])
    assert torch.equal(pl[0, 0][~padded], left[0, 0][~padded])
    off = pad_window(left, right, bl, br, gen, p_pad=0.0)
    assert off[0] is left


def test_canonical_training_asks_for_k_times_the_disparity(tmp_path):
    """Contract v2: the cache's ratio is divided by k = fx_c / fx_input, the labels stay the pair's."""
    from metricslam_train.data import StereoPairs

    n, h, w = 2, 8, 16
    path = tmp_path / "c.npz"
    bm = np.full((n, h, w), 0.02, np.float16)
    np.savez(path, left=np.zeros((n, h, w), np.uint8), right=np.zeros((n, h, w), np.uint8), bm_left=bm,
             bm_right=bm, baseline_ratio=np.float32(0.5), name="x", fx_px=np.float32(700.0))
    plain = StereoPairs([path])
    scaled = StereoPairs([path], [1.25])
    assert np.array_equal(plain.bm_left, scaled.bm_left)
    assert scaled.ratio[0] == pytest.approx(0.5 / 1.25)
    # what the loss wants from the network: output * ratio == label
    assert float(bm[0, 0, 0]) / scaled.ratio[0] == pytest.approx(1.25 * float(bm[0, 0, 0]) / plain.ratio[0])


def test_export_writes_a_v2_contract_for_a_canonical_run():
    from metricslam_train.export import contract_for
    from metricslam_train.network import PyramidDepthNet

    meta = {"model_id": "t", "input_height": 256, "input_width": 512,
            "normalization": {"scale": 1 / 255, "mean": 0.45, "std": 0.25}, "baseline_m": 0.537,
            "training_data": "x", "training_commit": "y"}
    net = PyramidDepthNet()
    assert contract_for(net, meta).contract_version == "1"
    v2 = contract_for(net, {**meta, "canonical_fx_px": 296.6, "canonical_fy_px": 489.5, "valid_min_fraction": 0.75})
    assert v2.contract_version == "2" and v2.uses_canonical_camera
    assert v2.canonical_camera().fx_px == pytest.approx(296.6)
