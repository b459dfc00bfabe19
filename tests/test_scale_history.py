"""The system's scale estimate over time (``metricslam run --json`` → ``scale_history``).

A short rendered drive (``metricslam.synth``, exact metric ground truth, world seed 3 — the depth
network's synthetic training worlds use seeds 11–16) runs through the real pipeline: once with
``metricslam run --json`` (threaded back end, shipped ONNX depth network) and once with
``--no-scale`` (inline back end). The recorded history must be internally consistent (one record
per marginalized keyframe, live scale = running product of the applied warps, optimized = kf
scale × live) and, with learned scale, close to the true metres per VO unit from ground truth —
which the ``--no-scale`` run must *not* claim to know (its scale stays the VO's own).
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from metricslam.camera import PinholeCamera
from metricslam.errors import DepthSourceError
from metricslam.slam.events import ScaleMeasured, Solved
from metricslam.slam.graph.backend import GlobalBackend
from metricslam.slam.graph.config import GraphConfig, LoopConfig
from metricslam.slam.scale_history import ScaleHistory
from metricslam.slam.types import MarginalizedKeyframe
from pipeline_run import run_inline

FRAMES = 70


@pytest.fixture(scope="module")
def drive(synth_sequence):
    return synth_sequence(FRAMES, seed=3, path="loop")


def _true_m_per_vo0(history: list[dict], gt_path) -> float:
    """Ground truth (reference only): GT path over VO path in the VO's initial units, between
    consecutive keyframes of one segment (positions of the keyframes' frames)."""
    from metricslam.trajectory.io import read_kitti_poses

    p_gt = read_kitti_poses(gt_path)[:, :3, 3]
    gt_m, vo0 = 0.0, 0.0
    for prev, rec in itertools.pairwise(history):
        if rec["step_vo"] is None or rec["segment_id"] != prev["segment_id"]:
            continue
        gt_m += float(np.linalg.norm(p_gt[rec["frame_index"]] - p_gt[prev["frame_index"]]))
        vo0 += rec["step_vo"] / rec["scale_live"]
    return gt_m / vo0


def _check_consistent(stats: dict) -> None:
    hist, corr = stats["scale_history"], stats["scale_corrections"]
    assert len(hist) == stats["marginalized_keyframes"] > 5
    frames = [r["frame_index"] for r in hist]
    assert frames == sorted(frames) and len(set(frames)) == len(frames)
    assert all(r["t_ns"] == r["frame_index"] * 100_000_000 for r in hist)  # synth: 10 Hz from 0
    assert len(corr) == stats["corrections_applied"]
    running = 1.0
    for c in corr:
        running *= c["s"]
        assert c["scale_live"] == pytest.approx(running, rel=1e-9)
    lives = {1.0, *(c["scale_live"] for c in corr)}
    for r in hist:
        assert r["scale_live"] in lives  # a keyframe's live scale is one the VO really had
        if r["scale_optimized"] is not None:
            assert r["scale_optimized"] == pytest.approx(r["scale_kf_optimized"] * r["scale_live"])


def test_run_json_records_the_metric_scale(drive, tmp_path):
    from metricslam_cli.main import main

    stats_path = tmp_path / "stats.json"
    assert main(["run", str(drive), "--out", str(tmp_path / "est.txt"), "--json",
                 str(stats_path), "--no-progress"]) == 0
    stats = json.loads(stats_path.read_text())
    assert stats["mode"] == "metric"
    _check_consistent(stats)
    hist = stats["scale_history"]
    measured = [r for r in hist if r["scale_factors"]]
    # every answered depth request (and only those) left its measurements; offline runs wait for
    # depth (--depth-queue) instead of dropping requests, so results do not depend on load: every
    # keyframe but the last one or two (too few landmarks left) has its measurements
    backend = stats["backend"]
    assert backend["depth_dropped"] == 0
    assert len(hist) - 2 <= len(measured) <= backend["depth_requests"] - backend["depth_failures"]
    assert all(r["scale_measured_median"] > 0 for r in measured)
    assert all(r["scale_factors"] == 0 or r["scale_measured_median"] is not None for r in hist)
    true = _true_m_per_vo0(hist, drive / "poses" / "00.txt")
    final = [r["scale_optimized"] for r in hist if r["scale_optimized"] is not None]
    assert len(final) == len(hist)
    # the system's own estimate (no ground truth in it) is metric to within 25 %
    assert abs(float(np.median(final)) / true - 1.0) < 0.25, (np.median(final), true)
    # the live warp made the VO metric: after the first corrections, live ≈ true
    assert abs(hist[-1]["scale_live"] / true - 1.0) < 0.25, (hist[-1]["scale_live"], true)


def test_no_scale_history_shows_the_vo_scale(drive):
    pipe, _ = run_inline(drive, use_scale=False)
    stats = {**pipe.stats(), **pipe.scale_history()}
    _check_consistent(stats)
    hist = stats["scale_history"]
    assert all(r["scale_factors"] is None for r in hist)  # nothing learned, nothing recorded
    assert hist[0]["scale_kf_optimized"] == pytest.approx(1.0, abs=1e-3)  # anchored gauge
    # the scale is the VO's own: it stays near 1 VO unit however far from metric that is
    final = np.array([r["scale_optimized"] for r in hist])
    assert np.all(np.isfinite(final)) and np.all(final > 0)
    assert float(np.median(final)) == pytest.approx(1.0, rel=0.25)


class _ConstantDepth:
    """A depth source answering a constant metric inverse depth (a real DepthSource)."""

    def __init__(self, inv_depth_per_m: float) -> None:
        self.inv_depth_per_m = inv_depth_per_m

    def inv_depth_map(self, image: np.ndarray, camera: PinholeCamera) -> np.ndarray:
        return np.full((8, 16), self.inv_depth_per_m, dtype=np.float32)


def _keyframe(frame_index: int, xi: np.ndarray) -> MarginalizedKeyframe:
    cam = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=32.0, cy_px=16.0, width_px=64, height_px=32)
    uv = np.column_stack([np.linspace(1, 60, xi.size), np.linspace(1, 30, xi.size)])
    return MarginalizedKeyframe(kf_id=frame_index, frame_index=frame_index, t_ns=frame_index,
                                segment_id=0, T_vo_kf=np.eye(4), T_prevkf_kf=None,
                                landmarks_uv_px=uv, landmarks_inv_depth=xi,
                                image=np.zeros((32, 64), np.uint8), camera=cam)


class _FailingDepth:
    def inv_depth_map(self, image: np.ndarray, camera: PinholeCamera) -> np.ndarray:
        raise DepthSourceError("depth service unreachable (test)")


def _inline_backend(source) -> GlobalBackend:
    return GlobalBackend(GraphConfig(inline=True, loop=LoopConfig(enabled=False)),
                         depth_source=source)


@pytest.mark.parametrize("ratio", [0.3, 1.0, 4.0])
def test_measured_median_is_xi_over_z(ratio):
    """The history records exactly what the back end measured, from its ScaleMeasured event."""
    z = 0.1  # 10 m
    backend = _inline_backend(_ConstantDepth(z))
    history = ScaleHistory()
    history.attach(backend.events)
    seen = []
    backend.events.subscribe(seen.append, ScaleMeasured)
    xi = ratio * z * np.exp(np.linspace(-0.2, 0.2, 31))  # median exactly ratio * z
    kf = _keyframe(5, xi)
    other = _keyframe(6, xi * 2.0)  # its depth request "dropped": never reaches the back end
    history.on_keyframe(kf)
    history.on_keyframe(other)
    backend.on_keyframe_marginalized(kf)
    recs = {r["frame_index"]: r for r in history.keyframes()}
    assert recs[5]["scale_factors"] == 31
    assert math.isclose(recs[5]["scale_measured_median"], ratio, rel_tol=1e-5)
    assert recs[6]["scale_factors"] == 0 and recs[6]["scale_measured_median"] is None
    assert recs[5]["scale_optimized"] is None  # no back end poses given
    (ev,) = seen
    assert ev.frame_index == 5 and ev.error == "" and ev.image_size == (64, 32)
    np.testing.assert_allclose(ev.net_inv_depth_per_m, z, rtol=1e-6)
    np.testing.assert_allclose(np.median(ev.scales), ratio, rtol=1e-5)


def test_failed_depth_request_is_an_event_and_a_broken_subscriber_changes_nothing():
    backend = _inline_backend(_FailingDepth())
    history = ScaleHistory()
    history.attach(backend.events)
    seen = []

    def broken(ev):
        raise RuntimeError("subscriber bug")

    backend.events.subscribe(broken)
    backend.events.subscribe(seen.append)
    kf = _keyframe(3, np.full(20, 0.1))
    history.on_keyframe(kf)
    backend.on_keyframe_marginalized(kf)
    measured = [ev for ev in seen if isinstance(ev, ScaleMeasured)]
    assert len(measured) == 1 and "unreachable" in measured[0].error
    assert measured[0].inv_depth_map_per_m is None and measured[0].scales.size == 0
    assert any(isinstance(ev, Solved) for ev in seen)  # the solve still ran and said so
    assert backend.stats()["depth_failures"] == 1
    assert history.keyframes()[0]["scale_factors"] == 0
