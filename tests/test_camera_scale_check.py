"""``metricslam camera --scale-sources/--mount-height`` (issue #33): the SLAM service owns the
scale settings, so the camera compares its flags with the scale block of the service's status and
stops with one clear error when they differ (a real service and real zenoh on loopback, frames
from a video file); the comparison itself as a pure function."""

from __future__ import annotations

import argparse
import logging

import cv2
import numpy as np
import pytest

from metricslam.errors import ConfigError
from metricslam_cli import camera_cmd
from metricslam_cli.scale_check import RequestedScale, scale_mismatch


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    camera_cmd.add_parser(parser.add_subparsers())
    return parser.parse_args(argv)


def test_flags_the_service_does_not_run_are_an_error_that_says_how_to_restart_it():
    error, warning = scale_mismatch(RequestedScale(("learned", "ground"), 1.65), ("learned",), None, "cam0")
    assert "--scale-sources learned,ground and --mount-height 1.65" in error and not warning
    assert "metricslam up --scale-sources learned,ground --mount-height 1.65" in error
    error, _ = scale_mismatch(RequestedScale(None, 1.2), ("learned", "ground"), 1.65)
    assert "--mount-height 1.2" in error and "--scale-sources" not in error.split("not the")[1].split(";")[0]
    assert "restart it with them (`metricslam up --scale-sources learned,ground --mount-height 1.2`" in error


def test_matching_flags_pass_and_a_calibration_height_only_warns():
    assert scale_mismatch(RequestedScale(("learned", "ground"), 1.65), ("learned", "ground"), 1.65) == ("", "")
    assert scale_mismatch(RequestedScale(("learned",)), ("learned",), None) == ("", "")
    error, warning = scale_mismatch(RequestedScale(calibration_mount_height_m=1.4), ("learned",), None)
    assert not error and "1.4 m above the road" in warning and "--mount-height 1.4" in warning
    assert scale_mismatch(RequestedScale(calibration_mount_height_m=1.4), ("ground",), 1.4) == ("", "")


def test_camera_turns_its_flags_into_a_request():
    args = _parse(["camera", "--fx", "600", "--scale-sources", "ground,learned", "--mount-height", "1.5"])
    req = camera_cmd.requested_scale(args, 1.2)
    assert req == RequestedScale(("ground", "learned"), 1.5, 1.2) and req.anything
    assert not camera_cmd.requested_scale(_parse(["camera", "--fx", "600"])).anything


def _video(seq_dir, path, n: int) -> None:
    from metricslam.datasets import open_sequence

    seq = open_sequence(seq_dir)
    h, w = seq[0].image.shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    assert writer.isOpened()
    for i in range(n):
        writer.write(cv2.cvtColor(np.ascontiguousarray(seq[i % len(seq)].image), cv2.COLOR_GRAY2BGR))
    writer.release()


@pytest.mark.slow
def test_camera_stops_when_the_service_runs_other_scale_settings(synth_sequence, tmp_path, caplog):
    from metricslam.slam.config_file import load_system_config
    from metricslam.slam.system_config import LIVE_PROFILE
    from metricslam_slam.service.settings import SlamServiceSettings
    from metricslam_slam.service.slam_service import SlamService
    from metricslam_slam.supervisor.launcher import free_port
    from metricslam_slam.supervisor.router import open_router

    video = tmp_path / "street.avi"
    _video(synth_sequence(40, seed=3, path="loop"), video, 100)  # 5 s at 20 Hz: statuses every 0.2 s
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = load_system_config(None, env={}, profile=LIVE_PROFILE,
                                overrides={"scale": {"sources": ["learned", "ground"], "mount_height_m": 1.65}})
    router = open_router(endpoint)
    service = SlamService(SlamServiceSettings(zenoh_endpoint=endpoint, depth_url=None, status_period_s=0.2),
                          config=config).start()
    camera = ["camera", "--device", str(video), "--zenoh-endpoint", endpoint, "--fx", "300",
              "--max-rate", "20", "--camera-id"]
    try:
        # the service runs learned,ground at 1.65 m: a camera asking for 1.2 m is refused ...
        args = _parse([*camera, "cam_a", "--scale-sources", "learned,ground", "--mount-height", "1.2"])
        with pytest.raises(ConfigError, match=r"runs camera cam_a with scale sources learned,ground with the "
                                              r"camera 1\.65 m above the road, not the --mount-height 1\.2"):
            args.func(args)
        # ... and one asking for what it runs publishes all its frames and says so
        args = _parse([*camera, "cam_b", "--scale-sources", "learned,ground", "--mount-height", "1.65"])
        with caplog.at_level(logging.INFO, logger="metricslam.camera"):
            assert args.func(args) == 0
        assert "runs camera cam_b with scale sources learned,ground with the camera 1.65 m above the road, " \
               "as asked" in caplog.text
    finally:
        service.stop()
        router.close()
