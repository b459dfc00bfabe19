"""Issue #19 item 1 through the real SLAM service (in-process, real zenoh on loopback): with the
live profile the first tracked pose is already ``provisional``ly metric; with no reachable depth
service the status says so and every pose says ``unscaled``. Frames are a rendered drive; the
"depth service" of the first test is the rendered depth handed to the service in-process."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from metricslam.datasets import open_sequence
from metricslam.slam.config_file import load_system_config
from metricslam.slam.system_config import LIVE_PROFILE
from metricslam.slam.types import ScaleState, TrackingState
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.launcher import free_port
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import PoseRecorder
from metricslam_slam.tools.replay import replay_sequence, wait_for_service
from metricslam_slam.zenoh_config import open_client


class RenderedDepth:
    """The rendered (true) inverse depth of each known image (1/m)."""

    def __init__(self, seq) -> None:
        self._inv = {}
        for i in range(len(seq)):
            frame = seq[i]
            inv = np.where(frame.depth_m > 0, 1.0 / np.maximum(frame.depth_m, 1e-6), 0.0)
            self._inv[self._key(frame.image)] = inv.astype(np.float32)

    @staticmethod
    def _key(image) -> str:
        return hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=16).hexdigest()

    def inv_depth_map(self, image, camera) -> np.ndarray:
        return self._inv[self._key(image)]


def _serve_and_replay(seq_dir, depth_url: str | None, depth_source=None):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    settings = SlamServiceSettings(zenoh_endpoint=endpoint, depth_url=depth_url, status_period_s=0.2,
                                   depth_retries=0, depth_connect_timeout_s=0.2)
    service = SlamService(settings, depth_source=depth_source,
                          config=load_system_config(None, env={}, profile=LIVE_PROFILE)).start()
    client = open_client(endpoint)
    try:
        wait_for_service(client, 10)
        recorder = PoseRecorder(client, "cam0")
        seq = open_sequence(seq_dir)
        report = replay_sequence(client, seq, "cam0", rate_hz=0, max_in_flight=2, progress=False)
        n_status = len(recorder.statuses)
        recorder.wait_for(lambda r: len(r.statuses) > n_status + 1, 5)
        recorder.close()
    finally:
        client.close()
        service.stop()
        router.close()
    assert report.complete, report.describe()
    return [recorder.poses[i] for i in range(len(seq))], recorder.latest_status()


@pytest.mark.slow
def test_live_poses_are_metric_from_the_first_tracked_one(synth_sequence) -> None:
    seq_dir = synth_sequence(60, seed=3, path="loop")
    poses, status = _serve_and_replay(seq_dir, None, RenderedDepth(open_sequence(seq_dir)))
    first = next(k for k, p in enumerate(poses) if p.state is TrackingState.TRACKING)
    assert all(p.scale_state is ScaleState.UNSCALED for p in poses[:first])
    assert all(p.scale_state is not ScaleState.UNSCALED for p in poses[first:])
    assert poses[first].scale_state is ScaleState.PROVISIONAL
    assert poses[-1].scale_state is ScaleState.METRIC and poses[-1].scale_factors > 0
    assert status.scale_state is ScaleState.METRIC
    assert status.session_stats["initial_scale.error"] == ""


@pytest.mark.slow
def test_without_a_reachable_depth_service_the_status_says_so_and_poses_are_unscaled(synth_sequence) -> None:
    seq_dir = synth_sequence(60, seed=3, path="loop")
    poses, status = _serve_and_replay(seq_dir, f"http://127.0.0.1:{free_port()}")
    assert all(p.scale_state is ScaleState.UNSCALED and not p.scale_established for p in poses)
    assert status.depth_reachable is False and status.depth_error
    assert status.scale_state is ScaleState.UNSCALED
    assert "unreachable" in status.session_stats["initial_scale.error"]
    assert status.session_stats["scale_states.unscaled"] == len(poses)
