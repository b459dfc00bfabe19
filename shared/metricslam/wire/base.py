"""The base every wire message builds on: :class:`Message` and the array field checks.

Every message module (``camera_messages``, ``map_messages``, ``odometry_message``) imports this
one and nothing else of the package's messages; :mod:`metricslam.wire.codec` imports all of them
and owns the byte layout. So the package's import graph has no cycle
(``tests/test_wire_import_graph.py``).
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, field_validator

from metricslam.errors import CodecError
from metricslam.wire.keys import check_camera_id

#: the frame a pose or point field is in: ``"world"`` the camera session's own world frame (its
#: first keyframe), ``"map"`` the saved map the SLAM service loaded, once the session relocalized
#: into it (``docs/maps.md``). A field named ``T_world_cam`` holds ``T_map_cam`` then.
FrameId = Literal["world", "map"]

#: the dtypes an array field may have on the wire, all little-endian
DTYPES = {"uint8": np.dtype("<u1"), "int64": np.dtype("<i8"), "float32": np.dtype("<f4"),
          "float64": np.dtype("<f8")}


class Message(BaseModel):
    """Base of all messages. Subclasses set ``KIND`` and list their array fields in ``ARRAYS``.

    A subclass goes on the wire once :data:`metricslam.wire.codec.MESSAGE_TYPES` lists it.
    """

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


def as_array(value: Any, dtype: str, name: str, shape: tuple[int | None, ...] | None = None) -> np.ndarray:
    """Check dtype (exact, one of :data:`DTYPES`) and shape (``None`` = any size) of an array field.

    A same-kind, same-size dtype of the other byte order is converted; anything else raises
    ``ValueError`` (pydantic turns it into a validation error, the codec into ``CodecError``).
    """
    if not isinstance(value, np.ndarray):
        raise ValueError(f"{name} must be a numpy array, got {type(value).__name__}")
    if value.dtype != DTYPES[dtype]:
        if value.dtype.kind == DTYPES[dtype].kind and value.dtype.itemsize == DTYPES[dtype].itemsize:
            value = value.astype(DTYPES[dtype])
        else:
            raise ValueError(f"{name} must have dtype {dtype}, got {value.dtype}")
    if shape is not None and (
        value.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, value.shape))
    ):
        raise ValueError(f"{name} must have shape {shape} (None = any), got {value.shape}")
    return value


def finite_pose(value: Any, name: str) -> np.ndarray:
    """Check a (4, 4) float64 homogeneous transform field: finite, last row ``[0, 0, 0, 1]``."""
    T = as_array(value, "float64", name, (4, 4))
    if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} must be a finite homogeneous 4x4 transform")
    return T
