"""Fuzzing the wire decoder: whatever the bytes, ``decode`` returns a message or raises
:class:`CodecError` — never ValueError, OverflowError, TypeError, MemoryError, ... (those used to
escape from shapes like ``[2**61, 8]`` and kill the pose recorder's zenoh callback).

Three generators: arbitrary bytes, byte-level mutations of valid messages, and well-framed
messages whose JSON header is generated (any kind, body and array specs, huge and negative
dimensions, any dtype name). Plus the intrinsics edge cases (NaN, inf, 1e308, ...).
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from metricslam.camera import PinholeCamera
from metricslam.errors import CameraError, CodecError
from metricslam.slam.types import TrackingState
from metricslam.wire.codec import (
    FrameMessage, Message, PoseMessage, StatusMessage, TrajectoryMessage, decode, encode,
)

FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=7.5, cy_px=5.5, width_px=16, height_px=12)
VALID = [
    encode(FrameMessage(camera_id="cam0", frame_index=3, t_ns=5, camera=CAMERA,
                        image=np.arange(192, dtype=np.uint8).reshape(12, 16))),
    encode(PoseMessage(camera_id="cam0", frame_index=3, t_ns=5, state=TrackingState.TRACKING,
                       T_world_cam=np.eye(4))),
    encode(TrajectoryMessage(camera_id="cam0", frame_index=np.arange(2, dtype=np.int64),
                             t_ns=np.arange(2, dtype=np.int64), T_world_cam=np.stack([np.eye(4)] * 2),
                             state_code=np.zeros(2, np.uint8))),
    encode(StatusMessage(camera_id="cam0", t_ns=1, frames_received=1, frames_processed=1, queue_drops=0,
                         malformed=0, queue_depth=0, fps=1.0, event="camera_refused", event_detail="full")),
]


def _decodes_or_codec_error(payload: bytes) -> None:
    try:
        assert isinstance(decode(payload), Message)
    except CodecError:
        pass  # the only error a receiver has to handle


def _framed(header: bytes, tail: bytes = b"") -> bytes:
    return b"MSLM" + struct.pack("<I", len(header)) + header + tail


json_scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70),
                         st.floats(allow_nan=False), st.text(max_size=20))
json_values = st.recursive(json_scalars, lambda kids: st.one_of(
    st.lists(kids, max_size=4), st.dictionaries(st.text(max_size=12), kids, max_size=4)), max_leaves=12)
dims = st.one_of(st.integers(0, 16), st.sampled_from([2**31, 2**61, 2**63, 2**64, 2**100, -1]),
                 st.integers(-2**70, 2**70))
array_specs = st.fixed_dictionaries({
    "name": st.sampled_from(["image", "T_world_cam", "frame_index", "t_ns", "state_code", "x"]),
    "dtype": st.sampled_from(["uint8", "int64", "float32", "float64", "object", "<f8"]),
    "shape": st.lists(dims, max_size=5)})
field_names = st.sampled_from(["frame_index", "t_ns", "camera", "state", "T_world_cam", "frames_received",
                               "fps", "camera_id", "event", "image", "scale_established"])


@FUZZ
@given(st.binary(max_size=512))
def test_random_bytes(data: bytes) -> None:
    _decodes_or_codec_error(data)
    _decodes_or_codec_error(b"MSLM" + data)


@FUZZ
@given(st.sampled_from(VALID), st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=8),
       st.integers(0, 10**6), st.binary(max_size=16))
def test_mutated_valid_messages(payload: bytes, flips: list, cut: int, extra: bytes) -> None:
    data = bytearray(payload)
    for pos, value in flips:
        data[pos % len(data)] = value
    _decodes_or_codec_error(bytes(data))
    _decodes_or_codec_error(bytes(data[:cut % (len(data) + 1)]) + extra)


@FUZZ
@given(st.sampled_from(["frame", "pose", "keyframe", "status", "trajectory", "calibration", "landmarks",
                        "keyframe_depth", "nope"]),
       st.dictionaries(field_names, json_values, max_size=6), st.lists(array_specs, max_size=4),
       st.one_of(st.just(1), json_values), st.binary(max_size=256))
def test_generated_headers(kind: str, body: dict, arrays: list, version, tail: bytes) -> None:
    body = {"camera_id": "cam0", **body}
    header = json.dumps({"schema_version": version, "kind": kind, "body": body, "arrays": arrays}).encode()
    _decodes_or_codec_error(_framed(header, tail))
    nbytes = sum(max(0, int(np.prod([d for d in a["shape"] if 0 <= d < 64] or [0]))) * 8 for a in arrays)
    _decodes_or_codec_error(_framed(header, bytes(min(nbytes, 4096))))


@pytest.mark.parametrize("shape", [[2**61, 8], [2**64], [2**63, 2], [-1, 4], [2**32, 2**32], [10**40]])
def test_huge_shapes_are_codec_errors(shape: list) -> None:
    header = json.dumps({"schema_version": 1, "kind": "pose", "body": {"camera_id": "c"},
                         "arrays": [{"name": "T_world_cam", "dtype": "float64", "shape": shape}]}).encode()
    with pytest.raises(CodecError):
        decode(_framed(header))


@pytest.mark.parametrize("field, value", [
    ("fx_px", float("nan")), ("fx_px", float("inf")), ("fx_px", 1e308), ("fy_px", -1.0), ("fx_px", 0.0),
    ("fx_px", 2e5), ("cx_px", 1e308), ("cx_px", -100.0), ("cy_px", 40.0), ("cy_px", float("nan"))])
def test_implausible_intrinsics_are_refused_everywhere(field: str, value: float) -> None:
    """Frames with NaN/inf/huge intrinsics are codec errors (the service counts them as
    malformed); the same check refuses them in PinholeCamera and the ``camera`` command."""
    good = json.loads(VALID[0][8:8 + struct.unpack_from("<I", VALID[0], 4)[0]])
    good["body"]["camera"][field] = value
    header = json.dumps(good).encode()  # json writes NaN / Infinity, as a hostile sender could
    tail = VALID[0][8 + struct.unpack_from("<I", VALID[0], 4)[0]:]
    with pytest.raises(CodecError, match="camera"):
        decode(_framed(header, tail))
    from metricslam_cli.camera_cmd import intrinsics

    kwargs = {"fx": 100.0, "fy": 100.0, "cx": 7.5, "cy": 5.5, field.removesuffix("_px")[:2]: value}
    with pytest.raises(CameraError):
        intrinsics(16, 12, **kwargs)
