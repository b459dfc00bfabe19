"""Wire codec: every message round-trips; every malformed payload raises CodecError."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from metricslam.camera import PinholeCamera
from metricslam.errors import CodecError
from metricslam.slam.types import TrackingState
from metricslam.wire import keys
from metricslam.wire.codec import (
    CalibrationMessage, FrameMessage, KeyframeMessage, PoseMessage, StatusMessage,
    TrajectoryMessage, decode, decode_as, encode,
)


def _camera(w: int = 64, h: int = 32) -> PinholeCamera:
    return PinholeCamera(fx_px=50.0, fy_px=51.0, cx_px=w / 2, cy_px=h / 2, width_px=w, height_px=h)


def _pose(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    T = np.eye(4)
    T[:3, :3] = q * np.sign(np.linalg.det(q))
    T[:3, 3] = rng.normal(size=3) * 10
    return T


def _frame(w: int = 64, h: int = 32, rgb: bool = False, seed: int = 0) -> FrameMessage:
    rng = np.random.default_rng(seed)
    shape = (h, w, 3) if rgb else (h, w)
    return FrameMessage(camera_id="cam0", frame_index=7, t_ns=123_456_789, camera=_camera(w, h),
                        t_sent_ns=42, image=rng.integers(0, 256, shape, dtype=np.uint8))


@settings(max_examples=25, deadline=None)
@given(w=st.integers(1, 40), h=st.integers(1, 40), rgb=st.booleans(), seed=st.integers(0, 2**16))
def test_frame_round_trip(w: int, h: int, rgb: bool, seed: int) -> None:
    msg = _frame(w, h, rgb, seed)
    out = decode_as(encode(msg), FrameMessage)
    assert out.camera == msg.camera and out.frame_index == 7 and out.t_ns == 123_456_789
    assert out.t_sent_ns == 42
    np.testing.assert_array_equal(out.image, msg.image)
    assert out.image.dtype == np.uint8 and out.image.flags.writeable


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.integers(0, 30))
def test_pose_keyframe_trajectory_round_trip(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    T = _pose(rng)
    pose = PoseMessage(camera_id="a.b-c", frame_index=3, t_ns=5, state=TrackingState.TRACKING,
                       is_keyframe=True, segment_id=2, scale_established=True, processing_ms=1.5,
                       T_world_cam=T)
    out = decode_as(encode(pose), PoseMessage)
    np.testing.assert_array_equal(out.T_world_cam, T)
    assert out.model_dump(exclude={"T_world_cam"}) == pose.model_dump(exclude={"T_world_cam"})

    kf = KeyframeMessage(camera_id="cam0", frame_index=3, t_ns=5, T_world_cam=T)
    assert decode_as(encode(kf), KeyframeMessage).image is None
    kf_img = KeyframeMessage(camera_id="cam0", frame_index=3, t_ns=5, T_world_cam=T,
                             image=np.full((4, 5), 9, np.uint8))
    np.testing.assert_array_equal(decode_as(encode(kf_img), KeyframeMessage).image, kf_img.image)

    states = [list(TrackingState)[i % len(TrackingState)] for i in range(n)]
    traj = TrajectoryMessage(
        camera_id="cam0", scale_established=True, frame_index=np.arange(n, dtype=np.int64),
        t_ns=np.arange(n, dtype=np.int64) * 100,
        T_world_cam=np.stack([_pose(rng) for _ in range(n)]) if n else np.zeros((0, 4, 4)),
        state_code=TrajectoryMessage.state_codes(states))
    out_t = decode_as(encode(traj), TrajectoryMessage)
    np.testing.assert_array_equal(out_t.T_world_cam, traj.T_world_cam)
    np.testing.assert_array_equal(out_t.t_ns, traj.t_ns)
    assert out_t.states == states


def test_status_and_calibration_round_trip() -> None:
    status = StatusMessage(camera_id="cam0", t_ns=1, frames_received=10, frames_processed=9,
                           queue_drops=1, malformed=2, queue_depth=0, fps=9.5, latency_ms_p50=3.0,
                           latency_ms_p99=7.0, tracking_state=TrackingState.LOST,
                           depth_url="http://x", depth_reachable=False, depth_error="refused",
                           session_stats={"keyframes": 3, "ms_per_frame": 12.5, "mode": "vo"})
    assert decode_as(encode(status), StatusMessage) == status
    cal = CalibrationMessage(camera_id="cam0", camera=_camera(), baseline_m=0.54)
    assert decode_as(encode(cal), CalibrationMessage) == cal


def _splice_header(payload: bytes, mutate) -> bytes:
    (hlen,) = struct.unpack_from("<I", payload, 4)
    header = json.loads(payload[8:8 + hlen])
    mutate(header)
    new = json.dumps(header).encode()
    return payload[:4] + struct.pack("<I", len(new)) + new + payload[8 + hlen:]


def _bad_payloads() -> dict[str, bytes]:
    good = encode(_frame())
    return {
        "empty": b"",
        "short": b"MSL",
        "garbage": bytes(np.random.default_rng(1).integers(0, 256, 500, dtype=np.uint8)),
        "bad magic": b"XXXX" + good[4:],
        "header length past end": good[:4] + struct.pack("<I", 10**6) + good[8:],
        "truncated arrays": good[:-1],
        "trailing bytes": good + b"\x00",
        "bad json": good[:8] + b"{" * (len(good) - 8),
        "version": _splice_header(good, lambda h: h.update(schema_version=99)),
        "kind": _splice_header(good, lambda h: h.update(kind="nope")),
        "extra field": _splice_header(good, lambda h: h["body"].update(extra=1)),
        "missing field": _splice_header(good, lambda h: h["body"].pop("t_ns")),
        "negative index": _splice_header(good, lambda h: h["body"].update(frame_index=-1)),
        "camera id": _splice_header(good, lambda h: h["body"].update(camera_id="a/b")),
        "image vs camera size": _splice_header(good, lambda h: h["body"]["camera"].update(width_px=65)),
        "wrong dtype": _splice_header(good, lambda h: h["arrays"][0].update(dtype="float64")),
        "wrong shape same bytes": _splice_header(good, lambda h: h["arrays"][0].update(shape=[64, 32])),
        "unknown array": _splice_header(good, lambda h: h["arrays"][0].update(name="depth")),
        "negative dim": _splice_header(good, lambda h: h["arrays"][0].update(shape=[-32, -64])),
    }


@pytest.mark.parametrize("name", sorted(_bad_payloads()))
def test_malformed_payloads_raise_codec_error(name: str) -> None:
    with pytest.raises(CodecError):
        decode(_bad_payloads()[name])


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_never_crash(data: bytes) -> None:
    with pytest.raises(CodecError):
        decode(data)


@settings(max_examples=100, deadline=None)
@given(cut=st.integers(0, 2000))
def test_any_truncation_raises(cut: int) -> None:
    good = encode(_frame(8, 4))
    if cut >= len(good):
        return
    with pytest.raises(CodecError):
        decode(good[:cut])


def test_wrong_kind_and_non_finite_pose() -> None:
    with pytest.raises(CodecError):
        decode_as(encode(_frame()), PoseMessage)
    with pytest.raises(ValueError):
        PoseMessage(camera_id="c", frame_index=0, t_ns=0, state="tracking",
                    T_world_cam=np.full((4, 4), np.nan))


def test_keys() -> None:
    assert keys.key("cam0", "pose") == "metricslam/cam0/pose"
    assert keys.parse_key("metricslam/cam-1/frame") == ("cam-1", "frame")
    for bad in ("metricslam/a/b/frame", "other/cam0/frame", "metricslam/_x/frame", "metricslam/c/bogus"):
        with pytest.raises(CodecError):
            keys.parse_key(bad)
    with pytest.raises(CodecError):
        keys.key("a*b", "pose")


def test_wire_is_pure() -> None:
    import subprocess
    import sys
    code = ("import sys, metricslam.wire; bad = [m for m in ('zenoh', 'httpx', 'fastapi', 'torch') "
            "if m in sys.modules]; assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_map_messages_round_trip_and_check_shapes() -> None:
    from metricslam.wire.map_messages import KeyframeDepthMessage, LandmarksMessage

    points = np.arange(12, dtype=np.float32).reshape(4, 3)
    lm = decode(encode(LandmarksMessage(camera_id="cam0", frame_index=3, t_ns=7, points_world=points)))
    assert isinstance(lm, LandmarksMessage) and lm.frame_index == 3
    np.testing.assert_array_equal(lm.points_world, points)
    inv = np.array([[0.1, 0.0], [0.5, -1.0]], dtype=np.float32)
    depth = decode(encode(KeyframeDepthMessage(camera_id="cam0", frame_index=3, t_ns=7, image_width_px=64,
                                               image_height_px=32, inv_depth_per_m=inv)))
    np.testing.assert_array_equal(depth.inv_depth_per_m, inv)
    np.testing.assert_allclose(depth.depth_m(), [[10.0, np.nan], [2.0, np.nan]])
    assert {"path", "landmarks", "keyframe_depth"} <= set(keys.TOPICS)
    with pytest.raises(ValueError):
        LandmarksMessage(camera_id="cam0", frame_index=0, t_ns=0, points_world=np.zeros((4, 2), np.float32))
