"""Training losses (torch): each term is lowest at the true disparity of a synthetic
fronto-parallel pair, supervision-only images get no stereo terms, and flip augmentation keeps a
valid pair. The training runs themselves: ``tests/test_training.py``."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from metricslam_train.data import augment  # noqa: E402
from metricslam_train.losses import (  # noqa: E402
    edge_aware_smoothness,
    lr_consistency,
    photometric,
    supervision,
    total_loss,
    warp_horizontal,
)
from tests.training_images import SHIFT_PX, H, W, texture as _texture  # noqa: E402


def _pair(shift_px: int = SHIFT_PX):
    """Left/right (1,1,H,W) of a textured plane with constant disparity: right(u) = left(u + d)."""
    wide = _texture(H, W + shift_px)
    left = torch.from_numpy(wide[:, :W].copy())[None, None]
    right = torch.from_numpy(wide[:, shift_px:shift_px + W].copy())[None, None]
    return left, right


def _const(value: float) -> torch.Tensor:
    return torch.full((1, 1, H, W), float(value))


def test_warp_reconstructs_left_at_true_disparity():
    left, right = _pair()
    left_hat = warp_horizontal(right, -_const(SHIFT_PX / W))
    inner = slice(SHIFT_PX + 1, W - 1)
    torch.testing.assert_close(left_hat[..., inner], left[..., inner], atol=1e-5, rtol=0)


@pytest.mark.parametrize("wrong_px", [0, 3, 9, 12])
def test_photometric_is_lowest_at_true_disparity(wrong_px):
    left, right = _pair()
    true = photometric(left, warp_horizontal(right, -_const(SHIFT_PX / W)))
    wrong = photometric(left, warp_horizontal(right, -_const(wrong_px / W)))
    assert float(true) < 0.02 < float(wrong)
    assert float(true) >= 0.0


def test_lr_consistency_zero_for_consistent_plane_and_positive_otherwise():
    d = _const(SHIFT_PX / W)
    assert float(lr_consistency(d, d)) == pytest.approx(0.0, abs=1e-7)
    assert float(lr_consistency(d, 1.5 * d)) > 0.0


def test_smoothness_zero_for_constant_disparity_positive_for_noise():
    left, _ = _pair()
    assert float(edge_aware_smoothness(_const(0.05), left)) == pytest.approx(0.0, abs=1e-7)
    noisy = _const(0.05) + 0.01 * torch.rand(1, 1, H, W)
    assert float(edge_aware_smoothness(noisy, left)) > 0.0


def test_supervision_zero_at_target_masked_and_pulls_towards_target():
    target = _const(0.05)
    target[..., :10] = 0.0  # invalid block-matching pixels
    pred = _const(0.05)
    pred[..., :10] = 0.2  # errors where the target is invalid must not count
    assert float(supervision(pred, target, 0.005)) == pytest.approx(0.0, abs=1e-9)
    low = _const(0.03).requires_grad_(True)
    supervision(low, target, 0.005).backward()
    assert float(low.grad[..., 10:].sum()) < 0  # gradient descent raises the disparity towards 0.05


def test_log_space_supervision_weighs_relative_error_alike_at_every_range():
    """The same 20 % disparity error costs the same near (d 0.1) and far (d 0.005) in log space;
    in d_frac space the far one is ~20x cheaper (why the far range was barely taught)."""
    near_t, far_t = _const(0.1), _const(0.005)
    near_log = float(supervision(near_t * 1.2, near_t, 0.05, log_space=True))
    far_log = float(supervision(far_t * 1.2, far_t, 0.05, log_space=True))
    assert near_log == pytest.approx(far_log, rel=1e-4) and near_log > 0
    near_lin = float(supervision(near_t * 1.2, near_t, 0.005))
    far_lin = float(supervision(far_t * 1.2, far_t, 0.005))
    assert near_lin > 10 * far_lin
    assert float(supervision(far_t, far_t, 0.05, log_space=True)) == pytest.approx(0.0, abs=1e-9)


def test_total_loss_is_lower_at_true_disparity_at_every_scale():
    left, right = _pair()
    bm = _const(SHIFT_PX / W)
    ratio = torch.ones(1)

    def outputs(d_frac: float):
        return [torch.full((1, 2, H >> k, W >> k), d_frac) for k in range(3, 7)]

    true_loss, terms = total_loss(outputs(SHIFT_PX / W), left, right, bm, bm, ratio)
    wrong_loss, _ = total_loss(outputs(2 * SHIFT_PX / W), left, right, bm, bm, ratio)
    assert float(true_loss) < float(wrong_loss)
    assert terms["sup"] == pytest.approx(0.0, abs=1e-6) and terms["lr"] == pytest.approx(0.0, abs=1e-6)


def test_flip_with_swap_keeps_a_valid_stereo_pair():
    left, right = _pair()
    bm = _const(SHIFT_PX / W)
    gen = torch.Generator().manual_seed(0)
    new_l, new_r, new_bl, new_br = augment(left, right, bm, bm, gen, p_flip=1.0, gamma_range=(1, 1),
                                           brightness_range=(1, 1))
    torch.testing.assert_close(new_l, right.flip(-1))
    good = photometric(new_l, warp_horizontal(new_r, -new_bl))
    bad = photometric(left.flip(-1), warp_horizontal(right.flip(-1), -new_bl))  # flip without swap
    assert float(good) < 0.02 < float(bad)


def test_supervision_only_images_get_no_photometric_or_left_right_loss():
    left, right = _pair()
    target = _const(SHIFT_PX / W)
    wrong = [torch.full((1, 2, H >> k, W >> k), 2 * SHIFT_PX / W) for k in range(3, 7)]
    ratio = torch.ones(1)
    # a "pair" whose right image is unrelated: only the supervision may see it
    junk_right = torch.from_numpy(_texture(H, W, seed=99))[None, None]
    _, stereo_terms = total_loss(wrong, left, junk_right, target, target, ratio, scales=(1, 3))
    _, mono_terms = total_loss(wrong, left, junk_right, target, target, ratio, scales=(1, 3),
                               stereo=torch.zeros(1))
    assert stereo_terms["photo"] > 0.01 and mono_terms["photo"] == 0.0 and mono_terms["lr"] == 0.0
    assert mono_terms["sup"] > 0.0
    # in a mixed batch the stereo pair's photometric term is its own, not diluted by the image
    two = [torch.cat([w] * 2) for w in wrong]
    _, mixed = total_loss(two, torch.cat([left, left]), torch.cat([right, junk_right]), torch.cat([target] * 2),
                          torch.cat([target] * 2), torch.ones(2), scales=(1, 3), stereo=torch.tensor([1.0, 0.0]))
    _, alone = total_loss(wrong, left, right, target, target, ratio, scales=(1, 3))
    assert mixed["photo"] == pytest.approx(alone["photo"], rel=1e-5)
