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
"""

from __future__ import annotations

import json
import math
import struct
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from metricslam.camera import PinholeCamera
from metricslam.errors import CodecError
from metricslam.slam.types import ScaleState, TrackingState
from metricslam.wire.keys import check_camera_id
from metricslam.wire.scale_status import ScaleHealthStatus

SCHEMA_VERSION = 1
MAGIC = b"MSLM"
MAX_HEADER_BYTES = 1 << 20
MAX_MESSAGE_BYTES = 256 << 20
_PREFIX = struct.Struct("<4sI")
_DTYPES = {"uint8": np.dtype("<u1"), "int64": np.dtype("<i8"), "float32": np.dtype("<f4"),
           "float64": np.dtype("<f8")}
#: tracking states as compact codes (index in this tuple) inside trajectory arrays.
STATE_CODES: tuple[TrackingState, ...] = tuple(TrackingState)


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


class Message(BaseModel):
    """Base of all messages. Subclasses set ``KIND`` and list their array fields in ``ARRAYS``."""

    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)
    KIND: ClassVar[str] = ""
    ARRAYS: ClassVar[tuple[str, ...]] = ()

    camera_id: str

    @field_validator("camera_id")
    @classmethod
    def _camera_id(cls, camera_id: str) -> str:
        try:
            return check_camera_id(camera_id)
        except CodecError as exc:
            raise ValueError(str(exc)) from None


def _as_array(value: Any, dtype: str, name: str, shape: tuple[int | None, ...] | None = None) -> np.ndarray:
    """Check dtype (exact) and shape (``None`` = any size) of an array field."""
    if not isinstance(value, np.ndarray):
        raise ValueError(f"{name} must be a numpy array, got {type(value).__name__}")
    if value.dtype != _DTYPES[dtype]:
        if value.dtype.kind == _DTYPES[dtype].kind and value.dtype.itemsize == _DTYPES[dtype].itemsize:
            value = value.astype(_DTYPES[dtype])
        else:
            raise ValueError(f"{name} must have dtype {dtype}, got {value.dtype}")
    if shape is not None and (
        value.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, value.shape))
    ):
        raise ValueError(f"{name} must have shape {shape} (None = any), got {value.shape}")
    return value


def _finite_pose(value: Any, name: str) -> np.ndarray:
    T = _as_array(value, "float64", name, (4, 4))
    if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} must be a finite homogeneous 4x4 transform")
    return T


class FrameMessage(Message):
    """One camera image with its intrinsics (``metricslam/<id>/frame``).

    ``image``: (H, W) uint8 gray or (H, W, 3) uint8 RGB, H x W = camera height x width.
    ``t_sent_ns``: sender's wall clock at publish time (ns), echoed in the pose for latency.
    """

    KIND: ClassVar[str] = "frame"
    ARRAYS: ClassVar[tuple[str, ...]] = ("image",)

    frame_index: int = Field(ge=0)
    t_ns: int = Field(ge=0)
    camera: PinholeCamera
    t_sent_ns: int | None = None
    image: np.ndarray

    @field_validator("image")
    @classmethod
    def _image(cls, image: Any) -> np.ndarray:
        image = _as_array(image, "uint8", "image")
        if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
            raise ValueError(f"image must be (H, W) or (H, W, 3) uint8, got shape {image.shape}")
        return image

    @model_validator(mode="after")
    def _image_matches_camera(self) -> "FrameMessage":
        h, w = self.image.shape[:2]
        if (w, h) != (self.camera.width_px, self.camera.height_px):
            raise ValueError(
                f"image is {w}x{h} but the camera says {self.camera.width_px}x{self.camera.height_px}"
            )
        return self


class CalibrationMessage(Message):
    """A camera's intrinsics (``metricslam/<id>/calibration``); frames carry them as well."""

    KIND: ClassVar[str] = "calibration"

    camera: PinholeCamera
    baseline_m: float | None = Field(default=None, gt=0)


class PoseMessage(Message):
    """The pose of one input frame (``metricslam/<id>/pose``), published for every frame.

    ``T_world_cam``: (4, 4) float64 camera-to-world, metres once ``scale_established``.
    ``processing_ms``: service time from frame receipt to this publish.
    ``scale_state``: what the pose's scale rests on (``unscaled`` / ``provisional`` / ``metric``,
    :class:`~metricslam.slam.types.ScaleState`) and ``scale_factors`` the learned scale
    measurements behind it; both optional (None from senders that predate them: then read
    ``scale_established`` alone, :meth:`effective_scale_state`).
    """

    KIND: ClassVar[str] = "pose"
    ARRAYS: ClassVar[tuple[str, ...]] = ("T_world_cam",)

    frame_index: int = Field(ge=0)
    t_ns: int = Field(ge=0)
    state: TrackingState
    is_keyframe: bool = False
    segment_id: int = Field(default=0, ge=0)
    scale_established: bool = False
    processing_ms: float = Field(default=0.0, ge=0)
    t_sent_ns: int | None = None
    scale_state: ScaleState | None = None
    scale_factors: int | None = Field(default=None, ge=0)
    T_world_cam: np.ndarray

    @field_validator("T_world_cam")
    @classmethod
    def _pose(cls, T: Any) -> np.ndarray:
        return _finite_pose(T, "T_world_cam")

    def effective_scale_state(self) -> ScaleState:
        """``scale_state``, or for an older sender ``metric`` if ``scale_established`` else
        ``unscaled`` (it had no provisional scale)."""
        if self.scale_state is not None:
            return self.scale_state
        return ScaleState.METRIC if self.scale_established else ScaleState.UNSCALED


class KeyframeMessage(Message):
    """A new keyframe (``metricslam/<id>/keyframe``): its pose and, optionally, its image."""

    KIND: ClassVar[str] = "keyframe"
    ARRAYS: ClassVar[tuple[str, ...]] = ("T_world_cam", "image")

    frame_index: int = Field(ge=0)
    t_ns: int = Field(ge=0)
    segment_id: int = Field(default=0, ge=0)
    scale_established: bool = False
    T_world_cam: np.ndarray
    image: np.ndarray | None = None

    @field_validator("T_world_cam")
    @classmethod
    def _pose(cls, T: Any) -> np.ndarray:
        return _finite_pose(T, "T_world_cam")

    @field_validator("image")
    @classmethod
    def _image(cls, image: Any) -> np.ndarray | None:
        return None if image is None else FrameMessage._image(image)


class StatusMessage(Message):
    """Health of one camera's SLAM session (``metricslam/<id>/status``), published periodically.

    ``depth_reachable``: None until the depth service was tried (or when scale is off); False
    means keyframes get NO learned scale factors until it answers (``depth_error`` says why).
    ``depth_outages``: times the depth service became unreachable since the service started.
    ``scale_state``: the latest pose's (optional; ``unscaled`` while no depth source answers).
    ``latency_ms_*``: frame receipt -> pose publish inside the service, over a recent window.
    ``event`` / ``event_detail``: set on one-off statuses about the camera's session
    (refused, closed, restarted or rolled over; docs/deployment.md "Bounds and state").
    ``scale_health``: scale sources, mounting height, scale σ, health (optional; :mod:`~metricslam.wire.scale_status`).
    """

    KIND: ClassVar[str] = "status"

    t_ns: int = Field(ge=0)
    frames_received: int = Field(ge=0)
    frames_processed: int = Field(ge=0)
    queue_drops: int = Field(ge=0)
    malformed: int = Field(ge=0)
    queue_depth: int = Field(ge=0)
    fps: float = Field(ge=0)
    latency_ms_p50: float | None = None
    latency_ms_p99: float | None = None
    tracking_state: TrackingState | None = None
    scale_established: bool = False
    keyframes: int = Field(default=0, ge=0)
    depth_url: str | None = None
    depth_reachable: bool | None = None
    depth_error: str | None = None
    depth_outages: int = Field(default=0, ge=0)
    scale_state: ScaleState | None = None
    session_stats: dict[str, float | int | str | bool | None] = Field(default_factory=dict)
    event: Literal["camera_refused", "camera_closed", "session_restarted", "session_rolled_over"] | None = None
    event_detail: str | None = Field(default=None, max_length=1000)
    scale_health: ScaleHealthStatus | None = None


class TrajectoryMessage(Message):
    """The whole current (optimized) trajectory of a camera, answer of ``…/trajectory``.

    ``frame_index`` (N,) int64, ``t_ns`` (N,) int64, ``T_world_cam`` (N, 4, 4) float64,
    ``state_code`` (N,) uint8 index into :data:`STATE_CODES`.
    """

    KIND: ClassVar[str] = "trajectory"
    ARRAYS: ClassVar[tuple[str, ...]] = ("frame_index", "t_ns", "T_world_cam", "state_code")

    scale_established: bool = False
    frame_index: np.ndarray
    t_ns: np.ndarray
    T_world_cam: np.ndarray
    state_code: np.ndarray

    @model_validator(mode="after")
    def _consistent(self) -> "TrajectoryMessage":
        n = len(self.frame_index) if isinstance(self.frame_index, np.ndarray) and self.frame_index.ndim == 1 else -1
        object.__setattr__(self, "frame_index", _as_array(self.frame_index, "int64", "frame_index", (None,)))
        object.__setattr__(self, "t_ns", _as_array(self.t_ns, "int64", "t_ns", (n,)))
        object.__setattr__(self, "T_world_cam", _as_array(self.T_world_cam, "float64", "T_world_cam", (n, 4, 4)))
        codes = _as_array(self.state_code, "uint8", "state_code", (n,))
        if np.any(codes >= len(STATE_CODES)):
            raise ValueError(f"state_code values must be < {len(STATE_CODES)}")
        object.__setattr__(self, "state_code", codes)
        return self

    @property
    def states(self) -> list[TrackingState]:
        return [STATE_CODES[c] for c in self.state_code]

    @staticmethod
    def state_codes(states: list[TrackingState]) -> np.ndarray:
        return np.array([STATE_CODES.index(TrackingState(s)) for s in states], dtype=np.uint8)


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.KIND: cls for cls in (FrameMessage, CalibrationMessage, PoseMessage, KeyframeMessage,
                              StatusMessage, TrajectoryMessage)
}
# map messages live in their own module (it builds on Message, so it is imported here, last)
from metricslam.wire.map_messages import KeyframeDepthMessage, LandmarksMessage  # noqa: E402

from metricslam.wire.odometry_message import OdometryMessage  # noqa: E402

MESSAGE_TYPES.update({cls.KIND: cls for cls in (LandmarksMessage, KeyframeDepthMessage, OdometryMessage)})


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
