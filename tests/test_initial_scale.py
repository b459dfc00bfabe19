"""Issue #19 item 1: metric from the first pose.

When the VO first has a map, the initial keyframe's depth (bounded wait) gives a provisional
metric scale; the first TRACKING pose is then already metric and says ``provisional``, frames
before it ``unscaled``, and ``metric`` once the graph's scale factors establish the scale. A
slow, failing or unreachable source leaves the poses ``unscaled``; the step is off unless
configured (offline runs are unchanged) and on in the live service's profile."""

from __future__ import annotations

import hashlib
import time

import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.datasets import open_sequence
from metricslam.errors import DepthSourceError
from metricslam.slam.config_file import load_system_config
from metricslam.slam.events import InitialScaleApplied
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.initial_scale import InitialScaleConfig, measure_initial_scale
from metricslam.slam.session_builder import build_session, preset_for
from metricslam.slam.system_config import LIVE_PROFILE, SystemConfig
from metricslam.slam.types import ScaleState, TrackingState

CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)
IMAGE = np.zeros((48, 64), dtype=np.uint8)
UV = np.stack(np.meshgrid(np.linspace(5, 58, 6), np.linspace(5, 42, 4)), -1).reshape(-1, 2)


class ConstantDepth:
    """Inverse depth ``inv_depth_per_m`` everywhere, after ``delay_s``."""

    def __init__(self, inv_depth_per_m: float, delay_s: float = 0.0) -> None:
        self.inv_depth_per_m, self.delay_s, self.calls = inv_depth_per_m, delay_s, 0

    def inv_depth_map(self, image, camera) -> np.ndarray:
        self.calls += 1
        time.sleep(self.delay_s)
        return np.full((8, 16), self.inv_depth_per_m, dtype=np.float32)


class Failing:
    reachable = None

    def inv_depth_map(self, image, camera):
        raise DepthSourceError("service said no")


def _measure(source, xi=None, **config):
    xi = np.full(len(UV), 0.1) if xi is None else xi
    return measure_initial_scale(source, IMAGE, CAMERA, UV, xi, 7, InitialScaleConfig(**config),
                                 GraphConfig())


def test_scale_is_the_robust_ratio_of_vo_to_metric_inverse_depth() -> None:
    xi = np.full(len(UV), 0.1)
    xi[:3] = [5.0, 0.001, 9.0]  # outliers the Huber estimate must shrug off
    res = _measure(ConstantDepth(0.05), xi)
    assert res.error == "" and res.frame_index == 7
    assert res.scale == pytest.approx(2.0, rel=0.05) and res.n_landmarks == len(UV)


def test_no_answer_in_time_or_a_failure_gives_no_scale() -> None:
    t0 = time.monotonic()
    slow = _measure(ConstantDepth(0.05, delay_s=2.0), timeout_s=0.2)
    assert time.monotonic() - t0 < 1.5 and slow.scale is None and "within 0.2 s" in slow.error
    failed = _measure(Failing())
    assert failed.scale is None and "service said no" in failed.error
    unreachable = Failing()
    unreachable.reachable = False
    assert "unreachable" in _measure(unreachable).error  # not even asked
    assert "min_landmarks" in _measure(ConstantDepth(0.05), min_landmarks=100).error
    assert "usable" in _measure(ConstantDepth(1e-4)).error  # sky everywhere: no measurement
    assert _measure(None).error == "no depth source"


def test_the_live_profile_turns_it_on_and_offline_runs_keep_it_off() -> None:
    assert SystemConfig().initial_scale.enabled is False
    assert load_system_config(None, env={}, profile=LIVE_PROFILE).initial_scale.enabled is True
    off = load_system_config(None, env={"METRICSLAM_INITIAL_SCALE__ENABLED": "false"}, profile=LIVE_PROFILE)
    assert off.initial_scale.enabled is False


class RenderedDepth:
    """The rendered (true) inverse depth of each known image (1/m)."""

    def __init__(self, seq) -> None:
        self._inv = {}
        for i in range(len(seq)):
            frame = seq[i]
            inv = np.where(frame.depth_m > 0, 1.0 / np.maximum(frame.depth_m, 1e-6), 0.0)
            self._inv[hashlib.blake2b(frame.image.tobytes(), digest_size=16).hexdigest()] = inv.astype(np.float32)

    def inv_depth_map(self, image, camera) -> np.ndarray:
        return self._inv[hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=16).hexdigest()]


def _run(seq_dir, source, **initial_scale):
    seq = open_sequence(seq_dir)
    config = load_system_config(None, env={}, overrides={"deterministic": True,
                                                         "initial_scale": initial_scale})
    pipe = build_session(seq.camera, config, depth_source=source, default_preset=preset_for(seq_dir))
    applied: list[InitialScaleApplied] = []
    pipe.backend.events.subscribe(applied.append, InitialScaleApplied)
    try:
        live = [pipe.process(seq[i]) for i in range(len(seq))]
    finally:
        pipe.close()
    return seq, live, pipe.stats(), applied


@pytest.mark.slow
def test_the_first_tracked_pose_is_already_metric(synth_sequence) -> None:
    seq_dir = synth_sequence(60, seed=3, path="loop")
    seq, live, stats, applied = _run(seq_dir, RenderedDepth(open_sequence(seq_dir)), enabled=True)
    first = next(k for k, e in enumerate(live) if e.state is TrackingState.TRACKING)
    assert all(e.scale_state is ScaleState.UNSCALED for e in live[:first])
    assert live[first].scale_state is ScaleState.PROVISIONAL and len(applied) == 1
    gt = seq.T_world_cam_gt
    ref = stats["initial_scale"]["frame_index"]  # the initialization's reference: the VO origin
    # the first tracked pose, and later ones, are metric: distance from the reference vs truth
    for k in (first, first + 5, len(live) - 1):
        d_est = np.linalg.norm(live[k].T_world_cam[:3, 3])
        d_gt = np.linalg.norm(gt[k][:3, 3] - gt[ref][:3, 3])
        assert d_est == pytest.approx(d_gt, rel=0.1), (k, d_est, d_gt)
    states = [e.scale_state for e in live]
    assert ScaleState.METRIC in states and states.index(ScaleState.METRIC) == stats["first_metric_frame"]
    assert all(s is ScaleState.METRIC for s in states[stats["first_metric_frame"]:])
    assert sum(stats["scale_states"].values()) == len(live)
    assert stats["scale_states"]["unscaled"] == first
    assert stats["initial_scale"]["error"] == "" and stats["initial_scale"]["n_landmarks"] >= 8
    assert live[-1].scale_factors > 0


@pytest.mark.slow
def test_without_an_answer_poses_stay_unscaled_and_say_so(synth_sequence) -> None:
    seq_dir = synth_sequence(60, seed=3, path="loop")
    _, live, stats, applied = _run(seq_dir, Failing(), enabled=True, timeout_s=0.5)
    assert not applied and all(e.scale_state is ScaleState.UNSCALED for e in live)
    assert "service said no" in stats["initial_scale"]["error"]
    assert stats["scale_states"] == {"unscaled": len(live), "provisional": 0, "metric": 0}
