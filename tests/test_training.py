"""Training side (torch): caches, data mixing, a few real steps, resume, export, weight average.
The loss terms and augmentation: ``tests/test_training_losses.py``."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

torch = pytest.importorskip("torch")

from metricslam.errors import TrainingError  # noqa: E402
from metricslam_train.config import TrainConfig  # noqa: E402
from metricslam_train.data import StereoPairs, build_cache, read_stereo_sequence  # noqa: E402
from metricslam_train.network import PyramidDepthNet  # noqa: E402
from tests.training_images import SHIFT_PX, H, W, texture as _texture  # noqa: E402

def _write_kitti_folder(root, n: int = 3, h: int = 2 * H, w: int = 2 * W, shift_px: int = 2 * SHIFT_PX,
                        ext: str = ".png"):
    for sub in ("image_0", "image_1"):
        (root / sub).mkdir(parents=True)
    for i in range(n):
        wide = (_texture(h, w + shift_px, seed=i) * 255).astype(np.uint8)
        cv2.imwrite(str(root / "image_0" / f"{i:06d}{ext}"), wide[:, :w])
        cv2.imwrite(str(root / "image_1" / f"{i:06d}{ext}"), wide[:, shift_px:shift_px + w])
    fx, b = 200.0, 0.5
    p0 = f"{fx} 0 {w / 2} 0 0 {fx} {h / 2} 0 0 0 1 0"
    p1 = f"{fx} 0 {w / 2} {-fx * b} 0 {fx} {h / 2} 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {p0}\nP1: {p1}\n")
    return root


def test_cache_holds_block_matching_disparity_as_width_fraction(tmp_path):
    seq = read_stereo_sequence(_write_kitti_folder(tmp_path / "seq"))
    assert seq.baseline_m == pytest.approx(0.5)
    cache = build_cache(seq, tmp_path / "c.npz", train_baseline_m=0.5, height=H, width=W, num_disparities=32)
    data = StereoPairs([cache])
    _, _, bm_left, bm_right, ratio, stereo = data[0]
    assert float(ratio) == pytest.approx(1.0) and float(stereo) == 1.0
    valid = bm_left[bm_left > 0]
    assert valid.numel() > 0.3 * H * W
    assert float(valid.median()) == pytest.approx(SHIFT_PX / W, rel=0.05)
    assert float(bm_right[bm_right > 0].median()) == pytest.approx(SHIFT_PX / W, rel=0.05)


def test_jpeg_pairs_are_training_data_like_png_pairs(tmp_path):
    """A stereo drive stored as JPEG (quality 95 here) caches the same disparity as its PNG twin."""
    png = read_stereo_sequence(_write_kitti_folder(tmp_path / "png"))
    jpg = read_stereo_sequence(_write_kitti_folder(tmp_path / "jpg", ext=".jpg"))
    assert [p.suffix for p in jpg.left_paths] == [".jpg"] * 3 and len(jpg.right_paths) == 3
    medians = []
    for seq, name in ((png, "p.npz"), (jpg, "j.npz")):
        cache = build_cache(seq, tmp_path / name, train_baseline_m=0.5, height=H, width=W, num_disparities=32)
        bm_left = StereoPairs([cache])[0][2]
        medians.append(float(bm_left[bm_left > 0].median()))
    assert medians[1] == pytest.approx(medians[0], rel=0.02)
    assert medians[1] == pytest.approx(SHIFT_PX / W, rel=0.05)


def test_a_measured_disparity_offset_is_removed_before_caching(tmp_path):
    """A pair whose disparities read 2 px (full resolution) too large caches the true ones."""
    seq = read_stereo_sequence(_write_kitti_folder(tmp_path / "seq"))  # true shift 2*SHIFT_PX at 2W
    cache = build_cache(seq, tmp_path / "c.npz", train_baseline_m=0.5, height=H, width=W, num_disparities=32,
                        disparity_offset_px=2.0)
    bm_left = StereoPairs([cache])[0][2]
    assert float(bm_left[bm_left > 0].median()) == pytest.approx((SHIFT_PX - 1) / W, rel=0.05)


def test_offsets_for_unknown_sequences_are_refused(tmp_path):
    from metricslam_train.train import prepare_caches

    with pytest.raises(TrainingError, match="kitti99"):
        prepare_caches(_config(tmp_path, disparity_offsets_px={"kitti99": -1.8}))


def _write_lidar_folder(root, n: int = 4, h: int = 2 * H, w: int = 2 * W, depth_m: float = 12.5):
    """KITTI-raw layout: colour images, sparse uint16 depth (metres x 256) on every 4th pixel."""
    for sub in ("image_02", "depth_02"):
        (root / sub).mkdir(parents=True)
    depth = np.zeros((h, w), np.uint16)
    depth[::4, ::4] = int(depth_m * 256)
    for i in range(n):
        gray = (_texture(h, w, seed=10 + i) * 255).astype(np.uint8)
        cv2.imwrite(str(root / "image_02" / f"{i:010d}.png"), np.dstack([gray] * 3))
        cv2.imwrite(str(root / "depth_02" / f"{i:010d}.png"), depth)
    (root / "calib.txt").write_text(f"K: 200.0 200.0 {w / 2} {h / 2}\n")
    return root


def test_depth_frames_cache_holds_metric_depth_as_training_rig_disparity(tmp_path):
    from metricslam_train.data import build_depth_cache

    folder = _write_lidar_folder(tmp_path / "lidar", depth_m=12.5)
    cache = build_depth_cache(folder, tmp_path / "d.npz", train_baseline_m=0.5, first=1, stop=3, height=H, width=W)
    data = StereoPairs([cache])
    assert len(data) == 2  # frames 1 and 2 only: the others stay out for validation
    left, right, bm_left, bm_right, ratio, stereo = data[0]
    assert float(stereo) == 0.0 and float(ratio) == 1.0 and float(bm_right.abs().max()) == 0.0
    # sparse LiDAR (1 pixel in 16) still gives a target in most cells of the half-size map
    assert float((bm_left > 0).float().mean()) > 0.2
    assert float(bm_left[bm_left > 0].median()) == pytest.approx(200.0 * 0.5 / (12.5 * 2 * W), rel=1e-3)
    with pytest.raises(TrainingError, match="no frames"):
        build_depth_cache(folder, tmp_path / "e.npz", train_baseline_m=0.5, first=9, height=H, width=W)


def test_training_mixes_stereo_pairs_and_depth_frames(tmp_path):
    from metricslam_train.train import train

    torch.set_num_threads(1)
    lidar = _write_lidar_folder(tmp_path / "lidar")
    cfg = _config(tmp_path, steps=3, batch_size=4, depth_frames=[{"folder": str(lidar), "stop": 2, "repeat": 3}])
    final = train(cfg, progress=False)
    meta = torch.load(final, weights_only=False)["meta"]
    assert "lidar frames 0..2 (2 images with metric depth, supervision only, x3" in meta["training_data"]
    records = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert len(records) == 3 and all(np.isfinite(r["loss"]) for r in records)


def _config(tmp_path, **over) -> TrainConfig:
    seq = tmp_path / "seq"
    values = dict(sequences=[str(seq if seq.is_dir() else _write_kitti_folder(seq))], cache_dir=str(tmp_path / "cache"),
                  run_dir=str(tmp_path / "run"), input_height=H, input_width=W, steps=4, batch_size=2,
                  lr=1e-3, checkpoint_every=2, train_baseline_m=0.5, augment={"p_flip": 0.0})
    values.update(over)
    return TrainConfig(**values)


def test_a_few_training_steps_reduce_the_loss(tmp_path):
    from metricslam_train.train import train

    torch.set_num_threads(1)
    cfg = _config(tmp_path, steps=12, lr_halve_at=[])
    train(cfg, progress=False)
    records = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == list(range(1, 13))
    assert set(records[0]) >= {"photo", "lr", "smooth", "sup", "loss"}
    first = np.mean([r["loss"] for r in records[:3]])
    last = np.mean([r["loss"] for r in records[-3:]])
    assert last < first


def test_training_resumes_and_exports(tmp_path):
    from metricslam.depth import DepthModel
    from metricslam_train.export import export_checkpoint
    from metricslam_train.train import train

    torch.set_num_threads(1)
    train(_config(tmp_path, steps=2), progress=False)
    final = train(_config(tmp_path, steps=3), progress=False)  # resumes from last.pt at step 2
    steps = [json.loads(line)["step"] for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3]
    contract = export_checkpoint(final, tmp_path / "m.onnx")
    model = DepthModel.load(tmp_path / "m.onnx")
    assert model.contract == contract
    assert "seq" in contract.training_data and contract.baseline_m == 0.5
    assert model.predict_d_frac([np.zeros((50, 70), np.uint8)]).shape == (1, H // 8, W // 8)


def test_an_ensemble_of_checkpoints_exports_the_mean_of_their_outputs(tmp_path):
    """Two seeds -> one ONNX graph, one contract; its output is the mean of the members' outputs."""
    from metricslam.depth import DepthModel
    from metricslam_train.export import export_checkpoint, export_ensemble
    from metricslam_train.train import train

    torch.set_num_threads(1)
    a = train(_config(tmp_path, steps=2, seed=1, run_dir=str(tmp_path / "a")), progress=False)
    b = train(_config(tmp_path, steps=2, seed=2, lr=5e-2, run_dir=str(tmp_path / "b")), progress=False)
    export_checkpoint(a, tmp_path / "a.onnx")
    export_checkpoint(b, tmp_path / "b.onnx")
    contract = export_ensemble([a, b], tmp_path / "ab.onnx")
    images = [(_texture(50, 70, seed=s) * 255).astype(np.uint8) for s in (5, 6)]
    d_a, d_b, d_ab = (DepthModel.load(tmp_path / f"{n}.onnx").predict_d_frac(images) for n in ("a", "b", "ab"))
    assert not np.allclose(d_a, d_b)  # the members differ, so the mean is a real test
    assert np.allclose(d_ab, (d_a + d_b) / 2, rtol=1e-5, atol=1e-7)
    single = DepthModel.load(tmp_path / "a.onnx").contract
    assert contract.params == 2 * single.params and contract.input_width == single.input_width
    assert DepthModel.load(tmp_path / "ab.onnx").contract == contract
    other = train(_config(tmp_path, steps=1, train_baseline_m=0.3, run_dir=str(tmp_path / "c")), progress=False)
    with pytest.raises(TrainingError, match="one contract"):
        export_ensemble([a, other], tmp_path / "bad.onnx")


def test_config_rejects_stale_keys(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("sequences: [a]\nlearning_rate: 0.1\n")
    with pytest.raises(TrainingError, match="learning_rate"):
        TrainConfig.from_yaml(path)
    with pytest.raises(TrainingError, match="does not exist"):
        TrainConfig.from_yaml(tmp_path / "missing.yaml")


def test_second_stage_starts_from_first_stage_weights(tmp_path):
    from metricslam_train.export import load_checkpoint
    from metricslam_train.train import train

    torch.set_num_threads(1)
    first = train(_config(tmp_path, steps=1), progress=False)
    second = train(_config(tmp_path, steps=1, run_dir=str(tmp_path / "run2"), init_from=str(first)), progress=False)
    meta = load_checkpoint(second)["meta"]
    assert "initialized from final.pt" in meta["training_data"]
    a, b = load_checkpoint(first)["model"], load_checkpoint(second)["model"]
    # one small Adam step away from the first stage, far closer than a fresh initialization
    fresh = PyramidDepthNet().state_dict()
    key = "estimators.0.out.weight"
    assert (b[key] - a[key]).abs().max() < (fresh[key] - a[key]).abs().max()


def test_exact_synthetic_disparity_agrees_with_block_matching_on_a_render(tmp_path):
    """The exact left/right disparities of a rendered pair (from its depth_0) match SGBM where
    SGBM is valid, to a fraction of a pixel, and cover more of the image than SGBM does."""
    from metricslam.synth import generate_sequence
    from metricslam.stereo import block_matching_pair
    from metricslam_train.data import exact_disparity_pair

    root = tmp_path / "synth"
    generate_sequence(root, 2, seed=21, path="straight", size=(620, 188))
    seq = read_stereo_sequence(root)
    assert len(seq.depth_paths) == 2
    left, right = (cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in (seq.left_paths[1], seq.right_paths[1]))
    depth_m = cv2.imread(str(seq.depth_paths[1]), cv2.IMREAD_UNCHANGED).astype(np.float32) / 256
    exact = exact_disparity_pair(depth_m, seq.fx_px, seq.baseline_m)
    sgbm = block_matching_pair(left, right, 64)
    for e, b in zip(exact, sgbm):
        both = (e > 0) & (b > 0)
        assert both.mean() > 0.4
        assert np.median(np.abs(e[both] - b[both])) < 0.5
        assert (e > 0).mean() >= (b > 0).mean()
    # and the cache built from it stores them as fractions of the width
    cache = build_cache(seq, tmp_path / "c.npz", train_baseline_m=seq.baseline_m, height=64, width=128,
                        exact_synthetic=True)
    with np.load(cache) as z:
        assert z["bm_left"].shape == (2, 64, 128)
        valid = z["bm_left"][1][z["bm_left"][1] > 0].astype(np.float32)
        assert np.median(valid) == pytest.approx(np.median(exact[0][exact[0] > 0]) / 620, rel=0.1)


def test_training_set_description_counts_repeated_entries():
    from metricslam_train.train import _with_counts
    assert _with_counts(["a", "a", "b", "a"]) == ["a, listed 3x", "b"]
    assert _with_counts(["a", "b"]) == ["a", "b"]


def test_weight_average_follows_the_weights_with_a_ramped_decay():
    from metricslam_train.train import WeightAverage

    net = torch.nn.Linear(2, 1)
    with torch.no_grad():
        net.weight.fill_(0.0)
    ema = WeightAverage(net, decay=0.9)
    with torch.no_grad():
        net.weight.fill_(1.0)
    ema.update(net, step=0)  # decay min(0.9, 1/10) = 0.1: mostly the new weights
    assert torch.allclose(ema.state["weight"], torch.full((1, 2), 0.9))
    for step in range(1, 200):
        ema.update(net, step)
    assert torch.allclose(ema.state["weight"], torch.ones(1, 2), atol=1e-6)
    assert ema.state["weight"] is not net.state_dict()["weight"]


def test_checkpoints_carry_the_weight_average_and_export_uses_it(tmp_path):
    from metricslam_train.export import export_checkpoint, load_checkpoint, network_from_checkpoint
    from metricslam_train.train import train

    torch.set_num_threads(1)
    final = train(_config(tmp_path, steps=3, ema_decay=0.99), progress=False)
    ckpt = load_checkpoint(final)
    assert set(ckpt["ema"]) == set(ckpt["model"])
    key = "estimators.0.out.weight"
    assert not torch.equal(ckpt["ema"][key], ckpt["model"][key])
    assert torch.equal(network_from_checkpoint(ckpt).state_dict()[key], ckpt["ema"][key])
    assert torch.equal(network_from_checkpoint(ckpt, "raw").state_dict()[key], ckpt["model"][key])
    export_checkpoint(final, tmp_path / "ema.onnx")
    export_checkpoint(final, tmp_path / "raw.onnx", weights="raw")
    assert (tmp_path / "ema.onnx").read_bytes() != (tmp_path / "raw.onnx").read_bytes()
    plain = train(_config(tmp_path, steps=1, run_dir=str(tmp_path / "plain")), progress=False)
    with pytest.raises(TrainingError, match="no weight average"):
        network_from_checkpoint(load_checkpoint(plain), "ema")


def test_sgbm_range_is_part_of_the_cache_name(tmp_path):
    from metricslam_train.train import prepare_caches

    paths = prepare_caches(_config(tmp_path, sgbm_num_disparities=64)).paths
    assert paths[0].name.endswith("_nd64.npz")
    with pytest.raises(ValidationError):
        _config(tmp_path, sgbm_num_disparities=100)


def test_fine_tuning_starts_from_an_exported_onnx_model(tmp_path):
    from metricslam_train.export import export_checkpoint, load_checkpoint, weights_from_onnx
    from metricslam_train.train import train

    torch.set_num_threads(1)
    first = train(_config(tmp_path, steps=1), progress=False)
    export_checkpoint(first, tmp_path / "m.onnx")
    state, contract = weights_from_onnx(tmp_path / "m.onnx")
    trained = load_checkpoint(first)["model"]
    assert set(state) == set(trained) and all(torch.equal(state[k], trained[k]) for k in state)
    second = train(_config(tmp_path, steps=1, lr=1e-12, run_dir=str(tmp_path / "ft"),
                           init_from=str(tmp_path / "m.onnx")), progress=False)
    ft = load_checkpoint(second)
    assert f"initialized from m.onnx ({contract.model_id})" in ft["meta"]["training_data"]
    key = "estimators.0.out.weight"
    assert torch.allclose(ft["model"][key], trained[key], atol=1e-6)  # a vanishing step away
    with pytest.raises(TrainingError, match="does not exist"):
        weights_from_onnx(tmp_path / "missing.onnx")
    with pytest.raises(TrainingError, match="one network, not an ensemble"):
        weights_from_onnx(tmp_path / "m.onnx", member=0)


def test_fine_tuning_starts_from_one_network_of_a_seed_ensemble(tmp_path):
    """The shipped float32 default is a seed ensemble (``nets.<i>.`` weights): ``init_member``
    picks the network a fine-tune starts from; without it the error says how."""
    from metricslam_train.export import export_ensemble, load_checkpoint, weights_from_onnx
    from metricslam_train.train import train

    torch.set_num_threads(1)
    a = train(_config(tmp_path, steps=1, model_id="seed-a", run_dir=str(tmp_path / "a")), progress=False)
    b = train(_config(tmp_path, steps=1, model_id="seed-b", seed=7, run_dir=str(tmp_path / "b")), progress=False)
    gen = torch.Generator().manual_seed(0)
    for ckpt in (a, b):  # one step leaves untrained heads equal across members (the exporter merges equal tensors)
        c = load_checkpoint(ckpt)
        c["model"] = {k: v + 1e-3 * torch.randn(v.shape, generator=gen) for k, v in c["model"].items()}
        torch.save(c, ckpt)
    export_ensemble([a, b], tmp_path / "ens.onnx", weights="raw")
    for member, ckpt in enumerate((a, b)):
        state, contract = weights_from_onnx(tmp_path / "ens.onnx", member)
        trained = load_checkpoint(ckpt)["model"]
        assert all(torch.equal(state[k], trained[k]) for k in trained)
        assert contract.model_id == ("seed-a", "seed-b")[member]
    for bad in (None, 2):
        with pytest.raises(TrainingError, match=r"seed ensemble of 2 networks \(seed-a\+seed-b\).*init_member: 0 … 1"):
            weights_from_onnx(tmp_path / "ens.onnx", bad)
    ft = train(_config(tmp_path, steps=1, lr=1e-12, run_dir=str(tmp_path / "ft"), init_from=str(tmp_path / "ens.onnx"),
                       init_member=1), progress=False)
    assert "initialized from ens.onnx network 1 (seed-b)" in load_checkpoint(ft)["meta"]["training_data"]
    with pytest.raises(ValidationError, match="init_member"):
        _config(tmp_path, init_member=0)


def test_the_shipped_float32_model_can_start_a_fine_tune():
    """docs/own_camera.md fine-tunes from the shipped float32 model: each of its networks loads."""
    from metricslam.depth import FLOAT32_MODEL_PATH
    from metricslam_train.export import weights_from_onnx

    import onnx
    from metricslam.depth.contract import ModelContract

    shipped = ModelContract.from_metadata({p.key: p.value for p in onnx.load(str(FLOAT32_MODEL_PATH)).metadata_props})
    ids = []
    for member in range(3):
        state, contract = weights_from_onnx(FLOAT32_MODEL_PATH, member)
        ids.append(contract.model_id)
        assert state and all(torch.isfinite(v.float()).all() for v in state.values())
    assert "+".join(ids) == shipped.model_id and len(set(ids)) == 3


def test_canonical_runs_know_each_caches_focal_length_at_the_input(tmp_path):
    from metricslam_train.data import read_stereo_sequence
    from metricslam_train.train import canonical_label_scales, prepare_caches

    assert prepare_caches(_config(tmp_path)).input_fx_px is None  # contract v1: not needed
    cfg = _config(tmp_path, canonical_fx_px=100.0, canonical_fy_px=90.0)
    caches = prepare_caches(cfg)
    seq = read_stereo_sequence(cfg.sequences[0])
    width_full = cv2.imread(str(seq.left_paths[0]), cv2.IMREAD_UNCHANGED).shape[1]
    assert caches.input_fx_px == [pytest.approx(seq.fx_px * W / width_full)]
    assert canonical_label_scales(cfg, caches) == [pytest.approx(100.0 / caches.input_fx_px[0])]


def test_a_wider_network_trains_and_exports_with_its_width(tmp_path):
    """``width`` (issue #31's wider-network experiment) multiplies every channel count; the
    checkpoint records it, so export rebuilds the same network."""
    from metricslam_train.export import export_checkpoint, load_checkpoint, network_from_checkpoint
    from metricslam_train.network import PyramidDepthNet, count_parameters
    from metricslam_train.train import train

    torch.set_num_threads(1)
    narrow, wide = (count_parameters(PyramidDepthNet(width=w)) for w in (1.0, 1.7))
    assert 2.5 * narrow < wide < 5_000_000  # the bound on a wider network
    ckpt = train(_config(tmp_path, steps=1, width=0.5), progress=False)
    meta = load_checkpoint(ckpt)["meta"]
    net = network_from_checkpoint(load_checkpoint(ckpt), "raw")
    assert meta["width"] == 0.5 and count_parameters(net) < narrow / 3
    contract = export_checkpoint(ckpt, tmp_path / "w.onnx")
    assert contract.params == count_parameters(net)
