"""The one codec for every message of the SLAM stack: versioned pydantic header + raw arrays.

Wire layout of one message (all integers little-endian)::

    b"MSLM"                       4 bytes magic
    header_len                    uint32
    header                        header_len bytes of UTF-8 JSON: :class:`Envelope`
    array bytes                   each array of ``Envelope.arrays`` in order, C-contiguous,
                                  little-endian, exactly prod(shape) * itemsize bytes

``Envelope`` = ``{"schema_version": 1, "kind": "frame", "body": {...}, "arrays": [...]}``:
``body`` holds the message's scalar fields (validated by the message's pydantic model with
``extra="forbid"``), ``arrays`` describes the array fields (name, dtype, shape). A receiver that
gets anything else — wrong magic, truncated header, bad JSON, unknown kind or version, a missing
or extra field, an array whose byte count does not match — gets :class:`CodecError`, never a
crash. Frames, keys and units follow ``docs/conventions.md``; message fields carry units in
their names (``t_ns``, ``T_world_cam``, ``fx_px``).

The messages live beside this module, all on :class:`~metricslam.wire.base.Message`:
``camera_messages`` (frame, calibration, pose, keyframe, status, trajectory), ``map_messages``
(landmarks, keyframe depth) and ``odometry_message``; :data:`MESSAGE_TYPES` lists them, and every
one can be imported from here as well (``from metricslam.wire.codec import PoseMessage``).
"""

from __future__ import annotations

import json
import math
import struct
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from metricslam.errors import CodecError
from metricslam.wire.base import DTYPES as _DTYPES
from metricslam.wire.base import Message
from metricslam.wire.base import as_array as _as_array  # noqa: F401 -- the name before wire.base
from metricslam.wire.base import finite_pose as _finite_pose  # noqa: F401 -- the name before wire.base
from metricslam.wire.camera_messages import (
    STATE_CODES,
    CalibrationMessage,
    FrameMessage,
    KeyframeMessage,
    PoseMessage,
    StatusMessage,
    TrajectoryMessage,
)
from metricslam.wire.map_messages import KeyframeDepthMessage, LandmarksMessage
from metricslam.wire.odometry_message import OdometryMessage

__all__ = [
    "MAGIC", "MAX_HEADER_BYTES", "MAX_MESSAGE_BYTES", "MESSAGE_TYPES", "SCHEMA_VERSION", "STATE_CODES",
    "ArraySpec", "CalibrationMessage", "Envelope", "FrameMessage", "KeyframeDepthMessage", "KeyframeMessage",
    "LandmarksMessage", "Message", "OdometryMessage", "PoseMessage", "StatusMessage", "TrajectoryMessage",
    "decode", "decode_as", "encode",
]

SCHEMA_VERSION = 1
MAGIC = b"MSLM"
MAX_HEADER_BYTES = 1 << 20
MAX_MESSAGE_BYTES = 256 << 20
_PREFIX = struct.Struct("<4sI")

#: every message type the codec speaks, by its ``KIND`` (the envelope's ``kind``)
MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.KIND: cls for cls in (FrameMessage, CalibrationMessage, PoseMessage, KeyframeMessage, StatusMessage,
                              TrajectoryMessage, LandmarksMessage, KeyframeDepthMessage, OdometryMessage)
}


class ArraySpec(BaseModel):
    """Describes one array that follows the header."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    dtype: Literal["uint8", "int64", "float32", "float64"]
    shape: tuple[int, ...] = Field(max_length=4)

    @field_validator("shape")
    @classmethod
    def _non_negative(cls, shape: tuple[int, ...]) -> tuple[int, ...]:
        if any(n < 0 for n in shape):
            raise ValueError(f"array dimensions must be >= 0, got {shape}")
        # exact (Python int) size: int64 products of e.g. [2**61, 8] wrap around to 0 bytes
        if any(n > MAX_MESSAGE_BYTES for n in shape) or math.prod(shape) > MAX_MESSAGE_BYTES:
            raise ValueError(f"array of shape {list(shape)} exceeds the {MAX_MESSAGE_BYTES}-byte message limit")
        return shape

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * _DTYPES[self.dtype].itemsize


class Envelope(BaseModel):
    """The JSON header of every message."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    schema_version: int
    kind: str
    body: dict[str, Any]
    arrays: list[ArraySpec] = Field(max_length=16)


def encode(message: Message) -> bytes:
    """Serialize a message (see the module docstring for the layout)."""
    if type(message).KIND not in MESSAGE_TYPES:
        raise CodecError(f"cannot encode {type(message).__name__}: not a wire message type")
    body = message.model_dump(mode="json", exclude=set(message.ARRAYS))
    specs: list[dict] = []
    chunks: list[bytes] = []
    for name in message.ARRAYS:
        array = getattr(message, name)
        if array is None:
            continue
        dtype = next(k for k, v in _DTYPES.items() if v == array.dtype)
        specs.append({"name": name, "dtype": dtype, "shape": list(array.shape)})
        chunks.append(np.ascontiguousarray(array, dtype=_DTYPES[dtype]).tobytes())
    header = json.dumps({"schema_version": SCHEMA_VERSION, "kind": message.KIND, "body": body,
                         "arrays": specs}, separators=(",", ":")).encode()
    if len(header) > MAX_HEADER_BYTES:
        raise CodecError(f"header of {len(header)} bytes exceeds {MAX_HEADER_BYTES}")
    return b"".join([_PREFIX.pack(MAGIC, len(header)), header, *chunks])


def decode(payload: bytes | bytearray | memoryview) -> Message:
    """Parse and validate any message; raises :class:`CodecError` saying what is wrong, and
    nothing else on any bytes (``tests/test_wire_codec_fuzz.py``)."""
    try:
        return _decode(payload)
    except CodecError:
        raise
    except Exception as exc:  # noqa: BLE001 -- untrusted input: whatever slipped past the checks
        raise CodecError(f"malformed message ({type(exc).__name__}: {str(exc)[:200]})") from None


def _decode(payload: bytes | bytearray | memoryview) -> Message:
    data = memoryview(payload).cast("B")
    if len(data) < _PREFIX.size:
        raise CodecError(f"message of {len(data)} bytes is shorter than the {_PREFIX.size}-byte prefix")
    if len(data) > MAX_MESSAGE_BYTES:
        raise CodecError(f"message of {len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    magic, header_len = _PREFIX.unpack_from(data, 0)
    if magic != MAGIC:
        raise CodecError(f"bad magic {bytes(magic)!r}: not a metricslam wire message (expected {MAGIC!r})")
    end = _PREFIX.size + header_len
    if header_len > MAX_HEADER_BYTES or end > len(data):
        raise CodecError(f"header length {header_len} does not fit a {len(data)}-byte message")
    try:
        envelope = Envelope.model_validate_json(bytes(data[_PREFIX.size:end]))
    except ValidationError as exc:
        raise CodecError(f"malformed header: {_first_error(exc)}") from None
    if envelope.schema_version != SCHEMA_VERSION:
        raise CodecError(f"schema_version {envelope.schema_version} is not supported (this build "
                         f"speaks {SCHEMA_VERSION}); upgrade the older side")
    cls = MESSAGE_TYPES.get(envelope.kind)
    if cls is None:
        raise CodecError(f"unknown message kind {envelope.kind!r}; expected one of {sorted(MESSAGE_TYPES)}")
    expected = sum(spec.nbytes for spec in envelope.arrays)
    if expected != len(data) - end:
        raise CodecError(f"{envelope.kind}: arrays need {expected} bytes after the header, "
                         f"message has {len(data) - end}")
    fields = dict(envelope.body)
    offset = end
    for spec in envelope.arrays:
        if spec.name not in cls.ARRAYS or spec.name in fields:
            raise CodecError(f"{envelope.kind}: unexpected or duplicate array {spec.name!r}")
        raw = data[offset:offset + spec.nbytes]
        fields[spec.name] = np.frombuffer(raw, dtype=_DTYPES[spec.dtype]).reshape(spec.shape).copy()
        offset += spec.nbytes
    try:
        return cls.model_validate(fields)
    except ValidationError as exc:
        raise CodecError(f"invalid {envelope.kind} message: {_first_error(exc)}") from None


def decode_as(payload: bytes | bytearray | memoryview, cls: type[Message]) -> Message:
    """:func:`decode` and check that the message is a ``cls``."""
    message = decode(payload)
    if not isinstance(message, cls):
        raise CodecError(f"expected a {cls.KIND} message, got {message.KIND}")
    return message


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err.get("loc", ())) or "<root>"
    return f"{where}: {err.get('msg')} ({exc.error_count()} error(s))"
