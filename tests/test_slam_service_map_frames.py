"""How the SLAM service carries the map frame id (docs/maps.md "Live"), over real zenoh sessions.

Sessions here are stand-ins with the one attribute the service reads from a
:class:`~metricslam.slam.map.localization.MapFrameSession` — ``frame_id``, ``"world"`` for the
first frames and ``"map"`` from :data:`SWITCH` on — so what is checked is the transport: the
native pose, keyframe, odometry and trajectory messages carry the frame id; the continuous
odometry starts over at the switch instead of blending the jump into the map frame; the ROS 2
bridge publishes ``map`` as the parent frame (pose, odometry, ``/tf``) from then on. The real
relocalization is ``tests/test_slam_service_map.py``. The same transport recorded by
``poses --mcap`` keeps the frame ids (parent frame ``map``), and a trajectory stored in
``state_dir`` keeps its ``"map"`` label across a restart of the service.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.errors import ServiceError
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.types import PoseEstimate, TrackingState
from metricslam.wire import keys
from metricslam.wire.codec import decode_as
from metricslam.wire.odometry_message import OdometryMessage
from metricslam_slam.service.sessions import IdentitySession
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.launcher import free_port
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, query_trajectory
from metricslam_slam.zenoh_config import open_client

CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)
SWITCH = 3  # the first frame in the map frame
SHIFT_M = 100.0  # the map frame is the world moved 100 m along x


class RelocalizingSession(IdentitySession):
    """1 m along z per frame; in the "map" frame (x + 100 m) from frame SWITCH on."""

    frame_id = "world"

    def process(self, frame):
        self.frame_id = "map" if len(self._poses) >= SWITCH else "world"
        T = np.eye(4)
        T[2, 3] = float(len(self._poses))
        T[0, 3] = SHIFT_M if self.frame_id == "map" else 0.0
        pose = PoseEstimate(frame.index, frame.t_ns, T, TrackingState.TRACKING, is_keyframe=True)
        self._poses.append(pose)
        return pose

    def trajectory(self):
        return [p for p in self._poses if p.frame_index >= SWITCH] if self.frame_id == "map" else list(self._poses)


def _start(settings: SlamServiceSettings) -> SlamService:
    return SlamService(settings, session_factory=lambda cid, cam: RelocalizingSession(),
                       config=SystemConfig(depth={"use_scale": False}, queues={"frames": 64})).start()


@pytest.fixture()
def stack(request, tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    client = open_client(endpoint)
    extra = dict(request.param) if hasattr(request, "param") else {}
    if extra.get("state_dir") is True:
        extra["state_dir"] = tmp_path / "state"
    settings = SlamServiceSettings(zenoh_endpoint=endpoint, depth_url=None, session_kind="identity",
                                   status_period_s=0.2, ros2_domain_id=7, **extra)
    svc = _start(settings)
    yield client, svc
    svc.stop()
    client.close()
    router.close()


def _wait(predicate, timeout_s: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.02)
    return predicate()


def _publish(client, n: int) -> None:
    pub = FramePublisher(client, "cam0")
    assert pub.wait_for_subscriber(10)
    for i in range(n):
        pub.publish(i, 1_000_000_000 + i * 100_000_000, np.zeros((48, 64), np.uint8), CAMERA)
    pub.close()


def test_native_messages_carry_the_frame_id_and_the_odometry_starts_over(stack) -> None:
    client, _ = stack
    recorder = PoseRecorder(client, "cam0")
    odom: list[OdometryMessage] = []
    sub = client.declare_subscriber(keys.key("cam0", "odom"),
                                    lambda s: odom.append(decode_as(s.payload.to_bytes(), OdometryMessage)))
    time.sleep(0.3)
    _publish(client, 6)
    assert recorder.wait_frames(6, 20) and _wait(lambda: len(odom) >= 6 and len(recorder.keyframes) >= 6)
    sub.undeclare()
    assert [recorder.poses[i].frame_id for i in range(6)] == ["world"] * SWITCH + ["map"] * (6 - SWITCH)
    assert [k.frame_id for k in sorted(recorder.keyframes, key=lambda k: k.frame_index)] == \
        ["world"] * SWITCH + ["map"] * (6 - SWITCH)
    odom.sort(key=lambda m: m.frame_index)
    assert [m.frame_id for m in odom] == ["world"] * SWITCH + ["map"] * (6 - SWITCH)
    # the continuous stream is not blended from the world frame into the map frame: it starts over
    assert [m.T_world_cam[0, 3] for m in odom] == [0.0] * SWITCH + [SHIFT_M] * (6 - SWITCH)
    assert all(m.correction_m == 0.0 for m in odom)
    traj = query_trajectory(client, "cam0")
    assert traj.frame_id == "map" and list(traj.frame_index) == list(range(SWITCH, 6))
    recorder.close()


def _drive_until_closed(client, n_frames: int) -> PoseRecorder:
    """Publish ``n_frames`` on cam0 and wait until the idle camera session closed."""
    recorder = PoseRecorder(client, "cam0")
    time.sleep(0.3)
    _publish(client, n_frames)
    assert recorder.wait_for(lambda r: any(s.event == "camera_closed" for s in r.statuses), 20)
    return recorder


@pytest.mark.parametrize("stack", [{"camera_idle_timeout_s": 0.5}], indirect=True)
def test_a_closed_cameras_trajectory_keeps_its_map_frame_id(stack) -> None:
    client, _ = stack
    recorder = _drive_until_closed(client, 5)
    traj = query_trajectory(client, "cam0")
    assert traj.frame_id == "map" and list(traj.frame_index) == list(range(SWITCH, 5))
    recorder.close()


@pytest.mark.parametrize("stack", [{"ros2": True}], indirect=True)
def test_ros2_parent_frame_is_map_once_relocalized(stack) -> None:
    pytest.importorskip("rosbags")
    from metricslam.ros2.typestore import ODOMETRY, dds_type_name
    from tests.ros2_cdr import CdrReader

    client, _ = stack
    got: list[bytes] = []
    tf: list[bytes] = []
    subs = [client.declare_subscriber(f"7/metricslam/cam0/odom/{dds_type_name(ODOMETRY)}/*",
                                      lambda s: got.append(s.payload.to_bytes())),
            client.declare_subscriber(f"7/tf/{dds_type_name('tf2_msgs/msg/TFMessage')}/*",
                                      lambda s: tf.append(s.payload.to_bytes()))]
    time.sleep(0.3)
    _publish(client, 5)
    assert _wait(lambda: len(got) >= 5 and len(tf) >= 5), (len(got), len(tf))
    for s in subs:
        s.undeclare()
    parents = [CdrReader(p).header()[2] for p in got]
    assert parents == ["cam0/world"] * SWITCH + ["map"] * (5 - SWITCH)
    tf_parents = []
    for payload in tf:
        r = CdrReader(payload)
        assert r.u32() == 1
        tf_parents.append(r.header()[2])
    assert tf_parents == ["cam0/world"] * SWITCH + ["map"] * (5 - SWITCH)


def test_poses_mcap_keeps_each_messages_frame(stack, tmp_path) -> None:
    """What ``poses --mcap`` writes (:func:`write_mcap` of a real :class:`PoseRecorder`): the
    bridge's parent frames, ``map`` for the map-frame poses, ``/tf`` and final trajectory."""
    pytest.importorskip("mcap")
    from metricslam_slam.tools.recording import write_mcap
    from tests.ros2_cdr import CdrReader
    from tests.test_mcap_recording import read_mcap

    client, _ = stack
    recorder = PoseRecorder(client, "cam0", map_topics=True)
    time.sleep(0.3)
    _publish(client, 6)
    assert recorder.wait_frames(6, 20)
    trajectory = query_trajectory(client, "cam0")
    write_mcap(tmp_path / "live.mcap", "cam0", recorder, trajectory)
    recorder.close()
    topics = read_mcap(tmp_path / "live.mcap")
    expected = ["cam0/world"] * SWITCH + ["map"] * (6 - SWITCH)
    assert [CdrReader(m[2]).header()[2] for m in topics["/metricslam/cam0/pose"]] == expected
    tf = [CdrReader(m[2]) for m in topics["/tf"]]
    assert all(r.u32() == 1 for r in tf) and [r.header()[2] for r in tf] == expected
    assert CdrReader(topics["/metricslam/cam0/path"][-1][2]).header()[2] == "map"


@pytest.mark.parametrize("stack", [{"camera_idle_timeout_s": 0.5, "state_dir": True}], indirect=True)
def test_a_restarted_service_answers_the_stored_trajectory_in_the_map_frame(stack) -> None:
    client, svc = stack
    recorder = _drive_until_closed(client, 5)
    recorder.close()
    svc.stop()  # the final trajectory is in state_dir; the next service has nothing in memory
    restarted = _start(svc.settings)
    answers = []
    try:  # its queryable reaches the router shortly after the start
        assert _wait(lambda: answers.append(_try_query(client)) or answers[-1] is not None, 10.0)
    finally:
        restarted.stop()
    traj = answers[-1]
    assert traj.frame_id == "map" and list(traj.frame_index) == list(range(SWITCH, 5))
    np.testing.assert_allclose(traj.T_world_cam[:, 0, 3], SHIFT_M)


def _try_query(client):
    try:
        return query_trajectory(client, "cam0", timeout_s=1.0)
    except ServiceError:
        return None
