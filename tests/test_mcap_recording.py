"""MCAP recordings for Foxglove (``run --mcap``, ``poses --mcap``), read back with the ``mcap``
reader; message bodies decoded with the independent CDR reader of tests/ros2_cdr.py."""

from __future__ import annotations

import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest

from metricslam.datasets import open_sequence
from metricslam.trajectory.io import read_kitti_poses
from metricslam_cli.main import main
from tests.ros2_cdr import CdrReader

CLI = [sys.executable, "-m", "metricslam_cli.main"]
ENDPOINT = "tcp/127.0.0.1:17520"  # 17520: this module alone


def read_mcap(path: Path) -> dict[str, list]:
    """topic -> [(log_time, publish_time, data, schema name, schema encoding, message encoding)]."""
    from mcap.reader import make_reader

    out: dict[str, list] = defaultdict(list)
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            out[channel.topic].append((message.log_time, message.publish_time, message.data,
                                       schema.name, schema.encoding, channel.message_encoding))
    return dict(out)


def _stamp(r: CdrReader) -> tuple[int, str]:
    sec, nanosec, frame = r.header()
    return sec * 1_000_000_000 + nanosec, frame


def check_layout(topics: dict[str, list], base: str, depth_info: bool = True) -> None:
    """Schemas and encodings of every message; stamps and bodies of the depth maps and clouds;
    with ``depth_info`` (the recorder knows the keyframes' camera: ``run``), each depth map's
    CameraInfo at its own resolution."""
    for msgs in topics.values():
        for log_time, publish_time, _, _, schema_encoding, message_encoding in msgs:
            assert (schema_encoding, message_encoding) == ("ros2msg", "cdr") and log_time == publish_time
    names = {t: msgs[0][3] for t, msgs in topics.items()}
    assert names[f"{base}/pose"] == "geometry_msgs/msg/PoseStamped" and names["/tf"] == "tf2_msgs/msg/TFMessage"
    assert names[f"{base}/path"] == "nav_msgs/msg/Path"
    assert names[f"{base}/landmarks"] == "sensor_msgs/msg/PointCloud2"
    assert names[f"{base}/keyframe/depth/image"] == "sensor_msgs/msg/Image"
    grids = {}
    for log_time, _, data, *_ in topics[f"{base}/keyframe/depth/image"]:
        r = CdrReader(data)
        t_ns, _ = _stamp(r)
        h, w, encoding = r.u32(), r.u32(), r.string()
        assert t_ns == log_time and encoding == "32FC1" and r.u8() == 0 and r.u32() == 4 * w
        depth_m = np.frombuffer(r.octets(), dtype="<f4").reshape(h, w)
        assert np.nanmedian(depth_m) > 0
        grids[t_ns] = (h, w)
    if not depth_info:  # a live client's recording: keyframe messages carry no intrinsics
        assert f"{base}/keyframe/depth/camera_info" not in names
        _check_landmarks(topics, base)
        return
    assert names[f"{base}/keyframe/depth/camera_info"] == "sensor_msgs/msg/CameraInfo"
    infos = {}
    for log_time, _, data, *_ in topics[f"{base}/keyframe/depth/camera_info"]:
        r = CdrReader(data)
        t_ns, _ = _stamp(r)
        assert t_ns == log_time
        infos[t_ns] = (r.u32(), r.u32())  # the depth image's own (coarse) height and width
    assert infos == grids  # one CameraInfo per depth image, at its resolution (the live bridge's pairing)
    _check_landmarks(topics, base)


def _check_landmarks(topics: dict[str, list], base: str) -> None:
    """Stamps and layout of the landmark clouds; the map is not empty by the end."""
    widths = []
    for log_time, _, data, *_ in topics[f"{base}/landmarks"]:
        r = CdrReader(data)
        assert _stamp(r)[0] == log_time and r.u32() == 1
        widths.append(r.u32())  # points (none while the map initializes)
        assert r.u32() == 3 and (r.string(), r.u32(), r.u8(), r.u32()) == ("x", 0, 7, 1)
    assert max(widths) > 20


def test_run_writes_an_mcap_of_a_rendered_sequence(synth_sequence, tmp_path: Path) -> None:
    seq_dir = synth_sequence(40, seed=3, path="loop")
    out, mcap_path = tmp_path / "est.txt", tmp_path / "run.mcap"
    assert main(["run", str(seq_dir), "--out", str(out), "--deterministic", "--no-progress",
                 "--mcap", str(mcap_path)]) == 0
    seq = open_sequence(seq_dir)
    t_ns = [seq[i].t_ns for i in range(len(seq))]
    topics = read_mcap(mcap_path)
    (base,) = {t.rsplit("/", 1)[0] for t in topics if t.endswith("/pose")}
    check_layout(topics, base)
    # every frame's pose, on the sequence's clock, in order
    poses = topics[f"{base}/pose"]
    assert [m[0] for m in poses] == t_ns and len(topics["/tf"]) == len(t_ns)
    for (log_time, _, data, *_) in poses:
        r = CdrReader(data)
        assert _stamp(r) == (log_time, base.split("/")[-1] + "/world")
    # keyframes: a JPEG and a CameraInfo each, landmarks with each
    images = topics[f"{base}/keyframe/image/compressed"]
    assert len(images) >= 5 and len(images) == len(topics[f"{base}/keyframe/camera_info"])
    assert len(topics[f"{base}/landmarks"]) == len(images)
    r = CdrReader(images[0][2])
    assert _stamp(r)[0] == images[0][0] and r.string() == "jpeg"
    jpeg = cv2.imdecode(np.frombuffer(r.octets(), np.uint8), cv2.IMREAD_UNCHANGED)
    assert jpeg.shape[:2] == seq[0].image.shape[:2]
    assert len(topics[f"{base}/keyframe/depth/image"]) >= 3
    # the last path is the final optimized trajectory, the one written to --out
    r = CdrReader(topics[f"{base}/path"][-1][2])
    assert _stamp(r)[0] == t_ns[-1]
    n = r.u32()
    stamps, positions = [], []
    for _ in range(n):
        stamps.append(_stamp(r)[0])
        positions.append(r.pose()[:3])
    T_est = read_kitti_poses(out)
    index = {t: i for i, t in enumerate(t_ns)}
    assert n >= len(t_ns) - 8 and all(s in index for s in stamps)
    np.testing.assert_allclose(positions, T_est[[index[s] for s in stamps], :3, 3], atol=1e-6)


@pytest.mark.data
@pytest.mark.slow
def test_run_mcap_on_kitti_06_has_every_frames_pose(shared_data: Path, tmp_path: Path) -> None:
    seq_dir = shared_data / "kitti_odometry" / "sequences" / "06"
    if not (seq_dir / "times.txt").is_file():
        pytest.skip(f"{seq_dir} is absent")
    mcap_path = tmp_path / "kitti06.mcap"
    assert main(["run", str(seq_dir), "--out", str(tmp_path / "est.txt"), "--deterministic",
                 "--no-progress", "--mcap", str(mcap_path)]) == 0
    t_ns = [int(round(float(line) * 1e9)) for line in (seq_dir / "times.txt").read_text().split()]
    assert len(t_ns) == 51
    topics = read_mcap(mcap_path)
    base = "/metricslam/cam_06"
    check_layout(topics, base)
    assert [m[0] for m in topics[f"{base}/pose"]] == [m[0] for m in topics["/tf"]]
    np.testing.assert_allclose([m[0] for m in topics[f"{base}/pose"]], t_ns, atol=1000)  # ns rounding
    assert len(topics[f"{base}/keyframe/image/compressed"]) >= 3 and len(topics[f"{base}/keyframe/depth/image"]) >= 2


def test_poses_records_a_live_mcap(synth_sequence, tmp_path: Path) -> None:
    """A real SLAM session behind the service (in-process depth model, deterministic), frames
    over Zenoh, ``metricslam poses --mcap`` recording everything the service publishes; the ROS 2
    bridge is on, and its Path and PointCloud2 samples are decoded too."""
    from metricslam.slam.system_config import SystemConfig
    from metricslam_slam.service.settings import SlamServiceSettings
    from metricslam_slam.service.slam_service import SlamService
    from metricslam_slam.supervisor.router import open_router
    from metricslam_slam.tools.client import FramePublisher, query_health
    from metricslam_slam.zenoh_config import open_client

    seq = open_sequence(synth_sequence(40, seed=3, path="loop"))
    n = len(seq)
    router = open_router(ENDPOINT)
    svc = SlamService(SlamServiceSettings(zenoh_endpoint=ENDPOINT, depth_url=None, keyframe_images=True,
                                          ros2=True, ros2_domain_id=5),
                      config=SystemConfig(vo={"preset": "synth"}, deterministic=True, queues={"frames": 64})).start()
    client = open_client(ENDPOINT)
    ros_samples: list = []
    ros_sub = client.declare_subscriber("5/metricslam/synth/**", lambda sample: ros_samples.append(
        (str(sample.key_expr).split("/")[3], sample.payload.to_bytes())))
    try:
        deadline = time.monotonic() + 5
        while query_health(client, 0.5) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        mcap_path = tmp_path / "live.mcap"
        rec = subprocess.Popen(CLI + ["poses", "--zenoh-endpoint", ENDPOINT, "--out", str(tmp_path / "est.txt"),
                                      "--frames", str(n), "--timeout", "120", "--camera-id", "synth",
                                      "--trajectory", "--mcap", str(mcap_path)],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert rec.stdout.readline().startswith("recording")
        time.sleep(0.5)  # its subscriptions reach the service through the router
        pub = FramePublisher(client, "synth")
        assert pub.wait_for_subscriber(10)
        for i in range(n):
            frame = seq[i]
            pub.publish(i, frame.t_ns, frame.image, frame.camera)
            time.sleep(0.02)
        assert rec.wait(180) == 0, rec.stdout.read()
    finally:
        ros_sub.undeclare()
        client.close()
        svc.stop()
        router.close()
    topics = read_mcap(mcap_path)
    base = "/metricslam/synth"
    check_layout(topics, base, depth_info=False)
    assert [m[0] for m in topics[f"{base}/pose"]] == [seq[i].t_ns for i in range(n)]
    assert len(topics[f"{base}/keyframe/image/compressed"]) >= 5
    assert f"{base}/keyframe/camera_info" not in topics  # keyframe messages carry no intrinsics
    assert len(topics[f"{base}/path"]) >= 2 and len(topics[f"{base}/keyframe/depth/image"]) >= 1
    by_leaf = defaultdict(list)
    for leaf, payload in ros_samples:
        by_leaf[leaf].append(payload)
    assert len(by_leaf["pose"]) == len(by_leaf["odom"]) >= n - 10  # tracking frames only
    assert 0 <= len(by_leaf["landmarks"]) - len(topics[f"{base}/landmarks"]) <= 1  # poses stops 1 s after its last pose
    r = CdrReader(by_leaf["path"][-1])
    assert _stamp(r)[1] == "synth/world" and r.u32() >= n - 10
