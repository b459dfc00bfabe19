"""Resumable training loop: caches, augmentation, Eq. 3 loss, checkpoints, per-term log.

Files in ``run_dir``: ``last.pt`` (resumable: model, optimizer, step, RNG), ``step_XXXXXX.pt``
snapshots, ``log.jsonl`` (one line per step: every loss term and the learning rate),
``config.yaml`` (the config used). Running again with the same ``run_dir`` resumes.
"""

from __future__ import annotations

import glob
import json
import logging
import time
from collections import Counter
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
import yaml

from metricslam.errors import TrainingError
from metricslam_train.config import TrainConfig
from metricslam_train.data import StereoPairs, augment, build_cache, build_depth_cache, pad_window, read_stereo_sequence, zoom
from metricslam_train.export import git_commit
from metricslam_train.losses import LossWeights, total_loss
from metricslam_train.network import PyramidDepthNet, count_parameters

log = logging.getLogger("metricslam.train")


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class Caches(NamedTuple):
    """What :func:`prepare_caches` returns: the cache files, a description of the training set,
    and (contract v2 only, else None) each cache's focal length at the network input, px."""

    paths: list[Path]
    description: str
    input_fx_px: list[float] | None


def prepare_caches(cfg: TrainConfig) -> Caches:
    """Build missing caches; return them with a description of the training set."""
    canonical = cfg.canonical_fx_px is not None
    paths, names, seen_names, input_fx = [], [], set(), []
    for entry in cfg.sequences:
        folders = expand_sequences(entry)
        n_pairs = 0
        for folder in folders:
            seq = read_stereo_sequence(folder, cfg.frame_step)
            seen_names.add(seq.name)
            exact = cfg.exact_synthetic_disparity and bool(seq.depth_paths)
            offset_px = float(cfg.disparity_offsets_px.get(seq.name, 0.0))
            tag = (f"{seq.name}_{cfg.input_height}x{cfg.input_width}_s{cfg.frame_step}{'_exact' if exact else ''}"
                   + (f"_off{offset_px:+.2f}px" if offset_px else "")
                   + (f"_nd{cfg.sgbm_num_disparities}" if cfg.sgbm_num_disparities != 128 else ""))
            path = Path(cfg.cache_dir) / f"{tag}.npz"
            if not path.is_file():
                log.info("building cache %s from %s", path, folder)
                build_cache(seq, path, cfg.train_baseline_m, cfg.input_height, cfg.input_width,
                            num_disparities=cfg.sgbm_num_disparities, exact_synthetic=exact,
                            disparity_offset_px=offset_px)
            paths.append(path)
            if canonical:
                input_fx.append(seq.fx_px * cfg.input_width / _image_width(seq.left_paths[0]))
            n_pairs += len(seq.left_paths)
        label = seq.name if len(folders) == 1 else f"{len(folders)} sequences"
        fixed = f", disparity offset {cfg.disparity_offsets_px[seq.name]:+.2f} px removed" \
            if len(folders) == 1 and cfg.disparity_offsets_px.get(seq.name) else ""
        names.append(f"{label} ({n_pairs} pairs{fixed}, {entry})")
    unknown = set(cfg.disparity_offsets_px) - seen_names
    if unknown:
        raise TrainingError(f"disparity_offsets_px names {sorted(unknown)} match no sequence (known: "
                            f"{sorted(seen_names)})")
    depth_paths, depth_names, depth_fx = _depth_frame_caches(cfg)
    return Caches(paths + depth_paths, "; ".join(_with_counts(names) + depth_names),
                  input_fx + depth_fx if canonical else None)


def _with_counts(names: list[str]) -> list[str]:
    """``["a", "a", "b"]`` → ``["a, listed 2x", "b"]`` (a sequence listed N times is N-fold weight)."""
    counts = Counter(names)
    return [name if counts[name] == 1 else f"{name}, listed {counts[name]}x" for name in dict.fromkeys(names)]


def _depth_frame_caches(cfg: TrainConfig) -> tuple[list[Path], list[str], list[float]]:
    """Build missing caches of ``cfg.depth_frames`` (each path listed ``repeat`` times); also each
    path's focal length at the network input (px)."""
    paths, names, input_fx = [], [], []
    for frames in cfg.depth_frames:
        stop = "end" if frames.stop is None else frames.stop
        tag = f"{Path(frames.folder).name}_f{frames.first}-{stop}_{cfg.input_height}x{cfg.input_width}_depth"
        path = Path(cfg.cache_dir) / f"{tag}.npz"
        if not path.is_file():
            log.info("building depth cache %s from %s", path, frames.folder)
            build_depth_cache(frames.folder, path, cfg.train_baseline_m, frames.first, frames.stop,
                              cfg.input_height, cfg.input_width)
        paths.extend([path] * frames.repeat)
        with np.load(path) as z:
            n_images = len(z["left"])
            fx_full = float(z["fx_px"])
        first = sorted((Path(frames.folder) / "image_02").glob("*.png"))[0]
        input_fx.extend([fx_full * cfg.input_width / _image_width(first)] * frames.repeat)
        names.append(f"{Path(frames.folder).name} frames {frames.first}..{stop} ({n_images} images with "
                     f"metric depth, supervision only, x{frames.repeat}, {frames.folder})")
    return paths, names, input_fx


def expand_sequences(entry: str) -> list[Path]:
    """One ``sequences`` entry -> folders: a path, or a glob (``runs/synth_train/w*``), sorted."""
    if not any(c in entry for c in "*?["):
        return [Path(entry)]
    folders = sorted(Path(p) for p in glob.glob(entry) if Path(p).is_dir())
    if not folders:
        raise TrainingError(f"sequences entry {entry!r} matches no folder: generate them first "
                            "(see the config's header)")
    return folders


def checkpoint_meta(cfg: TrainConfig, training_data: str) -> dict:
    """What export needs to write the model contract."""
    return {
        "model_id": cfg.model_id,
        "max_d_frac": cfg.max_d_frac,
        "width": cfg.width,
        "input_height": cfg.input_height,
        "input_width": cfg.input_width,
        "normalization": {"scale": 1 / 255, "mean": cfg.norm_mean, "std": cfg.norm_std},
        "baseline_m": cfg.train_baseline_m,
        "training_data": training_data,
        "training_commit": git_commit(),
        **({"canonical_fx_px": cfg.canonical_fx_px, "canonical_fy_px": cfg.canonical_fy_px,
            "valid_min_fraction": cfg.valid_min_fraction} if cfg.canonical_fx_px is not None else {}),
    }


def canonical_label_scales(cfg: TrainConfig, caches: Caches) -> list[float] | None:
    """Per cache ``k = canonical_fx / fx_input`` (contract v2: the labels' d_frac is asked for at the
    canonical focal length instead of the drive's); None for contract v1."""
    if caches.input_fx_px is None:
        return None
    return [cfg.canonical_fx_px / fx for fx in caches.input_fx_px]


def _image_width(path: str | Path) -> float:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise TrainingError(f"cannot read {path}")
    return float(image.shape[1])


def _lr_at(cfg: TrainConfig, step: int) -> float:
    halvings = sum(step >= int(f * cfg.steps) for f in cfg.lr_halve_at)
    return cfg.lr * 0.5**halvings


class WeightAverage:
    """Exponential moving average of a network's floating-point state (Polyak averaging).

    ``update(net, step)`` after each optimizer step; ``state`` is a ``state_dict`` the network
    loads as is. The decay ramps up as ``min(decay, (1 + step) / (10 + step))`` so the first
    steps do not freeze the random initialization in.
    """

    def __init__(self, net: torch.nn.Module, decay: float) -> None:
        self.decay = float(decay)
        self.state = {k: v.detach().clone() for k, v in net.state_dict().items()}

    @torch.no_grad()
    def update(self, net: torch.nn.Module, step: int) -> None:
        d = min(self.decay, (1.0 + step) / (10.0 + step))
        for key, value in net.state_dict().items():
            if value.dtype.is_floating_point:
                self.state[key].mul_(d).add_(value.detach(), alpha=1.0 - d)
            else:
                self.state[key].copy_(value)


def train(cfg: TrainConfig, progress: bool = True) -> Path:
    """Train (or resume) to ``cfg.steps``; returns the path of the final checkpoint."""
    from tqdm import tqdm

    torch.set_num_threads(cfg.threads)
    device = pick_device(cfg.device)
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(yaml.safe_dump(json.loads(cfg.model_dump_json()), sort_keys=False))
    onnx_init = None
    if cfg.init_from and cfg.init_from.endswith(".onnx"):  # before the caches: a wrong file fails at once
        from metricslam_train.export import weights_from_onnx

        onnx_init = weights_from_onnx(cfg.init_from, cfg.init_member)
    caches = prepare_caches(cfg)
    training_data = caches.description
    data = StereoPairs(caches.paths, canonical_label_scales(cfg, caches))
    if len(data) < 1:
        raise TrainingError("the training caches hold no pairs")

    torch.manual_seed(cfg.seed)
    net = PyramidDepthNet(max_d_frac=cfg.max_d_frac, width=cfg.width).to(device)
    optim = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    step = 0
    last = run_dir / "last.pt"
    if onnx_init is not None:
        state, contract = onnx_init
        if not last.is_file():
            try:
                net.load_state_dict(state)
            except RuntimeError as exc:  # e.g. another width
                raise TrainingError(f"init_from {cfg.init_from} does not fit this config's network "
                                    f"(width {cfg.width:g}): {str(exc).splitlines()[0]}") from None
            log.info("initialized weights from %s (%s)", cfg.init_from, contract.model_id)
        which = "" if cfg.init_member is None else f" network {cfg.init_member}"
        training_data = (f"{training_data}; initialized from {Path(cfg.init_from).name}{which} ({contract.model_id}), "
                         f"trained on: {contract.training_data}")
    elif cfg.init_from:
        init = torch.load(cfg.init_from, map_location=device, weights_only=False)
        if "model" not in init or "meta" not in init:
            raise TrainingError(f"init_from {cfg.init_from} is not a metricslam training checkpoint")
        if not last.is_file():
            net.load_state_dict(init["model"])
            log.info("initialized weights from %s", cfg.init_from)
        training_data = (f"{training_data}; initialized from {Path(cfg.init_from).name}, trained on: "
                         f"{init['meta']['training_data']}")
    ema = WeightAverage(net, cfg.ema_decay) if cfg.ema_decay else None
    if last.is_file():
        ckpt = torch.load(last, map_location=device, weights_only=False)
        net.load_state_dict(ckpt["model"])
        if ema is not None:
            ema.state = ckpt["ema"] if "ema" in ckpt else {k: v.detach().clone() for k, v in net.state_dict().items()}
        optim.load_state_dict(ckpt["optim"])
        step = int(ckpt["step"])
        rng.bit_generator.state = ckpt["np_rng"]
        gen.set_state(ckpt["torch_rng"])
        log.info("resumed from %s at step %d", last, step)
    log.info("training %s: %d params, %d pairs, device %s", cfg.model_id, count_parameters(net), len(data), device)

    meta = checkpoint_meta(cfg, training_data)
    weights = LossWeights(cfg.loss.photo, cfg.loss.lr, cfg.loss.smooth, cfg.loss.sup)

    def save(path: Path) -> None:
        torch.save({"model": net.state_dict(), "optim": optim.state_dict(), "step": step, "meta": meta,
                    "np_rng": rng.bit_generator.state, "torch_rng": gen.get_state(),
                    "config": json.loads(cfg.model_dump_json()),
                    **({"ema": ema.state} if ema is not None else {})}, path.with_suffix(".tmp"))
        path.with_suffix(".tmp").replace(path)

    net.train()
    bar = tqdm(total=cfg.steps, initial=step, disable=not progress, desc=cfg.model_id)
    with (run_dir / "log.jsonl").open("a") as log_file:
        while step < cfg.steps:
            lr = _lr_at(cfg, step)
            for group in optim.param_groups:
                group["lr"] = lr
            idx = rng.choice(len(data), size=min(cfg.batch_size, len(data)), replace=len(data) < cfg.batch_size)
            batch = [data[int(i)] for i in idx]
            left, right, bm_l, bm_r, ratio, stereo = (torch.stack(t) for t in zip(*batch))
            a = cfg.augment
            left, right, bm_l, bm_r = augment(left, right, bm_l, bm_r, gen, a.p_flip, a.gamma_range,
                                              a.brightness_range)
            left, right, bm_l, bm_r = zoom(left, right, bm_l, bm_r, gen, a.p_zoom, a.zoom_range)
            left, right, bm_l, bm_r = pad_window(left, right, bm_l, bm_r, gen, a.p_pad, a.pad_width_range,
                                                 a.pad_height_range)
            left, right, bm_l, bm_r, ratio, stereo = (t.to(device) for t in (left, right, bm_l, bm_r, ratio, stereo))
            t0 = time.perf_counter()
            outputs = net((left - cfg.norm_mean) / cfg.norm_std)
            loss, terms = total_loss(outputs, left, right, bm_l, bm_r, ratio, weights, cfg.loss.scales,
                                     cfg.loss.huber_delta, cfg.loss.sup_space == "log",
                                     stereo if cfg.depth_frames else None, cfg.loss.label_pooling)
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            if ema is not None:
                ema.update(net, step)
            step += 1
            record = {"step": step, "loss": float(loss.detach()), **terms, "learning_rate": lr,
                      "d3_mean": float(outputs[0][:, 0].mean().detach()), "s": round(time.perf_counter() - t0, 4)}
            log_file.write(json.dumps(record) + "\n")
            bar.update(1)
            bar.set_postfix(loss=f"{record['loss']:.3f}", photo=f"{terms['photo']:.3f}", sup=f"{terms['sup']:.3f}")
            if step % 20 == 0:
                log_file.flush()
            if step % cfg.checkpoint_every == 0 or step == cfg.steps:
                log_file.flush()
                save(last)
                save(run_dir / f"step_{step:06d}.pt")
    bar.close()
    final = run_dir / "final.pt"
    save(final)
    return final
