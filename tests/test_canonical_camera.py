"""Contract version 2, the canonical camera: warp geometry, input/label/output resampling with known
answers, a toy v2 network end to end, and the version-1 path left byte-identical."""

from __future__ import annotations

import cv2
import numpy as np
import onnxruntime as ort
import pytest

from metricslam.camera import PinholeCamera
from metricslam.depth import DEFAULT_MODEL_PATH, DepthModel, sample_map
from metricslam.depth.canonical import (
    PAD_VALUE_U8,
    CanonicalCamera,
    canonical_d_frac,
    canonical_warp,
    cells_valid,
    inv_depth_from_canonical,
    to_caller_grid,
    to_canonical,
    warp_depth_labels,
)
from metricslam.errors import DepthModelError, ImageError
from tests.canonical_toy import (
    CANONICAL_FX_PX,
    INPUT_HW,
    expected_inv_depth_per_m,
    ray_image,
    write_toy_v2_model,
)

CANON = CanonicalCamera(fx_px=320.0, fy_px=300.0, width_px=512, height_px=256)
CENTRE = np.array([(512 - 1) / 2, (256 - 1) / 2])


def _camera(fx, fy, cx, cy, w, h) -> PinholeCamera:
    return PinholeCamera(fx_px=fx, fy_px=fy, cx_px=cx, cy_px=cy, width_px=w, height_px=h)


# ----- warp geometry -----

@pytest.mark.parametrize("fx,fy", [(700.0, 700.0), (400.0, 900.0), (1500.0, 1100.0)])
def test_principal_point_lands_at_input_centre_and_offsets_scale(fx, fy):
    cam = _camera(fx, fy, 601.3, 170.8, 1226, 370)
    warp = canonical_warp(cam, CANON)
    assert warp.scale_x == pytest.approx(320.0 / fx) and warp.scale_y == pytest.approx(300.0 / fy)
    np.testing.assert_allclose(warp.to_input([[cam.cx_px, cam.cy_px]])[0], CENTRE, atol=1e-12)
    d = np.array([[37.0, -12.5], [-400.0, 90.0]])
    got = warp.to_input(np.array([cam.cx_px, cam.cy_px]) + d)
    np.testing.assert_allclose(got, CENTRE + d * [warp.scale_x, warp.scale_y], atol=1e-9)
    np.testing.assert_allclose(warp.to_caller(got), np.array([cam.cx_px, cam.cy_px]) + d, atol=1e-9)
    np.testing.assert_allclose(warp.matrix @ np.array([*(np.array([cam.cx_px, cam.cy_px]) + d[0]), 1.0]),
                               got[0], atol=1e-9)


def test_identity_camera_is_an_exact_copy():
    cam = _camera(320.0, 300.0, 255.5, 127.5, 512, 256)
    image = np.random.default_rng(0).integers(0, 256, (256, 512), dtype=np.uint8)
    image_in, valid_in = to_canonical(image, canonical_warp(cam, CANON))
    np.testing.assert_array_equal(image_in, image)
    assert valid_in.all()


def test_integer_shift_pads_the_uncovered_columns():
    cam = _camera(320.0, 300.0, 255.5 + 3, 127.5, 512, 256)  # principal point 3 px right of centre
    image = np.random.default_rng(1).integers(0, 256, (256, 512), dtype=np.uint8)
    image_in, valid_in = to_canonical(image, canonical_warp(cam, CANON))
    np.testing.assert_array_equal(image_in[:, :509], image[:, 3:])
    assert (image_in[:, 509:] == PAD_VALUE_U8).all()
    assert valid_in[:, :509].all() and not valid_in[:, 509:].any()


def test_half_scale_is_the_area_mean():
    cam = _camera(640.0, 600.0, 511.5, 255.5, 1024, 512)  # same field of view at twice the size
    image = np.random.default_rng(2).integers(0, 256, (512, 1024), dtype=np.uint8)
    image_in, valid_in = to_canonical(image, canonical_warp(cam, CANON))
    np.testing.assert_array_equal(image_in, cv2.resize(image, (512, 256), interpolation=cv2.INTER_AREA))
    assert valid_in.all()


def test_wide_camera_is_cropped_and_narrow_camera_padded():
    image = np.full((400, 600), 200, np.uint8)
    wide = canonical_warp(_camera(150.0, 150.0, 299.5, 199.5, 600, 400), CANON)  # sx 2.13: crop
    image_in, valid_in = to_canonical(image, wide)
    assert valid_in.all() and (image_in == 200).all()
    narrow = canonical_warp(_camera(1280.0, 1200.0, 299.5, 199.5, 600, 400), CANON)  # sx 0.25: pad
    image_in, valid_in = to_canonical(image, narrow)
    cols, rows = valid_in.any(axis=0), valid_in.any(axis=1)
    assert cols.sum() == 150 and rows.sum() == 100  # 600·0.25 x 400·0.25, centred
    assert np.flatnonzero(cols)[[0, -1]].tolist() == [181, 330]
    assert (image_in[valid_in] == 200).all() and (image_in[~valid_in] == PAD_VALUE_U8).all()


def test_anisotropic_focal_lengths_map_a_linear_field_exactly():
    cam = _camera(500.0, 800.0, 300.0, 260.0, 640, 480)
    v, u = np.mgrid[0:480, 0:640].astype(float)
    field = lambda x, y: 100 + 0.1 * x + 0.05 * y  # noqa: E731
    image = np.round(field(u, v)).astype(np.uint8)
    warp = canonical_warp(cam, CANON)
    image_in, valid_in = to_canonical(image, warp)
    vi, ui = np.mgrid[0:256, 0:512].astype(float)
    caller = warp.to_caller(np.stack([ui.ravel(), vi.ravel()], 1))
    expected = field(caller[:, 0], caller[:, 1]).reshape(256, 512)
    inner = valid_in & np.pad(valid_in[2:-2, 2:-2], 2)  # away from the replicated edge
    assert np.abs(image_in[inner] - expected[inner]).max() <= 1.0


def test_image_of_another_size_is_refused():
    warp = canonical_warp(_camera(500.0, 500.0, 300.0, 200.0, 640, 480), CANON)
    with pytest.raises(ImageError, match="640x480"):
        to_canonical(np.zeros((480, 600), np.uint8), warp)


# ----- output cells and resampling -----

def test_cells_valid_counts_covered_pixels():
    valid_in = np.zeros((256, 512), bool)
    valid_in[:, :100] = True  # cells 0..11 full, cell 12 covers 4 of 8 columns
    cells = cells_valid(valid_in, (32, 64), 0.5)
    assert cells[:, :13].all() and not cells[:, 13:].any()
    assert cells_valid(valid_in, (32, 64), 1.0)[:, :12].all() and not cells_valid(valid_in, (32, 64), 1.0)[:, 12:].any()
    with pytest.raises(DepthModelError):
        cells_valid(valid_in, (32, 64), 0.0)


def test_to_caller_grid_identity_and_invalid_cells():
    cam = _camera(320.0, 300.0, 255.5, 127.5, 512, 256)
    warp = canonical_warp(cam, CANON)
    grid = np.random.default_rng(3).uniform(0.1, 1.0, (32, 64))
    valid = np.ones((32, 64), bool)
    np.testing.assert_allclose(to_caller_grid(grid, valid, warp), grid, rtol=1e-6)
    valid[:, 40:] = False
    out = to_caller_grid(grid, valid, warp)
    assert np.isnan(out[:, 40:]).all()
    np.testing.assert_allclose(out[:, :40], grid[:, :40], rtol=1e-6)


def test_to_caller_grid_outside_the_input_is_nan_and_linear_fields_survive():
    cam = _camera(160.0, 150.0, 400.0, 130.0, 900, 300)  # twice the canonical field of view: crop
    warp = canonical_warp(cam, CANON)
    jj, ii = np.meshgrid(np.arange(64), np.arange(32))
    grid = 2.0 + 0.01 * jj - 0.02 * ii  # linear in the input cell index
    out = to_caller_grid(grid, np.ones((32, 64), bool), warp, out_hw=(16, 48))
    u = (np.arange(48) + 0.5) * 900 / 48 - 0.5
    v = (np.arange(16) + 0.5) * 300 / 16 - 0.5
    x = (warp.scale_x * u + warp.offset_x_px + 0.5) / 8 - 0.5
    y = (warp.scale_y * v + warp.offset_y_px + 0.5) / 8 - 0.5
    inside = ((y >= -0.5) & (y <= 31.5))[:, None] & ((x >= -0.5) & (x <= 63.5))[None, :]
    assert np.isnan(out[~inside]).all() and np.isfinite(out[inside]).all()
    xx, yy = np.meshgrid(np.clip(x, 0, 63), np.clip(y, 0, 31))
    np.testing.assert_allclose(out[inside], (2.0 + 0.01 * xx - 0.02 * yy)[inside], rtol=1e-6)


# ----- metric conversion and training labels -----

def test_inv_depth_formula_and_label_d_frac_invert_each_other():
    canonical = CanonicalCamera(fx_px=320.0, fy_px=320.0, width_px=512, height_px=256)
    depth_m = np.array([[10.0, 0.0], [2.5, np.inf]])
    d = canonical_d_frac(depth_m, "depth_m", canonical, 0.5)
    assert d[0, 0] == pytest.approx(320 * 0.5 / (10 * 512)) and d[0, 1] == 0 and d[1, 1] == 0
    np.testing.assert_allclose(inv_depth_from_canonical(d, canonical, 0.5)[[0, 1], [0, 0]], [0.1, 0.4], rtol=1e-6)
    np.testing.assert_allclose(canonical_d_frac(1 / depth_m[:, :1], "inv_depth_per_m", canonical, 0.5), d[:, :1])
    assert canonical_d_frac(np.array([51.2]), "disparity_px", canonical, 0.5)[0] == pytest.approx(0.1)


def test_warp_depth_labels_nearest_and_exact():
    rng = np.random.default_rng(4)
    depth = rng.uniform(1, 80, (512, 1024))
    depth[rng.random(depth.shape) < 0.3] = 0.0  # sparse, like LiDAR
    cam = _camera(640.0, 600.0, 511.5, 255.5, 1024, 512)  # sx = sy = 0.5
    warp = canonical_warp(cam, CANON)
    out = warp_depth_labels(depth, warp, "depth_m")
    # input pixel j has its centre at caller u = 2j + 0.5: nearest (half up) is 2j + 1
    np.testing.assert_array_equal(out, depth[1::2, 1::2].astype(np.float32))
    np.testing.assert_allclose(warp_depth_labels(depth, warp, "disparity_px"), out * 0.5)
    shifted = canonical_warp(_camera(320.0, 300.0, 255.5 + 3, 127.5, 512, 256), CANON)
    small = depth[::2, ::2]
    got = warp_depth_labels(small, shifted, "inv_depth_per_m")
    np.testing.assert_array_equal(got[:, :509], small[:, 3:].astype(np.float32))
    assert (got[:, 509:] == 0).all()


# ----- a toy v2 network end to end -----

@pytest.fixture(scope="module")
def toy_path(tmp_path_factory):
    return write_toy_v2_model(tmp_path_factory.mktemp("toy") / "toy.onnx")


@pytest.fixture(scope="module")
def toy(toy_path) -> DepthModel:
    return DepthModel.load(toy_path)


def _check_against_rays(model: DepthModel, camera: PinholeCamera, image: np.ndarray) -> np.ndarray:
    """Run the model; compare every finite cell with the known inverse depth of its ray (1.5 %);
    cells whose ray is outside the canonical field are NaN, cells well inside are finite."""
    result = model.predict_inv_depth(image, camera=camera)
    h, w = result.inv_depth_per_m.shape
    u = (np.arange(w) + 0.5) * camera.width_px / w - 0.5
    v = (np.arange(h) + 0.5) * camera.height_px / h - 0.5
    xn, yn = np.meshgrid((u - camera.cx_px) / camera.fx_px, (v - camera.cy_px) / camera.fy_px)
    inv = result.inv_depth_per_m
    finite = np.isfinite(inv)
    assert finite.sum() > 0
    np.testing.assert_allclose(inv[finite], expected_inv_depth_per_m(xn, yn)[finite], rtol=0.015)
    np.testing.assert_array_equal(result.valid, finite)
    # where the cell centre's ray falls in the input (and on this image), with 1.5 input cells of margin
    warp = model.warp_for(camera)
    cx_in, cy_in = (INPUT_HW[1] - 1) / 2, (INPUT_HW[0] - 1) / 2
    u_in, v_in = cx_in + xn * CANONICAL_FX_PX, cy_in + yn * model.contract.canonical_fy_px
    lo_u, hi_u = max(-0.5, warp.offset_x_px - 0.5 * warp.scale_x), min(INPUT_HW[1] - 0.5, warp.to_input(
        [[camera.width_px - 0.5, 0]])[0, 0])
    lo_v, hi_v = max(-0.5, warp.offset_y_px - 0.5 * warp.scale_y), min(INPUT_HW[0] - 0.5, warp.to_input(
        [[0, camera.height_px - 0.5]])[0, 1])
    well_inside = (u_in > lo_u + 12) & (u_in < hi_u - 12) & (v_in > lo_v + 12) & (v_in < hi_v - 12)
    outside = (u_in < -0.5) | (u_in > INPUT_HW[1] - 0.5) | (v_in < -0.5) | (v_in > INPUT_HW[0] - 0.5)
    assert finite[well_inside].all() and not finite[outside].any()
    # d_frac keeps the v1 relation for the caller's camera
    np.testing.assert_allclose(result.d_frac[finite], (inv * camera.fx_px * model.contract.baseline_m
                                                       / camera.width_px)[finite], rtol=1e-5)
    return inv


@pytest.mark.parametrize("aspect", [4 / 3, 16 / 9, 3.3])
@pytest.mark.parametrize("fx_px", [400.0, 700.0, 1000.0, 1400.0])
def test_toy_v2_model_sees_the_same_rays_for_every_camera_crop_and_scale(toy, fx_px, aspect):
    width = 960
    height = int(round(width / aspect))
    cam = _camera(fx_px, 1.1 * fx_px, 0.47 * width, 0.55 * height, width, height)
    image = ray_image(cam)
    full = _check_against_rays(toy, cam, image)
    for fraction in (1 / 2, 2 / 3):  # centre crops, same focal length
        crop_w = int(round(width * fraction))
        x0 = (width - crop_w) // 2
        crop_cam = _camera(cam.fx_px, cam.fy_px, cam.cx_px - x0, cam.cy_px, crop_w, height)
        crop = _check_against_rays(toy, crop_cam, np.ascontiguousarray(image[:, x0:x0 + crop_w]))
        # the same inverse depth where the crop and the full image overlap
        h, w = crop.shape
        uv = np.stack(np.meshgrid((np.arange(w) + 0.5) * crop_w / w - 0.5 + x0,
                                  (np.arange(h) + 0.5) * height / h - 0.5), -1).reshape(-1, 2)
        from_full = sample_map(full, uv, (width, height)).reshape(h, w)
        both = np.isfinite(from_full) & np.isfinite(crop)
        assert both.sum() > 0.2 * both.size
        np.testing.assert_allclose(crop[both], from_full[both], rtol=0.02)
    for scale, interpolation in ((0.5, cv2.INTER_AREA), (2.0, cv2.INTER_LINEAR)):
        size = (int(round(width * scale)), int(round(height * scale)))
        scaled = cv2.resize(image, size, interpolation=interpolation)
        _check_against_rays(toy, cam.resized(*size), scaled)


def test_toy_v2_model_refuses_a_call_without_the_camera(toy):
    image = np.full((300, 400), 128, np.uint8)
    with pytest.raises(DepthModelError, match="PinholeCamera"):
        toy.predict_inv_depth(image, fx_px=500.0)
    with pytest.raises(DepthModelError, match="PinholeCamera"):
        toy.predict_d_frac([image])
    cam = _camera(500.0, 500.0, 199.5, 149.5, 400, 300)
    by_values = toy.predict_inv_depth(image, fx_px=500.0, fy_px=500.0, cx_px=199.5, cy_px=149.5)
    np.testing.assert_array_equal(by_values.inv_depth_per_m, toy.predict_inv_depth(image, camera=cam).inv_depth_per_m)
    assert toy.predict_d_frac([image, image], cameras=[cam, cam]).shape == (2, 32, 64)
    with pytest.raises(ImageError, match="400x300"):  # the camera must describe the image
        toy.predict_inv_depth(np.full((300, 401), 128, np.uint8), camera=cam)


# ----- version 1: the shipped model's path is unchanged -----

def test_v1_shipped_model_is_byte_identical_to_the_old_path():
    model = DepthModel.load(DEFAULT_MODEL_PATH, threads=1)
    c = model.contract
    assert not c.uses_canonical_camera
    image = np.random.default_rng(5).integers(0, 256, (370, 1226), dtype=np.uint8)
    fx_px = 707.0912
    # the version-1 formula, written out: whole image resized, network, d_frac·W/(fx·B)
    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = 1, 1
    session = ort.InferenceSession(str(DEFAULT_MODEL_PATH), options, providers=["CPUExecutionProvider"])
    resized = cv2.resize(image, (c.input_width, c.input_height), interpolation=cv2.INTER_AREA)
    x = ((resized.astype(np.float32) * c.normalization.scale - c.normalization.mean)
         / c.normalization.std)[None, None]
    d_frac = np.asarray(session.run([c.output_name], {c.input_name: x})[0], np.float32).reshape(
        c.output_height, c.output_width)
    d = d_frac.astype(np.float64)
    expected = (np.where(d > 0, d, 0.0) * 1226 / (fx_px * c.baseline_m)).astype(np.float32)
    for result in (model.predict_inv_depth(image, fx_px),
                   model.predict_inv_depth(image, camera=_camera(fx_px, 700.0, 600.0, 180.0, 1226, 370))):
        assert result.inv_depth_per_m.tobytes() == expected.tobytes()
        assert result.d_frac.tobytes() == d_frac.tobytes()
        assert result.valid.all()


def test_cli_depth_passes_the_whole_camera(tmp_path, toy, toy_path):
    from metricslam_cli.main import main

    cam = _camera(900.0, 1000.0, 260.0, 150.0, 480, 360)
    image = ray_image(cam)
    path, out = tmp_path / "ray.png", tmp_path / "d.npy"
    cv2.imwrite(str(path), image)
    expected = toy.predict_inv_depth(image, camera=cam).depth_m()
    run = ["depth", str(path), "--model", str(toy_path), "--out", str(out)]
    assert main([*run, "--fx", "900", "--fy", "1000", "--cx", "260", "--cy", "150",
                 "--png", str(tmp_path / "d.png")]) == 0
    np.testing.assert_array_equal(np.load(out), expected)
    assert cv2.imread(str(tmp_path / "d.png")).shape == (360, 480, 3)
    calib = tmp_path / "cam.yaml"
    calib.write_text("width: 480\nheight: 360\nfx: 900\nfy: 1000\ncx: 260\ncy: 150\n")
    assert main([*run, "--calib", str(calib)]) == 0
    np.testing.assert_array_equal(np.load(out), expected)
    assert main(run) == 1  # no intrinsics
    assert main([*run, "--calib", str(calib), "--fx", "900"]) == 1  # two sources of intrinsics
    assert main([*run, "--fx", "900"]) == 0  # fy = fx, principal point at the centre
    assert not np.array_equal(np.load(out), expected, equal_nan=True)
