"""SLAM service over real zenoh sessions on loopback (router + service + clients in-process).

The sessions here are small real SlamSessions (identity / deliberately slow) so the tests pin the
transport contract: a pose for every frame, status, trajectory query, several cameras, bounded
drop-oldest queues, malformed frames counted and dropped without killing the service.
"""

from __future__ import annotations

import time
import zlib

import numpy as np
import pytest
import zenoh

from metricslam.camera import PinholeCamera
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.types import TrackingState
from metricslam.wire import keys
from metricslam.wire.codec import FrameMessage, encode
from metricslam_slam.service.sessions import IdentitySession
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService, congestion_for
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, query_health, query_trajectory
from metricslam_slam.zenoh_config import open_client

CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)


def _image(i: int) -> np.ndarray:
    return np.full((48, 64), i % 256, dtype=np.uint8)


class SlowSession(IdentitySession):
    """Identity poses, but each frame takes ``delay_s`` (to overflow the queue)."""

    def __init__(self, delay_s: float) -> None:
        super().__init__()
        self.delay_s = delay_s

    def process(self, frame):
        time.sleep(self.delay_s)
        return super().process(frame)


@pytest.fixture()
def stack(request):
    """(router endpoint, client session, start_service(factory, **settings))."""
    port = 17400 + zlib.crc32(request.node.name.encode()) % 40  # distinct per test, in our range
    endpoint = f"tcp/127.0.0.1:{port}"
    router = open_router(endpoint)
    client = open_client(endpoint)
    services = []

    def start_service(factory=None, queue_size=64, **overrides):
        # queue of 64 frames: bursts below are faster than any real camera
        settings = SlamServiceSettings(zenoh_endpoint=endpoint, depth_url=None,
                                       session_kind="identity", status_period_s=0.2, **overrides)
        config = SystemConfig(depth={"use_scale": False}, queues={"frames": queue_size})
        svc = SlamService(settings, session_factory=factory, config=config).start()
        services.append(svc)
        deadline = time.monotonic() + 5  # until every started service answers through the router
        while len(list(client.get(keys.HEALTH_KEY, timeout=0.5))) < len(services) \
                and time.monotonic() < deadline:
            time.sleep(0.05)
        return svc

    yield endpoint, client, start_service
    for svc in services:
        svc.stop()
    client.close()
    router.close()


def test_pose_for_every_frame_status_and_trajectory(stack) -> None:
    _, client, start_service = stack
    start_service()
    recorder = PoseRecorder(client, "cam0")
    pub = FramePublisher(client, "cam0")
    assert pub.wait_for_subscriber(10)
    n = 30
    for i in range(n):
        pub.publish(i, i * 100_000_000, _image(i), CAMERA)
    assert recorder.wait_frames(n, 10), f"got {len(recorder.poses)} of {n} poses"
    assert sorted(recorder.poses) == list(range(n))
    pose = recorder.poses[5]
    assert pose.t_ns == 500_000_000 and pose.state == TrackingState.TRACKING
    np.testing.assert_array_equal(pose.T_world_cam, np.eye(4))
    assert pose.t_sent_ns is not None and pose.processing_ms >= 0

    assert recorder.wait_for(lambda r: r.statuses and r.statuses[-1].frames_processed == n, 5)
    status = recorder.latest_status()
    assert status.frames_received == n and status.queue_drops == 0 and status.malformed == 0
    assert status.latency_ms_p50 is not None and status.depth_reachable is None

    traj = query_trajectory(client, "cam0")
    assert list(traj.frame_index) == list(range(n)) and traj.T_world_cam.shape == (n, 4, 4)
    with pytest.raises(Exception, match="no SLAM session"):
        query_trajectory(client, "unknown-cam", timeout_s=2)
    health = query_health(client)
    assert health["ready"] and health["cameras"] == ["cam0"]
    recorder.close()
    pub.close()


def test_two_cameras_get_separate_sessions(stack) -> None:
    _, client, start_service = stack
    made = []

    def factory(camera_id, camera):
        made.append(camera_id)
        return IdentitySession()

    start_service(factory)
    recs = {cid: PoseRecorder(client, cid) for cid in ("left", "right")}
    pubs = {cid: FramePublisher(client, cid) for cid in ("left", "right")}
    assert all(pub.wait_for_subscriber(10) for pub in pubs.values())
    for i in range(10):
        for cid in pubs:
            pubs[cid].publish(i, i, _image(i), CAMERA)
    for cid, rec in recs.items():
        assert rec.wait_frames(10, 10), cid
        assert sorted(rec.poses) == list(range(10))
    assert sorted(made) == ["left", "right"]


def test_malformed_frames_are_counted_and_dropped(stack) -> None:
    _, client, start_service = stack
    svc = start_service()
    recorder = PoseRecorder(client, "cam0")
    pub = FramePublisher(client, "cam0")
    assert pub.wait_for_subscriber(10)
    good = encode(FrameMessage(camera_id="cam0", frame_index=0, t_ns=0, camera=CAMERA, image=_image(0)))
    wrong_camera = encode(FrameMessage(camera_id="other", frame_index=0, t_ns=0, camera=CAMERA, image=_image(0)))
    bad = [b"", b"garbage" * 10, b"XXXX" + good[4:], good[:-10], good[:8] + b"[" + good[9:],
           wrong_camera]
    key = keys.key("cam0", "frame")
    pub.publish(0, 0, _image(0), CAMERA)
    for payload in bad:
        client.put(key, payload)
    client.put("metricslam/_bad/frame", good)  # not a camera id
    other = PinholeCamera(fx_px=90.0, fy_px=90.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)
    pub.publish(1, 1, _image(1), other)  # intrinsics changed mid-stream
    for i in range(2, 6):
        pub.publish(i, i, _image(i), CAMERA)
    assert recorder.wait_frames(5, 10)
    assert sorted(recorder.poses) == [0, 2, 3, 4, 5]
    assert recorder.wait_for(
        lambda r: r.statuses and r.statuses[-1].malformed == len(bad) + 1
        and r.statuses[-1].frames_processed == 5, 5), recorder.latest_status()
    assert svc.unrouted == 1
    assert query_health(client)["ready"]


def test_bounded_queue_drops_oldest_and_counts(stack) -> None:
    _, client, start_service = stack
    start_service(lambda cid, cam: SlowSession(0.05), queue_size=2)
    recorder = PoseRecorder(client, "cam0")
    pub = FramePublisher(client, "cam0")
    assert pub.wait_for_subscriber(10)
    n = 30
    for i in range(n):
        pub.publish(i, i, _image(i), CAMERA)
    assert recorder.wait_for(lambda r: r.statuses and r.statuses[-1].frames_received == n
                             and r.statuses[-1].queue_depth == 0
                             and r.statuses[-1].frames_processed + r.statuses[-1].queue_drops == n, 10)
    status = recorder.latest_status()
    assert status.queue_drops > 0
    assert n - 1 in recorder.poses  # the newest frame always survives drop-oldest
    assert len(recorder.poses) == status.frames_processed


def test_cameras_partitioned_across_workers(stack) -> None:
    _, client, start_service = stack
    svc_a = start_service(frame_key_expr="metricslam/fleet-a-$*/frame")
    svc_b = start_service(frame_key_expr="metricslam/fleet-b-$*/frame")
    recs = {cid: PoseRecorder(client, cid) for cid in ("fleet-a-1", "fleet-b-1")}
    for cid in recs:
        pub = FramePublisher(client, cid)
        assert pub.wait_for_subscriber(10)
        for i in range(5):
            pub.publish(i, i, _image(i), CAMERA)
        pub.close()
    for rec in recs.values():
        assert rec.wait_frames(5, 10)
        assert sorted(rec.poses) == list(range(5))
    assert svc_a.health()["cameras"] == ["fleet-a-1"] and svc_b.health()["cameras"] == ["fleet-b-1"]
    assert len(query_trajectory(client, "fleet-b-1").frame_index) == 5


def test_settled_trajectory_waits_until_the_answers_agree() -> None:
    """``poses --trajectory`` asks until three answers agree: the last keyframes' solve lands
    after the last pose. A service that keeps changing is given up on at the timeout."""
    from metricslam.wire.codec import TrajectoryMessage
    from metricslam_slam.tools.client import settled_trajectory

    def message(x: float) -> TrajectoryMessage:
        T = np.tile(np.eye(4), (2, 1, 1))
        T[1, 0, 3] = x
        return TrajectoryMessage(camera_id="cam0", scale_established=True, frame_index=np.arange(2),
                                 t_ns=np.arange(2) * 100_000_000, T_world_cam=T,
                                 state_code=np.zeros(2, dtype=np.uint8))

    answers = iter([1.0, 1.5, 2.0, 2.0, 2.0, 9.0])
    got = settled_trajectory(lambda: message(next(answers)), period_s=0.01)
    assert got.T_world_cam[1, 0, 3] == 2.0
    changing = iter(range(10_000))
    t0 = time.monotonic()
    got = settled_trajectory(lambda: message(float(next(changing))), timeout_s=0.2, period_s=0.01)
    assert time.monotonic() - t0 < 1.0 and got.T_world_cam[1, 0, 3] > 5


def test_poses_keyframes_and_status_are_published_with_block_congestion_control() -> None:
    """Zenoh's default congestion control drops a sample when the TX queue is full; a pose for
    every processed frame needs ``BLOCK`` (a starved TX thread once lost frame 9's pose)."""
    for topic in ("pose", "keyframe", "status"):
        assert congestion_for(topic) == zenoh.CongestionControl.BLOCK, topic
    for topic in ("path", "landmarks", "keyframe_depth"):
        assert congestion_for(topic) == zenoh.CongestionControl.DROP, topic
