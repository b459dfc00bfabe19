"""Test-only CDR reader and writer, written from the OMG XCDR1 rules with ``struct`` alone, so
the tests check ``rosbags``' encoder (and our decoders) against an independent implementation.

Rules used: a 4-byte encapsulation header (``00 01 00 00`` = CDR little-endian) then the fields
in declaration order; every primitive is aligned to its own size, counted from the byte after
the header; a string is a uint32 length (including the NUL), the bytes and a NUL; a sequence
is a uint32 count then its elements; fixed arrays have no count.
"""

from __future__ import annotations

import struct

import numpy as np

CDR_LE = b"\x00\x01\x00\x00"


class CdrReader:
    def __init__(self, data: bytes) -> None:
        assert data[:4] == CDR_LE, f"encapsulation {data[:4].hex()} is not CDR little-endian"
        self.buf, self.pos = data[4:], 0

    def _prim(self, fmt: str):
        size = struct.calcsize(fmt)
        self.pos += (-self.pos) % size
        (value,) = struct.unpack_from("<" + fmt, self.buf, self.pos)
        self.pos += size
        return value

    def i32(self) -> int:
        return self._prim("i")

    def u32(self) -> int:
        return self._prim("I")

    def u8(self) -> int:
        return self._prim("B")

    def f64(self) -> float:
        return self._prim("d")

    def f64s(self, n: int) -> np.ndarray:
        return np.array([self.f64() for _ in range(n)])

    def string(self) -> str:
        n = self.u32()
        raw = self.buf[self.pos:self.pos + n]
        assert n >= 1 and raw[-1:] == b"\x00", "string without its NUL"
        self.pos += n
        return raw[:-1].decode()

    def octets(self) -> bytes:
        n = self.u32()
        raw = bytes(self.buf[self.pos:self.pos + n])
        self.pos += n
        return raw

    def header(self) -> tuple[int, int, str]:
        return self.i32(), self.u32(), self.string()

    def pose(self) -> np.ndarray:
        """position (3) then quaternion x, y, z, w (4)."""
        return self.f64s(7)

    def done(self) -> None:
        assert self.pos <= len(self.buf) and len(self.buf) - self.pos < 8, \
            f"{len(self.buf) - self.pos} bytes left over"


class CdrWriter:
    def __init__(self) -> None:
        self.buf = bytearray()

    def _prim(self, fmt: str, value) -> "CdrWriter":
        size = struct.calcsize(fmt)
        self.buf += b"\x00" * ((-len(self.buf)) % size)
        self.buf += struct.pack("<" + fmt, value)
        return self

    def i32(self, v: int) -> "CdrWriter":
        return self._prim("i", v)

    def u32(self, v: int) -> "CdrWriter":
        return self._prim("I", v)

    def u8(self, v: int) -> "CdrWriter":
        return self._prim("B", v)

    def f64(self, v: float) -> "CdrWriter":
        return self._prim("d", v)

    def string(self, s: str) -> "CdrWriter":
        raw = s.encode() + b"\x00"
        self.u32(len(raw))
        self.buf += raw
        return self

    def octets(self, raw: bytes) -> "CdrWriter":
        self.u32(len(raw))
        self.buf += raw
        return self

    def header(self, sec: int, nanosec: int, frame_id: str) -> "CdrWriter":
        return self.i32(sec).u32(nanosec).string(frame_id)

    def bytes(self) -> bytes:
        return CDR_LE + bytes(self.buf)


def image_cdr(sec: int, nanosec: int, frame_id: str, h: int, w: int, encoding: str, step: int,
              data: bytes) -> bytes:
    """sensor_msgs/Image: header, height, width, encoding, is_bigendian (uint8), step, data."""
    return (CdrWriter().header(sec, nanosec, frame_id).u32(h).u32(w).string(encoding).u8(0)
            .u32(step).octets(data).bytes())


def camera_info_cdr(sec: int, nanosec: int, frame_id: str, h: int, w: int, K: np.ndarray,
                    d: list[float]) -> bytes:
    """sensor_msgs/CameraInfo: header, height, width, distortion_model, d (sequence), k[9], r[9],
    p[12], binning_x, binning_y, roi (x_offset, y_offset, height, width, do_rectify)."""
    wr = CdrWriter().header(sec, nanosec, frame_id).u32(h).u32(w).string("plumb_bob").u32(len(d))
    for v in d:
        wr.f64(v)
    for v in np.asarray(K, dtype=float).reshape(9):
        wr.f64(float(v))
    for v in np.eye(3).reshape(9):
        wr.f64(float(v))
    for v in np.hstack([np.asarray(K, dtype=float), np.zeros((3, 1))]).reshape(12):
        wr.f64(float(v))
    return wr.u32(0).u32(0).u32(0).u32(0).u32(0).u32(0).u8(0).bytes()
