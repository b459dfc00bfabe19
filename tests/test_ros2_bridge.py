"""ROS 2 over Zenoh: rmw_zenoh names and attachments from its design document, REP-2016 type
hashes against published values, CDR bytes checked by an independent decoder (tests/ros2_cdr.py),
and the SLAM service's bridge over a real Zenoh session on loopback (explicit endpoint)."""

from __future__ import annotations

import struct
import time
import zlib

import numpy as np
import pytest
import zenoh
from scipy.spatial.transform import Rotation

from metricslam.camera import PinholeCamera
from metricslam.errors import CodecError
from metricslam.ros2 import messages
from metricslam.ros2.rmw_zenoh import Node, Qos, attachment, gid, parse_attachment, ros_token, topic_key
from metricslam.ros2.typestore import (
    CAMERA_INFO, IMAGE, ODOMETRY, PATH, POINT_CLOUD2, POSE_STAMPED, dds_type_name, deserialize, serialize, type_hash,
)
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.types import ScaleState
from metricslam_slam.service.ros2_bridge import (
    PROVISIONAL_VARIANCE, UNKNOWN_VARIANCE, odometry_covariances, scale_state_from_covariance,
)
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher, PoseRecorder
from metricslam_slam.zenoh_config import open_client
from tests.ros2_cdr import CdrReader, camera_info_cdr, image_cdr

STRING = "std_msgs/msg/String"
# REP-2016 hashes (ROS 2 Jazzy/Rolling). Sources: String — the example in rmw_zenoh's
# docs/design.md; Image, PointCloud2 — `ros2 topic info -v` transcripts in public repositories;
# the rest — hash tables of independent ROS 2 client libraries (Rust, Swift, C++) in public code.
PUBLISHED_HASHES = {
    STRING: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    ODOMETRY: "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    POSE_STAMPED: "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    PATH: "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
    POINT_CLOUD2: "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
    IMAGE: "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    CAMERA_INFO: "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
}
CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)


def _T(rotvec=(0.1, -0.2, 0.3), t=(1.0, -2.0, 3.5)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _check_pose(pose7: np.ndarray, T: np.ndarray) -> None:
    np.testing.assert_allclose(pose7[:3], T[:3, 3], atol=1e-12)
    np.testing.assert_allclose(Rotation.from_quat(pose7[3:]).as_matrix(), T[:3, :3], atol=1e-9)


# -- names, hashes, attachments (rmw_zenoh docs/design.md) -------------------------------------
@pytest.mark.parametrize("msgtype", sorted(PUBLISHED_HASHES))
def test_type_hashes_are_rep2016_values_published_elsewhere(msgtype: str) -> None:
    assert type_hash(msgtype) == PUBLISHED_HASHES[msgtype]


def test_dds_type_names() -> None:
    assert dds_type_name(ODOMETRY) == "nav_msgs::msg::dds_::Odometry_"
    assert dds_type_name(POINT_CLOUD2) == "sensor_msgs::msg::dds_::PointCloud2_"
    with pytest.raises(CodecError):
        dds_type_name("Odometry")


def test_key_expressions_are_the_design_documents_examples() -> None:
    h = PUBLISHED_HASHES[STRING]
    assert topic_key(0, "/chatter", STRING) == f"0/chatter/std_msgs::msg::dds_::String_/{h}"
    assert topic_key(0, "/robot1/chatter", STRING) == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{h}"
    assert topic_key(7, "/metricslam/cam0/odom", ODOMETRY) == \
        f"7/metricslam/cam0/odom/nav_msgs::msg::dds_::Odometry_/{PUBLISHED_HASHES[ODOMETRY]}"
    for bad in ("chatter", "/a//b", "/1abc", "/a-b"):
        with pytest.raises(CodecError):
            topic_key(0, bad, STRING)
    assert ros_token("fleet-a.1") == "fleet_a_1" and ros_token("0cam") == "cam_0cam"


def test_liveliness_tokens_are_the_design_documents_examples() -> None:
    h = PUBLISHED_HASHES[STRING]
    listener = Node(domain_id=2, zid="aac3178e146ba6f1fc6e6a4085e77f21", node_id=0, name="listener")
    assert listener.token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert listener.endpoint_token(10, "MS", "/chatter", STRING, Qos(depth=10)) == (
        f"@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
        f"std_msgs::msg::dds_::String_/{h}/::,10:,:,:,,")
    talker = Node(domain_id=2, zid="8b20917502ee955ac4476e0266340d5c", node_id=0, name="talker")
    token = talker.endpoint_token(10, "MP", "/chatter", STRING, Qos(depth=7))
    assert token == (f"@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
                     f"std_msgs::msg::dds_::String_/{h}/::,7:,:,:,,")
    assert Qos(depth=1, durability=1).key() == ":1:,1:,:,:,,"
    ours = Node(0, "ab12", 0, "metricslam_slam").endpoint_token(3, "MP", "/metricslam/cam0/path", PATH, Qos())
    for key in (token, ours, listener.token()):
        zenoh.KeyExpr(key)  # valid key expressions (raises otherwise)
    assert len(gid(token)) == 16 and gid(token) != gid(ours)


def test_attachment_bytes_follow_the_design_document() -> None:
    source_gid = bytes(range(16))
    att = attachment(42, 1_700_000_000_123_456_789, source_gid)
    expected = (struct.pack("<q", 42) + struct.pack("<q", 1_700_000_000_123_456_789) + bytes([16]) + source_gid)
    assert att == expected and len(att) == 33
    assert parse_attachment(att) == (42, 1_700_000_000_123_456_789, source_gid)
    # what rmw_zenoh deserializes it with: zenoh-ext's (int64, int64, byte array)
    from zenoh.ext import Int64, z_deserialize
    seq, t_ns, raw = z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(att))
    assert (int(seq), int(t_ns), bytes(raw)) == (42, 1_700_000_000_123_456_789, source_gid)
    with pytest.raises(CodecError):
        parse_attachment(att[:-1])


# -- CDR: bytes built from the spec, and decoded independently ---------------------------------
def test_pose_stamped_cdr_is_byte_exact() -> None:
    T = np.eye(4)  # identity rotation: the quaternion (0, 0, 0, 1) is exact in binary
    T[:3, 3] = [1.25, -2.5, 1e3]
    frame = b"cam0/world\x00"  # 11 bytes with the NUL
    body = struct.pack("<iI", 1, 500_000_000) + struct.pack("<I", len(frame)) + frame
    body += b"\x00" * ((-len(body)) % 8)  # doubles are 8-aligned (offset 23 -> 24)
    body += struct.pack("<7d", 1.25, -2.5, 1e3, 0.0, 0.0, 0.0, 1.0)
    assert serialize(messages.pose_stamped(T, 1_500_000_000, "cam0/world")) == b"\x00\x01\x00\x00" + body


def test_odometry_decodes_with_an_independent_reader() -> None:
    T = _T()
    pose_cov, twist_cov = odometry_covariances(True, 0.5, 0.02)
    r = CdrReader(serialize(messages.odometry(T, 12_000_000_007, "cam0/world", "cam0/camera_optical",
                                              pose_cov, twist_cov)))
    assert r.header() == (12, 7, "cam0/world") and r.string() == "cam0/camera_optical"
    _check_pose(r.pose(), T)
    np.testing.assert_array_equal(r.f64s(36).reshape(6, 6), pose_cov)
    np.testing.assert_array_equal(r.f64s(6), np.zeros(6))
    np.testing.assert_array_equal(r.f64s(36).reshape(6, 6), twist_cov)
    r.done()


def test_odometry_covariance_is_nominal_and_says_when_scale_is_unknown() -> None:
    cov, twist = odometry_covariances(True, 0.5, 0.02)
    np.testing.assert_allclose(np.diag(cov), [0.25] * 3 + [0.0004] * 3)
    cov, twist = odometry_covariances(False, 0.5, 0.02)
    assert np.all(np.diag(cov)[:3] == UNKNOWN_VARIANCE) and np.all(np.diag(twist)[:3] == UNKNOWN_VARIANCE)
    cov, twist = odometry_covariances(ScaleState.PROVISIONAL, 0.5, 0.02)
    assert np.all(np.diag(cov)[:3] == PROVISIONAL_VARIANCE) and np.all(np.diag(twist)[:3] == PROVISIONAL_VARIANCE)


@pytest.mark.parametrize("state", list(ScaleState))
def test_scale_state_reads_back_from_the_odometry_covariance(state) -> None:
    pose_cov, _ = odometry_covariances(state, 0.5, 0.02)
    r = CdrReader(serialize(messages.odometry(_T(), 0, "w", "c", pose_cov, pose_cov)))
    r.header(), r.string(), r.pose()
    assert scale_state_from_covariance(r.f64s(36)) is state


def test_odometry_carries_the_twist_in_the_child_frame() -> None:
    cov, _ = odometry_covariances(True, 0.5, 0.02)
    twist_cam = np.array([0.01, -0.2, 0.03, 0.5, -0.1, 9.5])  # [ω, v]
    r = CdrReader(serialize(messages.odometry(_T(), 0, "w", "c", cov, cov, twist_cam=twist_cam)))
    r.header(), r.string(), r.pose(), r.f64s(36)
    np.testing.assert_array_equal(r.f64s(6), [0.5, -0.1, 9.5, 0.01, -0.2, 0.03])  # linear, angular
    with pytest.raises(CodecError, match="finite"):
        messages.odometry(_T(), 0, "w", "c", cov, cov, twist_cam=np.full(6, np.nan))


def test_path_decodes_with_an_independent_reader() -> None:
    t_ns = np.array([0, 100_000_000, 2_000_000_001])
    Ts = np.array([_T(t=(i, 0, 0)) for i in range(3)])
    r = CdrReader(serialize(messages.path(t_ns, Ts, 2_000_000_001, "w")))
    assert r.header() == (2, 1, "w") and r.u32() == 3
    for k in range(3):
        sec, nsec, frame = r.header()
        assert sec * 10**9 + nsec == t_ns[k] and frame == "w"
        _check_pose(r.pose(), Ts[k])
    r.done()


def test_point_cloud2_decodes_with_an_independent_reader() -> None:
    points = np.array([[1, 2, 3], [np.nan, 0, 0], [-4.5, 5.25, 60]], dtype=np.float64)
    r = CdrReader(serialize(messages.point_cloud2(points, 5, "cam0/world")))
    assert r.header() == (0, 5, "cam0/world")
    assert (r.u32(), r.u32()) == (1, 2)  # height, width: the NaN point is dropped
    fields = [(r.string(), r.u32(), r.u8(), r.u32()) for _ in range(r.u32())]
    assert fields == [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]
    assert r.u8() == 0 and (r.u32(), r.u32()) == (12, 24)  # little-endian, point/row step
    data = np.frombuffer(r.octets(), dtype="<f4").reshape(-1, 3)
    np.testing.assert_array_equal(data, points[[0, 2]].astype(np.float32))
    assert r.u8() == 1
    r.done()


def test_image_input_mono_rgb_bgr_with_row_padding() -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
    gray = rgb[:, :, 0].copy()
    pad = lambda a, step: b"".join(row.tobytes() + b"\xee" * (step - row.size) for row in a.reshape(len(a), -1))  # noqa: E731
    cases = [("mono8", gray, 8, gray), ("rgb8", rgb, 16, rgb), ("bgr8", rgb[:, :, ::-1], 15, rgb)]
    for encoding, sent, step, expected in cases:
        msg = deserialize(image_cdr(3, 4, "cam", 4, 5, encoding, step, pad(sent, step)), IMAGE)
        assert messages.stamp_ns(msg.header) == 3_000_000_004
        np.testing.assert_array_equal(messages.image_pixels(msg), expected)
    with pytest.raises(CodecError, match="not supported"):
        messages.image_pixels(deserialize(image_cdr(0, 0, "c", 4, 5, "16UC1", 10, bytes(40)), IMAGE))
    with pytest.raises(CodecError, match="bytes"):
        messages.image_pixels(deserialize(image_cdr(0, 0, "c", 4, 5, "mono8", 5, bytes(19)), IMAGE))


def test_camera_info_input_gives_the_pinhole_camera_and_refuses_distortion() -> None:
    info = deserialize(camera_info_cdr(0, 0, "cam", 48, 64, CAMERA.K, [0.0] * 5), CAMERA_INFO)
    assert messages.camera_from_info(info) == CAMERA
    back = CdrReader(serialize(messages.camera_info(CAMERA, 0, "cam")))
    assert back.header() == (0, 0, "cam") and (back.u32(), back.u32()) == (48, 64)
    assert back.string() == "plumb_bob" and back.u32() == 5 and np.all(back.f64s(5) == 0)
    np.testing.assert_array_equal(back.f64s(9).reshape(3, 3), CAMERA.K)
    distorted = deserialize(camera_info_cdr(0, 0, "cam", 48, 64, CAMERA.K, [-0.3, 0.1, 0, 0, 0]), CAMERA_INFO)
    with pytest.raises(CodecError, match="rectified"):
        messages.camera_from_info(distorted)


# -- the service's bridge over real Zenoh sessions (loopback, explicit endpoint) ---------------
@pytest.fixture()
def ros_stack(request):
    """(client session, service) with the ROS 2 bridge on domain 7, identity sessions."""
    port = 17510 + zlib.crc32(request.node.name.encode()) % 10  # 17510-17519: ours alone
    endpoint = f"tcp/127.0.0.1:{port}"
    router = open_router(endpoint)
    client = open_client(endpoint)
    settings = SlamServiceSettings(zenoh_endpoint=endpoint, depth_url=None, session_kind="identity",
                                   status_period_s=0.2, ros2=True, ros2_domain_id=7)
    svc = SlamService(settings, config=SystemConfig(depth={"use_scale": False}, queues={"frames": 64})).start()
    yield client, svc
    svc.stop()
    client.close()
    router.close()


def _subscribe(client, key: str) -> list:
    got: list = []
    sub = client.declare_subscriber(key, lambda s: got.append(
        (str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment else None)))
    got.append(sub)  # keep it declared; got[0] is the subscriber
    return got


def _wait(predicate, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.02)
    return predicate()


def test_odometry_over_zenoh_for_a_published_frame(ros_stack) -> None:
    client, svc = ros_stack
    key = f"7/metricslam/cam0/odom/nav_msgs::msg::dds_::Odometry_/{PUBLISHED_HASHES[ODOMETRY]}"
    got = _subscribe(client, key)
    time.sleep(0.3)  # the subscription reaches the service through the router
    pub = FramePublisher(client, "cam0")
    assert pub.wait_for_subscriber(10)
    pub.publish(0, 1_500_000_000, np.zeros((48, 64), np.uint8), CAMERA)
    assert _wait(lambda: len(got) > 1), "no Odometry on the rmw_zenoh key"
    key_expr, payload, att = got[1]
    assert key_expr == key
    r = CdrReader(payload)
    assert r.header() == (1, 500_000_000, "cam0/world") and r.string() == "cam0/camera_optical"
    _check_pose(r.pose(), np.eye(4))
    assert np.all(np.diag(r.f64s(36).reshape(6, 6))[:3] == UNKNOWN_VARIANCE)  # no learned scale here
    seq, t_ns, source_gid = parse_attachment(att)
    assert seq == 1 and abs(t_ns - time.time_ns()) < 60e9
    tokens = [str(rep.ok.key_expr) for rep in client.liveliness().get("@ros2_lv/7/**", timeout=2) if rep.ok]
    zid = svc.ros2.node.zid
    assert f"@ros2_lv/7/{zid}/0/0/NN/%/%/metricslam_slam" in tokens
    (odom_token,) = [t for t in tokens if "/MP/" in t and "%metricslam%cam0%odom/" in t]
    assert odom_token.endswith(f"/nav_msgs::msg::dds_::Odometry_/{PUBLISHED_HASHES[ODOMETRY]}/::,10:,:,:,,")
    assert source_gid == gid(odom_token)
    assert {"pose", "path", "landmarks"} <= {t.split("%")[-1].split("/")[0] for t in tokens if "/MP/" in t}


def test_ros_image_input_waits_for_camera_info(ros_stack) -> None:
    client, svc = ros_stack
    recorder = PoseRecorder(client, "rosc")
    odom = _subscribe(client, f"7/metricslam/rosc/odom/{dds_type_name(ODOMETRY)}/*")
    time.sleep(0.3)
    image_key = f"7/metricslam/rosc/image/{dds_type_name(IMAGE)}/{PUBLISHED_HASHES[IMAGE]}"
    info_key = f"7/metricslam/rosc/camera_info/{dds_type_name(CAMERA_INFO)}/{PUBLISHED_HASHES[CAMERA_INFO]}"
    frame = np.arange(48 * 64, dtype=np.uint8).reshape(48, 64)
    client.put(image_key, image_cdr(2, 0, "rosc", 48, 64, "mono8", 64, frame.tobytes()))
    assert recorder.wait_for(lambda r: any("ros2_input" in s.session_stats for s in r.statuses), 5)
    note = [s for s in recorder.statuses if "ros2_input" in s.session_stats][0].session_stats["ros2_input"]
    assert "waiting for sensor_msgs/CameraInfo on /metricslam/rosc/camera_info" in note
    assert not recorder.poses
    client.put(info_key, camera_info_cdr(0, 0, "rosc", 48, 64, CAMERA.K, [0.0] * 5))
    time.sleep(0.3)
    for i in range(3):
        client.put(image_key, image_cdr(3 + i, 0, "rosc", 48, 64, "mono8", 64, frame.tobytes()),
                   attachment=attachment(i + 1, time.time_ns(), bytes(16)))
    assert recorder.wait_frames(3, 10), recorder.poses
    assert [recorder.poses[i].t_ns for i in range(3)] == [3_000_000_000, 4_000_000_000, 5_000_000_000]
    assert _wait(lambda: len(odom) > 3)
    stats = svc.health()["ros2"]["inputs"]["rosc"]
    assert stats["camera_info"] and stats["refused_without_camera_info"] == 1
    recorder.close()


def _tf_cdr(payload: bytes) -> list[tuple[tuple[int, int, str], str, np.ndarray]]:
    """tf2_msgs/TFMessage by the independent reader: [(header, child_frame_id, pose7)]."""
    r = CdrReader(payload)
    out = [(r.header(), r.string(), r.f64s(7)) for _ in range(r.u32())]
    r.done()
    return out


def test_tf_world_to_camera_for_every_pose(ros_stack) -> None:
    """A subscriber built from the published key expression (any type hash) gets one ``/tf``
    transform ``cam0/world`` -> ``cam0/camera_optical`` per pose, stamped like the pose, with the
    pose's value, as the MCAP recordings carry it; the token advertises tf2_ros's keep-last 100."""
    client, svc = ros_stack
    tf = _subscribe(client, f"7/tf/{dds_type_name('tf2_msgs/msg/TFMessage')}/*")
    recorder = PoseRecorder(client, "cam0")
    time.sleep(0.3)
    pub = FramePublisher(client, "cam0")
    assert pub.wait_for_subscriber(10)
    stamps = [1_000_000_000 + i * 100_000_000 for i in range(4)]
    for i, t_ns in enumerate(stamps):
        pub.publish(i, t_ns, np.zeros((48, 64), np.uint8), CAMERA)
    assert recorder.wait_frames(4, 10)
    assert _wait(lambda: len(tf) > 4), f"{len(tf) - 1} /tf messages for 4 poses"
    got = [_tf_cdr(payload) for _, payload, _ in tf[1:]]
    assert [len(m) for m in got] == [1, 1, 1, 1]
    assert [m[0][0] for m in got] == [(t // 10**9, t % 10**9, "cam0/world") for t in stamps]
    for (_, child, pose7), i in zip((m[0] for m in got), range(4)):
        assert child == "cam0/camera_optical"
        _check_pose(pose7, recorder.poses[i].T_world_cam)
    tokens = [str(rep.ok.key_expr) for rep in client.liveliness().get("@ros2_lv/7/**", timeout=2) if rep.ok]
    (tf_token,) = [t for t in tokens if "/MP/" in t and "/%tf/" in t]
    assert tf_token.endswith("/::,100:,:,:,,")
    recorder.close()


def test_keyframe_depth_has_a_camera_info_at_its_own_resolution(ros_stack) -> None:
    """The depth image and its CameraInfo pair as image_transport pairs them (siblings), and the
    CameraInfo is the grid's: its size, K scaled so pixel centres map to pixel centres."""
    from metricslam.wire.map_messages import KeyframeDepthMessage
    from metricslam_slam.service.ros2_bridge import depth_camera

    client, svc = ros_stack
    base = "7/metricslam/cam0/keyframe/depth"
    images = _subscribe(client, f"{base}/image/{dds_type_name(IMAGE)}/*")
    infos = _subscribe(client, f"{base}/camera_info/{dds_type_name(CAMERA_INFO)}/*")
    recorder = PoseRecorder(client, "cam0")
    time.sleep(0.3)
    pub = FramePublisher(client, "cam0")
    assert pub.wait_for_subscriber(10)
    pub.publish(0, 0, np.zeros((48, 64), np.uint8), CAMERA)  # the service learns the intrinsics
    assert recorder.wait_frames(1, 10)
    inv = np.full((12, 16), 0.25, np.float32)
    inv[0, 0] = 0.0  # unknown
    svc.ros2.forward("cam0", "keyframe_depth", KeyframeDepthMessage(
        camera_id="cam0", frame_index=0, t_ns=2_000_000_000, image_width_px=64, image_height_px=48,
        inv_depth_per_m=inv))
    assert _wait(lambda: len(images) > 1 and len(infos) > 1)
    image = deserialize(images[1][1], IMAGE)
    info = deserialize(infos[1][1], CAMERA_INFO)
    assert (image.height, image.width, image.encoding) == (12, 16, "32FC1")
    assert (info.height, info.width) == (12, 16)
    assert image.header.frame_id == info.header.frame_id == "cam0/camera_optical"
    assert messages.stamp_ns(image.header) == messages.stamp_ns(info.header) == 2_000_000_000
    depth = np.frombuffer(bytes(image.data), np.float32).reshape(12, 16)
    assert np.isnan(depth[0, 0]) and np.allclose(depth.ravel()[1:], 4.0)
    grid = depth_camera(CAMERA, KeyframeDepthMessage(
        camera_id="cam0", frame_index=0, t_ns=0, image_width_px=64, image_height_px=48, inv_depth_per_m=inv))
    np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3), grid.K)
    # a point projects onto the same place of the image in both: grid px = image px scaled (centres)
    p = np.array([[0.3, -0.2, 2.0]])
    uv_image, uv_grid = CAMERA.project(p)[0], grid.project(p)[0]
    np.testing.assert_allclose((uv_grid + 0.5) * 4.0 - 0.5, uv_image, atol=1e-9)
    recorder.close()


def test_ros2_without_rosbags_fails_at_start_naming_the_extra(monkeypatch) -> None:
    from metricslam.errors import ConfigError
    from metricslam.ros2 import typestore as typestore_module
    from metricslam_slam.service.ros2_bridge import Ros2Bridge

    def missing():
        raise ConfigError("ROS 2 messages need rosbags: pip install 'metricslam[ros]'")

    monkeypatch.setattr("metricslam_slam.service.ros2_bridge.typestore", missing)
    assert typestore_module.typestore() is not None  # the real one is untouched
    with pytest.raises(ConfigError, match=r"SLAM_ROS2=1.*metricslam\[ros\]"):
        Ros2Bridge.check_available()
    settings = SlamServiceSettings(zenoh_endpoint="tcp/127.0.0.1:1", depth_url=None, session_kind="identity",
                                   ros2=True)
    with pytest.raises(ConfigError, match="SLAM_ROS2=1"):
        SlamService(settings, config=SystemConfig(depth={"use_scale": False})).start(connect_timeout_s=0.1)
