"""Frozen training configuration, read from YAML (``metricslam train --config CONFIG.yaml``)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from metricslam.errors import TrainingError


class AugmentConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    p_flip: float = Field(0.5, ge=0, le=1)
    gamma_range: tuple[float, float] = (0.8, 1.2)
    brightness_range: tuple[float, float] = (0.7, 1.4)
    #: scale augmentation (data.zoom): probability per pair and the magnification range (>= 1,
    #: log-uniform); labels scale with the magnification. Off by default.
    p_zoom: float = Field(0.0, ge=0, le=1)
    zoom_range: tuple[float, float] = (1.0, 1.0)
    #: field-of-view augmentation for the canonical camera (data.pad_window, contract v2): with
    #: probability ``p_pad`` only a centred window (width/height fractions drawn from the ranges) of
    #: the input keeps its pixels, the rest is padded as inference pads a narrower camera. Off by default.
    p_pad: float = Field(0.0, ge=0, le=1)
    pad_width_range: tuple[float, float] = (0.35, 1.0)
    pad_height_range: tuple[float, float] = (0.5, 1.0)


class LossConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    photo: float = 1.0
    lr: float = 1.0
    smooth: float = 0.1
    sup: float = 10.0
    #: pyramid levels the loss is summed over (0 = base 256x512 … 6); D0..D2 come from D3.
    scales: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6)
    #: where the supervision term compares disparities: "d_frac" (the paper's eq. 7) or "log"
    #: (relative error; every depth range counts alike, see losses.supervision)
    sup_space: Literal["d_frac", "log"] = "d_frac"
    #: Huber threshold of the supervision term in ``sup_space`` units (d_frac: 0.005 = 2.6 px at
    #: 512 wide; log: 0.05 = 5 %).
    huber_delta: float = Field(0.005, gt=0)
    #: how block-matching / LiDAR targets are reduced to the coarse scales: "mean" of the valid
    #: disparities per cell, or their "median" (what the SGBM oracle of bench/landmark_depth.py
    #: scores; the mean leans to the nearer surface at depth edges)
    label_pooling: Literal["mean", "median"] = "mean"


class DepthFramesConfig(BaseModel):
    """Single images with metric depth (a KITTI-raw layout folder: ``image_02/``, ``depth_02/``
    uint16 metres x 256, ``calib.txt`` with ``K:``), e.g. projected LiDAR.

    They are supervised only (no right image: no photometric or left-right term). Frames
    ``first <= i < stop`` are used; keep the others out for validation.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    folder: str
    first: int = Field(0, ge=0)
    stop: int | None = Field(None, ge=1)
    #: how many times the frames are listed (sampling weight against the stereo pairs)
    repeat: int = Field(1, ge=1)


class TrainConfig(BaseModel):
    """Everything that determines a training run.

    ``sequences`` are KITTI-layout stereo folders (``image_0``, ``image_1``, ``calib.txt``);
    each is preprocessed once into ``cache_dir`` (uint8 pairs + SGBM disparity).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    model_id: str = "pyramid-l3"
    sequences: tuple[str, ...]
    #: measured disparity offset (observed − true, full-resolution px) of a stereo sequence's pair,
    #: by sequence name (``kitti01``): the right images are shifted to remove it before caching.
    #: Measure it on the TRAINING sequence only, e.g. ``bench/scale_upper_bound.py``'s
    #: ``stereo_check`` (corners triangulated with the sequence's ground-truth motion).
    disparity_offsets_px: dict[str, float] = Field(default_factory=dict)
    #: images with metric depth (LiDAR), supervised only; see :class:`DepthFramesConfig`
    depth_frames: tuple[DepthFramesConfig, ...] = ()
    cache_dir: str = "runs/depth_cache"
    run_dir: str = "runs/depth"
    frame_step: int = Field(1, ge=1)
    #: rendered sequences (with ``depth_0/``) supervise with their exact disparity, not SGBM
    exact_synthetic_disparity: bool = False
    #: SGBM search range of the stereo labels, full-resolution px (multiple of 16). KITTI's
    #: fx·B ≈ 387 px·m: 128 px reaches 3.0 m, 192 px 2.0 m; nearer surfaces get no (or aliased)
    #: labels. Part of the cache name, so changing it rebuilds the caches.
    sgbm_num_disparities: int = Field(128, ge=16, multiple_of=16)
    train_baseline_m: float = Field(0.537, gt=0)
    input_height: int = Field(256, gt=0, multiple_of=64)
    input_width: int = Field(512, gt=0, multiple_of=64)
    norm_mean: float = 0.45
    norm_std: float = Field(0.25, gt=0)
    max_d_frac: float = Field(0.3, gt=0, le=1)
    #: channel multiplier of the network (``network.PyramidDepthNet``; cost ~ its square); 1.0 ships
    width: float = Field(1.0, gt=0, le=2)
    steps: int = Field(3000, ge=1)
    batch_size: int = Field(8, ge=1)
    lr: float = Field(1e-4, gt=0)
    #: fractions of ``steps`` after which the learning rate halves (the paper halves after epochs 30
    #: and 40 of 100; our short CPU runs are far from converged by then, so we halve later)
    lr_halve_at: tuple[float, ...] = (0.6, 0.8)
    loss: LossConfig = LossConfig()
    augment: AugmentConfig = AugmentConfig()
    #: optional checkpoint whose weights start this run (a second training stage), or a float32
    #: ONNX model written by `metricslam export` (e.g. the shipped depth_l3.onnx: fine-tune it);
    #: the optimizer and step count start fresh, and its training data is recorded with this run's.
    init_from: str | None = None
    #: with ``init_from`` a seed ensemble ONNX (the shipped ``depth_l3.onnx`` since v4): which of
    #: its networks starts this run (0 … N-1; one network costs a third of a three-seed ensemble per
    #: keyframe); None for a single network or a checkpoint
    init_member: int | None = Field(None, ge=0)
    #: canonical camera (depth contract v2, ``metricslam.depth.canonical``): the network input's focal
    #: lengths, px at ``input_width x input_height``; both or neither. None: contract v1 (the whole
    #: image resized). With them, each cache's labels are rescaled to the canonical focal length.
    canonical_fx_px: float | None = Field(None, gt=0)
    canonical_fy_px: float | None = Field(None, gt=0)
    #: contract v2's ``valid_min_fraction``: output cells with less real (unpadded) input are invalid
    valid_min_fraction: float = Field(0.75, gt=0, le=1)
    checkpoint_every: int = Field(250, ge=1)
    #: exponential moving average of the weights (Polyak averaging), updated every step with
    #: decay ``min(ema_decay, (1 + step) / (10 + step))``; checkpoints carry it as ``ema`` and
    #: export uses it. ``None`` = off. 0.999 averages over roughly the last 1,000 steps, which
    #: damps the checkpoint-to-checkpoint swings of the metric level.
    ema_decay: float | None = Field(None, gt=0, lt=1)
    seed: int = 0
    threads: int = Field(1, ge=1)
    device: str = "auto"

    @model_validator(mode="after")
    def _canonical_both_or_neither(self) -> "TrainConfig":
        if (self.canonical_fx_px is None) != (self.canonical_fy_px is None):
            raise ValueError("canonical_fx_px and canonical_fy_px go together: give both (contract v2) or neither (v1)")
        if self.init_member is not None and not (self.init_from or "").endswith(".onnx"):
            raise ValueError("init_member names a network of an ONNX ensemble: it needs init_from: MODEL.onnx")
        return self

    @classmethod
    def from_yaml(cls, path: str | Path) -> "TrainConfig":
        p = Path(path)
        if not p.is_file():
            raise TrainingError(f"config {p} does not exist (see training/configs/shipped/train_depth.yaml for an example)")
        try:
            raw = yaml.safe_load(p.read_text()) or {}
            return cls(**raw)
        except (yaml.YAMLError, ValidationError, TypeError) as exc:
            raise TrainingError(f"{p}: invalid training config: {exc}") from exc
