"""bench.canonical_invariance's comparisons with known answers: a model that reads depth from the
ray (the contract-v2 toy) is crop- and scale-invariant, a wrong crop camera is caught, exact-depth
cells and the v2 relabelling do what they say. No shared data, no trained model."""

from __future__ import annotations

import numpy as np
import pytest

from bench.canonical_invariance import write_metadata_as_v2
from bench.canonical_variants import (
    Variant,
    cell_centres_px,
    centre_crop_width,
    depth_ratios,
    exact_depth_cells,
    make_variants,
    net_over_exact,
    ratio_stats,
    same_ray_px,
)
from metricslam.camera import PinholeCamera
from metricslam.depth import DepthModel
from tests.canonical_toy import ray_image, toy_contract, write_toy_v2_model

KITTI_LIKE = PinholeCamera(fx_px=718.856, fy_px=718.856, cx_px=607.19, cy_px=185.22, width_px=1241, height_px=376)


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> DepthModel:
    return DepthModel.load(write_toy_v2_model(tmp_path_factory.mktemp("toy") / "toy.onnx"))


@pytest.fixture(scope="module")
def full(toy):
    image = ray_image(KITTI_LIKE)
    return image, toy.predict_inv_depth(image, camera=KITTI_LIKE).inv_depth_per_m


def test_variant_cameras_see_the_same_rays():
    image = np.zeros((376, 1241), np.uint8)
    crop, crop23, half, double = make_variants(image, KITTI_LIKE)
    assert crop.image.shape == (376, 620) and crop.camera.cx_px == pytest.approx(KITTI_LIKE.cx_px - 310)
    assert crop23.image.shape == (376, 827)
    assert half.image.shape == (188, 620) and double.image.shape == (752, 2482)
    # a crop pixel is the full pixel x0 to its right; a 2x pixel u is full (u + 0.5)/2 − 0.5
    np.testing.assert_allclose(same_ray_px([[0.0, 10.0]], crop.camera, KITTI_LIKE), [[310.0, 10.0]], atol=1e-9)
    np.testing.assert_allclose(same_ray_px([[9.0, 3.0]], double.camera, KITTI_LIKE), [[4.25, 1.25]], atol=1e-9)


@pytest.mark.parametrize("index", range(4))
def test_toy_model_is_invariant_to_crops_and_rescales(toy, full, index):
    image, inv_full = full
    var = make_variants(image, KITTI_LIKE)[index]
    inv = toy.predict_inv_depth(var.image, camera=var.camera).inv_depth_per_m
    ratios, valid = depth_ratios(inv_full, KITTI_LIKE, inv, var.camera)
    stats = ratio_stats(ratios)
    assert stats["n"] > 100 and valid > 0.2
    assert stats["median"] == pytest.approx(1.0, abs=0.02), var.name
    assert stats["iqr"] < 0.02


def test_a_crop_whose_cx_was_not_shifted_is_detected(toy, full):
    image, inv_full = full
    good = centre_crop_width(image, KITTI_LIKE, 0.5)
    bad = Variant("crop_w1/2 (cx not shifted)", good.image, good.camera.model_copy(update={"cx_px": KITTI_LIKE.cx_px}))
    inv = toy.predict_inv_depth(bad.image, camera=bad.camera).inv_depth_per_m
    median = ratio_stats(depth_ratios(inv_full, KITTI_LIKE, inv, bad.camera)[0])["median"]
    assert abs(median - 1.0) > 0.05


def test_depth_ratios_known_answer_and_nan_cells():
    cam = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=15.5, width_px=64, height_px=32)
    inv_full = np.full((8, 16), 0.5)
    inv_var = np.full((8, 16), 0.25)  # reads twice the depth
    inv_var[:, :4] = np.nan
    ratios, valid = depth_ratios(inv_full, cam, inv_var, cam)
    assert valid == pytest.approx(0.75) and ratios.size == 8 * 12
    np.testing.assert_allclose(ratios, 2.0)


def test_exact_depth_cells_known_answer():
    # 854 px over 64 cells (13.34 px each): each pixel goes to the cell its centre falls in
    cols = np.minimum(((np.arange(854) + 0.5) * 64 / 854).astype(int), 63)
    rows = np.arange(480) // 15
    depth = (1.0 + rows[:, None] + 100.0 * cols[None, :]).astype(np.float64)
    depth[:15, :] = 0.0  # row 0 of the grid: no depth (sky)
    depth[15:23, 0:13] = 0.0  # cell (1, 0): 7 of 15 rows left, under half
    cells = exact_depth_cells(depth, (32, 64))
    expected = 1.0 + np.arange(32)[:, None] + 100.0 * np.arange(64)[None, :]
    assert np.isnan(cells[0]).all() and np.isnan(cells[1, 0])
    np.testing.assert_allclose(cells[2:], expected[2:])
    np.testing.assert_allclose(cells[1, 1:], expected[1, 1:])
    # a network that reads 1.1x the exact depth everywhere, invalid in its left quarter
    inv = 1.0 / (1.1 * np.where(np.isnan(cells), 10.0, cells))
    inv[:, :16] = np.nan
    ratios, valid = net_over_exact(inv, cells)
    assert valid == pytest.approx(0.75)
    np.testing.assert_allclose(ratios, 1.1)
    assert ratios.size == np.isfinite(cells[:, 16:]).sum()


def test_cell_centres_follow_the_sample_map_convention():
    uv = cell_centres_px((2, 4), 8, 4)
    np.testing.assert_allclose(uv[:4, 0], [0.5, 2.5, 4.5, 6.5])
    np.testing.assert_allclose(uv[[0, 4], 1], [0.5, 2.5])


def test_write_metadata_as_v2_changes_only_the_contract(tmp_path):
    v1 = toy_contract(contract_version="1", canonical_fx_px=None, canonical_fy_px=None, valid_min_fraction=None)
    src = write_toy_v2_model(tmp_path / "v1.onnx", v1)
    dst = write_metadata_as_v2(src, tmp_path / "v2.onnx", fx_px=300.0, fy_px=480.0, valid_min_fraction=0.75)
    old, new = DepthModel.load(src), DepthModel.load(dst)
    assert old.contract.contract_version == "1" and new.contract.contract_version == "2"
    assert (new.contract.canonical_fx_px, new.contract.canonical_fy_px, new.contract.valid_min_fraction) == (
        300.0, 480.0, 0.75)
    assert new.contract.model_dump(exclude={"contract_version", "canonical_fx_px", "canonical_fy_px",
                                            "valid_min_fraction"}) == \
        old.contract.model_dump(exclude={"contract_version", "canonical_fx_px", "canonical_fy_px",
                                         "valid_min_fraction"})
    batch = np.zeros((1, 1, 256, 512), np.float32)
    np.testing.assert_array_equal(old.run(batch), new.run(batch))
