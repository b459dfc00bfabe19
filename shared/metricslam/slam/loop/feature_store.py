"""``FeatureStore``: the place-recognition database's per-keyframe verification features, held in
a private temporary SQLite database on disk (or in RAM).

Retrieval needs only each indexed keyframe's bag-of-words row. Its verification features — the
packed ORB corners with their depths (:class:`~metricslam.slam.loop.corners.PackedCorners`, at
most 56 bytes a corner, ~1,000 corners) and the landmark features
(:class:`~metricslam.slam.loop.verification.LandmarkFeatures`) — are read only when the keyframe
is one of a query's few retrieval candidates. On disk they cost a 1000-keyframe session no
resident memory beyond SQLite's page cache (``cache_kib``) and a few small values per keyframe
(ids, corner counts, a reference to the intrinsics).

SQLite's private temporary database (filename ``""``) lives in ``SQLITE_TMPDIR``/``TMPDIR``
(else ``/var/tmp``, ``/usr/tmp``, ``/tmp``); SQLite removes the file as it opens it, so nothing is
left behind by a crash, and forgotten entries' pages are reused. An entry's arrays are one blob
(:func:`pack_arrays`: a JSON header of names, dtypes and shapes, then the raw bytes) and come back
equal (lossless; dtypes kept). Most reads are candidates that do not verify, so decoding has to be
cheap: with ``.npz`` (Python's ``zipfile``, holding the GIL the VO thread needs) the store
slowed a 2,700-frame run with loops (``docs/history/rule_loop_spill_session12b.md``). A write that
fails (full or read-only temporary directory) keeps that entry in RAM and counts it
(``n_kept_in_memory``): no loop candidate is lost; a read that fails is counted
(``n_read_errors``) and the candidate is skipped for that query. The loop detector reports both
in the back end's stats.
"""

from __future__ import annotations

import json
import logging
import sqlite3

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.slam.loop.corners import PackedCorners
from metricslam.slam.loop.verification import LandmarkFeatures

log = logging.getLogger(__name__)

#: SQLite page cache of the store (KiB): what stays resident however many keyframes it holds.
DEFAULT_CACHE_KIB = 512


def pack_arrays(arrays: dict[str, np.ndarray | None]) -> bytes:
    """Numeric arrays (None values left out) as one blob: the header's length (4 bytes, little
    endian), a JSON header ``[[name, dtype, shape], ...]``, then each array's bytes in C order."""
    present = [(k, np.asarray(v, order="C")) for k, v in arrays.items() if v is not None]
    header = json.dumps([[k, v.dtype.str, list(v.shape)] for k, v in present]).encode()
    return b"".join([len(header).to_bytes(4, "little"), header, *(v.tobytes() for _, v in present)])


def unpack_arrays(blob: bytes) -> dict[str, np.ndarray]:
    """The arrays of :func:`pack_arrays` (writable copies, equal dtypes and shapes)."""
    n = int.from_bytes(blob[:4], "little")
    out, offset = {}, 4 + n
    for name, dtype, shape in json.loads(blob[4:offset]):
        dt = np.dtype(dtype)
        count = int(np.prod(shape, dtype=np.int64))
        out[name] = np.frombuffer(blob, dt, count, offset).reshape(tuple(shape)).copy()
        offset += count * dt.itemsize
    return out


def _landmarks_arrays(f: LandmarkFeatures) -> dict[str, np.ndarray | None]:
    return {"uv_px": f.uv_px, "points": f.points, "descriptors": f.descriptors, "exact": f.exact}


def _landmarks_from(a: dict[str, np.ndarray]) -> LandmarkFeatures:
    return LandmarkFeatures(a["uv_px"], a["points"], a["descriptors"], a.get("exact"))


def _corners_arrays(c: PackedCorners) -> dict[str, np.ndarray | None]:
    geo = c.points_geo
    return {"n": np.array([c.n_corners, c.n_with_depth], np.int64), "uv_px": c.uv_px,
            "descriptors": c.descriptors, "rows": c.points[0], "values": c.points[1],
            "geo_rows": None if geo is None else geo[0], "geo_values": None if geo is None else geo[1]}


def _corners_from(a: dict[str, np.ndarray], camera: PinholeCamera | None) -> PackedCorners:
    geo = (a.get("geo_rows"), a["geo_values"]) if "geo_values" in a else None
    return PackedCorners(int(a["n"][0]), int(a["n"][1]), a["uv_px"], a["descriptors"],
                         (a.get("rows"), a["values"]), geo, camera)


class FeatureStore:
    """Verification features by keyframe id (see module docstring). Not thread-safe: one thread
    uses it at a time (the loop detector's)."""

    def __init__(self, on_disk: bool = True, cache_kib: int = DEFAULT_CACHE_KIB) -> None:
        self._db: sqlite3.Connection | None = None
        if on_disk:
            self._db = sqlite3.connect("", check_same_thread=False, isolation_level=None)
            self._db.execute(f"PRAGMA cache_size=-{int(cache_kib)}")
            self._db.execute("PRAGMA journal_mode=OFF")
            self._db.execute("CREATE TABLE f (kf_id INTEGER PRIMARY KEY, landmarks BLOB, corners BLOB)")
        # kf_id -> (n corners with depth or None: no corners, the corners' camera or None)
        self._meta: dict[int, tuple[int | None, PinholeCamera | None]] = {}
        self._ram: dict[int, tuple[LandmarkFeatures, PackedCorners | None]] = {}
        self.n_kept_in_memory = 0
        self.n_read_errors = 0

    def __len__(self) -> int:
        return len(self._meta)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._meta

    def put(self, kf_id: int, landmarks: LandmarkFeatures, corners: PackedCorners | None) -> None:
        """Hold keyframe ``kf_id``'s landmark features and packed corners (None: none)."""
        self._meta[kf_id] = (None, None) if corners is None else (corners.n_with_depth, corners.camera)
        if self._db is not None:
            try:
                self._db.execute("INSERT OR REPLACE INTO f VALUES (?, ?, ?)", (
                    kf_id, pack_arrays(_landmarks_arrays(landmarks)),
                    None if corners is None else pack_arrays(_corners_arrays(corners))))
                return
            except sqlite3.Error as exc:
                if not self.n_kept_in_memory:
                    log.warning("loop database: cannot write keyframe features to the temporary "
                                "SQLite file (%s); keeping them in RAM (check TMPDIR's free space)", exc)
                self.n_kept_in_memory += 1
        self._ram[kf_id] = (landmarks, corners)

    def n_with_depth(self, kf_id: int) -> int | None:
        """Corners with depth of ``kf_id`` (None: no corners or unknown id), without reading them."""
        return self._meta.get(kf_id, (None, None))[0]

    def landmarks(self, kf_id: int) -> LandmarkFeatures | None:
        """The landmark features of ``kf_id`` (None: unknown id or unreadable)."""
        if kf_id in self._ram:
            return self._ram[kf_id][0]
        blob = self._read(kf_id, "landmarks")
        return None if blob is None else _landmarks_from(unpack_arrays(blob))

    def corners(self, kf_id: int) -> PackedCorners | None:
        """The packed corners of ``kf_id`` (None: none, unknown id or unreadable)."""
        if kf_id in self._ram:
            return self._ram[kf_id][1]
        blob = self._read(kf_id, "corners")
        return None if blob is None else _corners_from(unpack_arrays(blob), self._meta[kf_id][1])

    def forget(self, kf_id: int) -> None:
        """Drop ``kf_id`` (no-op when unknown)."""
        if self._meta.pop(kf_id, None) is None:
            return
        if self._ram.pop(kf_id, None) is None and self._db is not None:
            try:
                self._db.execute("DELETE FROM f WHERE kf_id = ?", (kf_id,))
            except sqlite3.Error as exc:  # the row stays in the file; nothing reads it again
                log.debug("loop database: delete of keyframe %d failed: %s", kf_id, exc)

    def close(self) -> None:
        """Close the temporary database (SQLite removes it); the store is empty afterwards."""
        if self._db is not None:
            self._db.close()
            self._db = None
        self._meta.clear()
        self._ram.clear()

    def _read(self, kf_id: int, column: str) -> bytes | None:
        if kf_id not in self._meta or self._db is None:
            return None
        try:
            row = self._db.execute(f"SELECT {column} FROM f WHERE kf_id = ?", (kf_id,)).fetchone()
        except sqlite3.Error as exc:
            self.n_read_errors += 1
            log.warning("loop database: cannot read keyframe %d's features (%s); candidate skipped",
                        kf_id, exc)
            return None
        return None if row is None or row[0] is None else row[0]
