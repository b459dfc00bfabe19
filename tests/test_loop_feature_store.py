"""The loop database's verification features on disk (:mod:`metricslam.slam.loop.feature_store`):
lossless round trips, forgetting, a failing write kept in RAM, and what stays resident."""

from __future__ import annotations

import os
import sqlite3

import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.slam.loop.corners import CornerFeatures, PackedCorners
from metricslam.slam.loop.feature_store import FeatureStore
from metricslam.slam.loop.verification import LandmarkFeatures
from metricslam_slam.service.memory import release_memory
from metricslam_slam.tools.soak import rss_mib

CAMERA = PinholeCamera(fx_px=700.0, fy_px=700.0, cx_px=610.0, cy_px=180.0, width_px=1226, height_px=370)


def _corners(rng: np.random.Generator, n: int, with_geo: bool) -> PackedCorners:
    uv = rng.uniform([0, 0], [1225, 369], (n, 2)).astype(np.float32).astype(np.float64)
    z = rng.uniform(2.0, 50.0, n)
    z[rng.random(n) < 0.1] = np.nan  # corners without network depth
    geo = None
    if with_geo:
        geo = np.full((n, 3), np.nan)
        some = rng.random(n) < 0.07
        geo[some] = rng.normal(size=(int(some.sum()), 3))
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    return PackedCorners.pack(CornerFeatures(uv, desc, CAMERA.unproject(uv, z), geo), CAMERA)


def _landmarks(rng: np.random.Generator, k: int, exact: bool) -> LandmarkFeatures:
    return LandmarkFeatures(rng.uniform(0, 300, (k, 2)), rng.normal(size=(k, 3)),
                            rng.integers(0, 256, (k, 32), dtype=np.uint8),
                            (rng.random(k) < 0.5) if exact else None)


def _equal(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, tuple):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize("on_disk", [True, False])
def test_features_come_back_equal_and_are_forgotten(on_disk: bool) -> None:
    rng = np.random.default_rng(0)
    store = FeatureStore(on_disk=on_disk)
    items = {k: (_landmarks(rng, 40 + k, exact=k % 2 == 0), _corners(rng, 900, with_geo=k % 3 != 0) if k != 4 else None)
             for k in range(6)}
    for k, (lm, c) in items.items():
        store.put(k, lm, c)
    assert len(store) == 6 and 3 in store and store.n_kept_in_memory == 0
    for k, (lm, c) in items.items():
        back = store.landmarks(k)
        assert all(_equal(getattr(lm, f), getattr(back, f)) for f in ("uv_px", "points", "descriptors", "exact"))
        if c is None:
            assert store.corners(k) is None and store.n_with_depth(k) is None
            continue
        got = store.corners(k)
        assert store.n_with_depth(k) == c.n_with_depth == got.n_with_depth and got.n_corners == c.n_corners
        assert got.camera is c.camera
        for f in ("uv_px", "descriptors", "points", "points_geo"):
            assert _equal(getattr(c, f), getattr(got, f)), f
        assert all(_equal(getattr(c.unpack(), f), getattr(got.unpack(), f))
                   for f in ("uv_px", "descriptors", "points", "points_geo"))
    store.forget(2)
    store.forget(99)  # unknown: no-op
    assert 2 not in store and store.landmarks(2) is None and store.corners(2) is None and len(store) == 5
    store.close()
    assert len(store) == 0 and store.landmarks(0) is None


class _FullDisk:
    """Stands in for the SQLite connection of a store whose temporary directory is full."""

    def execute(self, *args):
        raise sqlite3.OperationalError("database or disk is full")

    def close(self) -> None:
        pass


def test_a_failing_write_keeps_the_features_in_ram_and_counts_it(caplog) -> None:
    rng = np.random.default_rng(1)
    store = FeatureStore()
    store._db = _FullDisk()
    lm, c = _landmarks(rng, 30, exact=True), _corners(rng, 500, with_geo=True)
    store.put(7, lm, c)
    store.put(8, lm, None)
    assert store.n_kept_in_memory == 2 and store.landmarks(7) is lm and store.corners(7) is c
    assert store.corners(8) is None and store.n_read_errors == 0
    assert "keeping them in RAM" in caplog.text and "TMPDIR" in caplog.text
    store.forget(7)
    assert 7 not in store


def _rss_mib() -> float:
    release_memory()  # collect and malloc_trim, so RSS counts what is held
    return rss_mib(os.getpid())


def test_on_disk_the_features_are_not_resident() -> None:
    """~40 MiB of corners (900 a keyframe, 900 keyframes) leave resident only SQLite's small page
    cache; the same in RAM would add the full 40 MiB."""
    rng = np.random.default_rng(2)
    entries = [(_landmarks(rng, 60, exact=True), _corners(rng, 900, with_geo=True)) for _ in range(8)]
    payload_mib = 900 * sum(c.nbytes for _, c in entries) / len(entries) / 2**20
    assert payload_mib > 35
    store = FeatureStore()
    before = _rss_mib()
    for k in range(900):
        store.put(k, *entries[k % len(entries)])
    grown = _rss_mib() - before
    assert grown < 8, f"{grown:.1f} MiB resident for {payload_mib:.0f} MiB of features"
    assert store.n_kept_in_memory == 0
    assert _equal(store.corners(899).descriptors, entries[899 % len(entries)][1].descriptors)
    store.close()


def test_packed_arrays_keep_dtype_shape_and_values_including_empty_ones() -> None:
    from metricslam.slam.loop.feature_store import pack_arrays, unpack_arrays

    arrays = {"empty": np.zeros((0, 32), np.uint8), "flags": np.array([True, False, True]),
              "scalar": np.array(7, np.int64), "nan": np.array([[np.nan, 1.5, -np.inf]], np.float64),
              "f32": np.arange(6, dtype=np.float32).reshape(3, 2)[:, ::-1], "gone": None}
    back = unpack_arrays(pack_arrays(arrays))
    assert set(back) == set(arrays) - {"gone"}
    for name, value in back.items():
        assert _equal(arrays[name], value), name
        assert value.flags.writeable and value.flags.c_contiguous


def test_the_detector_reports_the_store_degrading(synth_sequence) -> None:
    """A full temporary directory shows up in the back end's stats, not only in a log line."""
    from metricslam.datasets import open_sequence
    from metricslam.slam.graph.config import LoopConfig
    from metricslam.slam.loop import LoopDetector

    seq = open_sequence(synth_sequence(6))
    detector = LoopDetector(LoopConfig(vocabulary_train_keyframes=3, vocabulary_words=50, keyframe_stride=1))
    assert detector.store_counters == {"loop_features_in_ram": 0, "loop_feature_read_errors": 0}
    detector._store._db = _FullDisk()
    rng = np.random.default_rng(0)
    for k in range(3):
        frame = seq[k]
        uv = rng.uniform([0, 0], [frame.camera.width_px - 1, frame.camera.height_px - 1], (60, 2))
        detector.add_and_query(k, frame.image, frame.camera, uv, np.full(60, 0.1))
    assert detector.store_counters["loop_features_in_ram"] == 3
