"""Issue #33 remainder: ``--scale-sources`` / ``--mount-height`` on ``up`` and ``camera`` (checked
like ``run``, passed to the SLAM child), the scale block of the status topic (real service, real
zenoh on loopback; older status messages still decode), and the road-height consistency gate."""

from __future__ import annotations

import argparse
import json
import struct

import numpy as np
import pytest

from metricslam.errors import ConfigError
from metricslam.slam.config_file import load_system_config
from metricslam.slam.ground.consistency import HeightConsistency, HeightConsistencyConfig
from metricslam.slam.system_config import LIVE_PROFILE
from metricslam.wire.codec import MAGIC, StatusMessage, decode_as, encode
from metricslam.wire.scale_status import ScaleHealthStatus
from metricslam_cli import camera_cmd, up_cmd
from metricslam_slam.supervisor.launcher import Stack, free_port


def _parse(module, argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    module.add_parser(parser.add_subparsers())
    return parser.parse_args(argv)


# -- consistency gate --------------------------------------------------------------------------
def test_gate_refuses_a_height_far_from_the_recent_median_and_counts_nothing_else():
    gate = HeightConsistency(HeightConsistencyConfig(max_deviation=0.25, window=10, min_history=3))
    rng = np.random.default_rng(0)
    for k in range(8):
        assert gate.check(k, 1.65 * (1 + 0.03 * rng.standard_normal()), None) == ""
    why = gate.check(8, 0.8, None)  # a car close ahead
    assert "% from the median" in why
    assert gate.check(9, 1.70, None) == ""  # the road again


def test_gate_compares_heights_in_graph_metres_so_a_vo_rescale_is_no_outlier():
    gate = HeightConsistency()
    scales = {k: 1.0 for k in range(5)} | {k: 0.01 for k in range(5, 10)}  # VO units ×100 from kf 5
    for k in range(5):
        assert gate.check(k, 1.65, scales.get) == ""
    for k in range(5, 10):
        assert gate.check(k, 165.0, scales.get) == ""
    assert gate.check(10, 1.65, lambda _k: 1.0) != ""  # same number, wrong units: refused


def test_gate_adopts_a_new_level_after_enough_agreeing_refusals():
    gate = HeightConsistency(HeightConsistencyConfig(reset_after=4))
    for k in range(5):
        gate.check(k, 1.65, None)
    answers = [gate.check(5 + i, 1.2, None) for i in range(4)]
    assert all(answers[:3]) and answers[3] == ""
    assert gate.check(9, 1.21, None) == ""


# -- up / camera / launcher -----------------------------------------------------------------------
def test_launcher_passes_the_scale_flags_to_the_slam_child_only_when_given():
    ep = f"tcp/127.0.0.1:{free_port()}"
    plain = next(c for c in Stack(ep, depth_port=None).children if c.name == "slam-service")
    assert "--scale-sources" not in plain.argv and "--mount-height" not in plain.argv
    stack = Stack(ep, depth_port=None, scale_sources="learned,ground", mount_height_m=1.65)
    argv = next(c for c in stack.children if c.name == "slam-service").argv
    assert argv[argv.index("--scale-sources") + 1] == "learned,ground"
    assert float(argv[argv.index("--mount-height") + 1]) == 1.65


@pytest.mark.parametrize("flags", [["--mount-height", "-1"], ["--mount-height", "nan"], ["--mount-height", "11"],
                                   ["--scale-sources", "ground"], ["--scale-sources", "learned,lidar"]])
def test_up_refuses_bad_scale_flags_before_starting_anything(flags, monkeypatch):
    monkeypatch.delenv("METRICSLAM_CONFIG", raising=False)
    monkeypatch.setattr("metricslam_slam.supervisor.launcher.Stack.start",
                        lambda *a, **k: pytest.fail("the stack started"))
    args = _parse(up_cmd, ["up", "--no-scale", *flags])
    with pytest.raises(ConfigError):
        args.func(args)


@pytest.mark.parametrize("flags", [["--mount-height", "0"], ["--scale-sources", "ground"],
                                   ["--scale-sources", "ground,ground"]])
def test_camera_checks_scale_flags_like_run(flags, monkeypatch):
    monkeypatch.delenv("METRICSLAM_CONFIG", raising=False)
    args = _parse(camera_cmd, ["camera", "--fx", "600", *flags])
    with pytest.raises(ConfigError):
        camera_cmd.check_scale_flags(args)


def test_camera_takes_the_calibration_height_and_says_learned_only_without_one(monkeypatch, caplog):
    monkeypatch.delenv("METRICSLAM_CONFIG", raising=False)
    args = _parse(camera_cmd, ["camera", "--fx", "600", "--scale-sources", "learned,ground"])
    config = camera_cmd.check_scale_flags(args, calibration_mount_height_m=1.2)
    assert config.scale.sources == ("learned", "ground") and config.scale.mount_height_m == 1.2
    from metricslam_cli.scale_options import log_scale_sources

    with caplog.at_level("INFO"):
        log_scale_sources(camera_cmd.check_scale_flags(_parse(camera_cmd, ["camera", "--fx", "600"])),
                          __import__("logging").getLogger("t"))
    assert "learned scale only" in caplog.text


# -- status message ------------------------------------------------------------------------------
def test_status_scale_block_round_trips_and_older_statuses_still_decode():
    block = ScaleHealthStatus(sources=("learned", "ground"), mount_height_m=1.65, scale_sigma_log=0.02,
                              learned_scale=0.8, ground_scale=1.0, disagreement_log=-0.22, warning=True,
                              warnings_issued=1, ground_factors=30, ground_rejected=4)
    msg = StatusMessage(camera_id="cam0", t_ns=1, frames_received=1, frames_processed=1, queue_drops=0,
                        malformed=0, queue_depth=0, fps=0.0, scale_health=block)
    assert decode_as(encode(msg), StatusMessage).scale_health == block
    # an older sender's status: no scale_health key at all
    header = {"schema_version": 1, "kind": "status", "arrays": [],
              "body": {"camera_id": "cam0", "t_ns": 1, "frames_received": 1, "frames_processed": 1,
                       "queue_drops": 0, "malformed": 0, "queue_depth": 0, "fps": 0.0}}
    raw = json.dumps(header).encode()
    old = decode_as(MAGIC + struct.pack("<I", len(raw)) + raw, StatusMessage)
    assert old.scale_health is None


@pytest.mark.slow
@pytest.mark.parametrize("sources", ["learned", "learned,ground"])
def test_service_status_carries_sources_height_and_scale_uncertainty(synth_sequence, sources):
    pytest.importorskip("numba")
    from test_slam_service_scale import RenderedDepth

    from metricslam.datasets import open_sequence
    from metricslam_slam.service.settings import SlamServiceSettings
    from metricslam_slam.service.slam_service import SlamService
    from metricslam_slam.supervisor.router import open_router
    from metricslam_slam.tools.client import PoseRecorder
    from metricslam_slam.tools.replay import replay_sequence, wait_for_service
    from metricslam_slam.zenoh_config import open_client

    seq_dir = synth_sequence(60, seed=3, path="loop")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = load_system_config(None, env={}, profile=LIVE_PROFILE,
                                overrides={"scale": {"sources": sources.split(","), "mount_height_m": 1.65}})
    router = open_router(endpoint)
    service = SlamService(SlamServiceSettings(zenoh_endpoint=endpoint, depth_url=None, status_period_s=0.2),
                          depth_source=RenderedDepth(open_sequence(seq_dir)), config=config).start()
    client = open_client(endpoint)
    try:
        wait_for_service(client, 10)
        recorder = PoseRecorder(client, "cam0")
        report = replay_sequence(client, open_sequence(seq_dir), "cam0", rate_hz=0, max_in_flight=2,
                                 progress=False)
        n = len(recorder.statuses)
        recorder.wait_for(lambda r: len(r.statuses) > n + 1, 5)
        recorder.close()
    finally:
        client.close()
        service.stop()
        router.close()
    assert report.complete, report.describe()
    health = recorder.latest_status().scale_health
    assert health is not None and health.sources == tuple(sources.split(","))
    assert health.mount_height_m == 1.65
    assert health.scale_sigma_log is not None and 0 < health.scale_sigma_log < 1
    assert health.learned_scale is not None and health.learned_spread_log is not None
    if "ground" in sources:
        assert health.ground_factors is not None and health.ground_rejected is not None
    else:
        assert health.ground_factors is None and health.ground_scale is None and not health.warning
