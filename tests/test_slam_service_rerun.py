"""``--rerun``: a recording made by the SLAM service holds image, camera, trajectory, keyframes,
landmarks and keyframe depth (real pipeline, real KITTI frames, real zenoh, in-process model)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

rr = pytest.importorskip("rerun", reason="rerun-sdk is the optional viz extra")

from metricslam.datasets import open_sequence  # noqa: E402
from metricslam.slam.system_config import SystemConfig  # noqa: E402
from metricslam_slam.service.settings import SlamServiceSettings  # noqa: E402
from metricslam_slam.service.slam_service import SlamService  # noqa: E402
from metricslam_slam.supervisor.router import open_router  # noqa: E402
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, query_health  # noqa: E402
from metricslam_slam.zenoh_config import open_client  # noqa: E402

ENDPOINT = "tcp/127.0.0.1:17470"


@pytest.mark.slow
def test_rerun_recording_has_the_entities(shared_data: Path, tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    seq = open_sequence(shared_data / "kitti_odometry" / "sequences" / "06")
    n = 30
    rrd = tmp_path / "live.rrd"
    router = open_router(ENDPOINT)
    svc = SlamService(SlamServiceSettings(zenoh_endpoint=ENDPOINT, depth_url=None, rerun=str(rrd)),
                      config=SystemConfig(queues={"frames": 64})).start()
    client = open_client(ENDPOINT)
    try:
        deadline = time.monotonic() + 10
        while query_health(client, 0.5) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        recorder = PoseRecorder(client, "kitti06")
        publisher = FramePublisher(client, "kitti06")
        assert publisher.wait_for_subscriber(10)
        for i in range(n):
            frame = seq[i]
            publisher.publish(frame.index, frame.t_ns, frame.image, frame.camera)
            recorder.wait_for(lambda r, i=i: len(r.poses) >= i - 2, 30)
        assert recorder.wait_frames(n, 60)
        recorder.close()
        publisher.close()
    finally:
        client.close()
        svc.stop()
        router.close()
    paths = {chunk.entity_path for chunk in RrdReader(rrd).stream()}
    for entity in ("camera", "camera/image", "trajectory", "keyframes", "landmarks"):
        assert f"/world/kitti06/{entity}" in paths, (entity, sorted(paths))
    assert "/world/keyframe_depth" in paths, sorted(paths)  # logged as depth answers arrive
