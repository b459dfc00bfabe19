"""Bounded sessions of the real SLAM service (child process): the soak helpers, the loop
database's cap, and session roll-over on a rendered 100-frame loop played back and forth. How far
memory stays flat over long soaks is measured by ``bench/slam_service_soak.py``
(``bench/results/slam_service_soak.md``), not asserted here."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.loop.vocabulary import BowDatabase
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import query_health
from metricslam_slam.tools.soak import growth_mib_per_1000_frames, ping_pong, soak
from metricslam_slam.zenoh_config import open_client

ENDPOINT = "tcp/127.0.0.1:17661"


def test_ping_pong_and_growth_helpers() -> None:
    it = ping_pong(4)
    assert [next(it) for _ in range(10)] == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3]
    assert growth_mib_per_1000_frames([(0, 100.0), (500, 105.0), (1000, 110.0)]) == pytest.approx(10.0)


def test_bow_database_forgets_its_oldest_rows() -> None:
    db = BowDatabase(3)
    for k in range(70):  # past the first capacity doubling
        db.add(k, [k, 1.0, 0.0])
    assert db.forget_oldest() == 0 and len(db) == 69 and db.row(0)[0] == 1.0
    ids, scores = db.scores([1.0, 0.0, 0.0], upto=69)
    assert ids[0] == 1 and scores[-1] == 69.0
    assert LoopConfig().max_database_keyframes == 1000


def test_loop_database_keeps_the_newest_keyframes(synth_sequence) -> None:
    from metricslam.datasets import open_sequence
    from metricslam.slam.loop import LoopDetector

    seq = open_sequence(synth_sequence(30))
    config = LoopConfig(max_database_keyframes=5, vocabulary_train_keyframes=3, vocabulary_words=50,
                        keyframe_stride=1, skip_recent_keyframes=2, min_keyframes_between_loops=0)
    detector = LoopDetector(config)
    rng = np.random.default_rng(0)
    for k in range(30):
        frame = seq[k]
        uv = rng.uniform([0, 0], [frame.camera.width_px - 1, frame.camera.height_px - 1], (60, 2))
        detector.add_and_query(k, frame.image, frame.camera, uv, np.full(60, 0.1))
        assert len(detector._store) <= 5
        assert detector._db is None or len(detector._db) == len(detector._order) <= 5
    assert detector._order == list(range(25, 30))


def _array_bytes(value) -> int:
    """Bytes of the numpy arrays in ``value`` (dataclass fields, tuples, nested)."""
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, (tuple, list)):
        return sum(_array_bytes(v) for v in value)
    if hasattr(value, "__dataclass_fields__"):
        return sum(_array_bytes(getattr(value, f)) for f in value.__dataclass_fields__)
    return 0


def test_loop_database_entries_are_packed_losslessly(synth_sequence) -> None:
    """The database's largest per-keyframe item, every indexed keyframe's ~1000 corners, is held
    in at most 56 bytes a corner (unpacked: 96 — pixels float64 16, descriptor 32, network point
    24, triangulated point 24 though most corners have none; packed, the network point is its
    depth, 8), on disk (``features_on_disk``), and comes back from there bit for bit as what verification
    used (rendered depth as the network's map, the true motion as the VO's)."""
    from metricslam.datasets import open_sequence
    from metricslam.geometry import se3
    from metricslam.slam.loop import LoopDetector
    from metricslam.slam.loop.corners import CornerFeatures

    seq = open_sequence(synth_sequence(30))
    detector = LoopDetector(LoopConfig(vocabulary_train_keyframes=3, vocabulary_words=50, keyframe_stride=1,
                                         features_on_disk=True))
    made: dict[int, CornerFeatures] = {}
    corner_features = detector._corner_features

    def recording(*args, **kwargs) -> CornerFeatures:
        made[len(made)] = features = corner_features(*args, **kwargs)
        return features

    detector._corner_features = recording
    rng = np.random.default_rng(0)
    prev_T = None
    for k in range(0, 30, 2):
        frame = seq[k]
        inv_depth = np.where(frame.depth_m > 0, 1.0 / np.maximum(frame.depth_m, 1e-6), 0.0).astype(np.float32)
        uv = rng.uniform([0, 0], [frame.camera.width_px - 1, frame.camera.height_px - 1], (60, 2))
        xi = 2.0 * inv_depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]  # 0.5 m per VO unit
        T_prev_k = None if prev_T is None else se3.inverse(prev_T) @ frame.T_world_cam
        if T_prev_k is not None:
            T_prev_k[:3, 3] *= 2.0  # in VO units
        detector.add_and_query(k, frame.image, frame.camera, uv, xi, inv_depth_map=inv_depth, T_prevkf_kf=T_prev_k)
        prev_T = frame.T_world_cam
    assert len(detector._store) == len(made) == 15
    assert detector._store.n_kept_in_memory == 0  # all on disk, read back below
    entries = {kf_id: detector._store.corners(kf_id) for kf_id in detector._order}
    n_corners = sum(len(f.uv_px) for f in made.values())
    assert n_corners > 15 * 500
    assert sum(f.n_with_depth for f in made.values()) > n_corners / 2  # network points for most corners
    assert any(np.isfinite(f.points_geo).all(axis=1).any() for f in made.values())  # some triangulated
    stored = sum(_array_bytes(entry) for entry in entries.values())
    assert stored <= 56 * n_corners, f"{stored / n_corners:.1f} bytes per corner"
    assert all(entry.camera is not None for entry in entries.values())  # network points as depth
    for kf_id, features in zip(detector._order, made.values()):
        entry = entries[kf_id]
        assert entry.n_with_depth == features.n_with_depth
        back = entry.unpack()
        for name in ("uv_px", "descriptors", "points", "points_geo"):
            a, b = getattr(features, name), getattr(back, name)
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name


def test_a_long_session_rolls_over_into_linked_sessions(synth_sequence) -> None:
    """With a small keyframe cap the service closes the session and carries the camera on in a
    new linked one, again and again, without losing poses. (The memory figures of a long soak are
    a benchmark, not a test: ``bench/slam_service_soak.py``.)"""
    seq = synth_sequence(100)
    router = open_router(ENDPOINT)
    client = open_client(ENDPOINT)
    env = {**os.environ, "SLAM_MAX_SESSION_KEYFRAMES": "15", "METRICSLAM_GRAPH__LOOP__MAX_DATABASE_KEYFRAMES": "10"}
    proc = subprocess.Popen([sys.executable, "-m", "metricslam_cli.main", "slam-service", "--zenoh-endpoint",
                             ENDPOINT, "--depth-url", "none", "--preset", "synth", "--status-period", "1"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(120):
            if query_health(client, 1.0) is not None:
                break
            assert proc.poll() is None, "the SLAM service exited"
        result = soak(client, seq, "soak0", 200, proc.pid)
    finally:
        proc.terminate()
        proc.wait(60)
        client.close()
        router.close()
    assert result["poses"] == 200 and result["tracking"] > 0.9
    assert sum(e == "session_rolled_over" for e, _ in result["events"]) >= 2, result["events"]


def test_the_service_caps_glibc_malloc_arenas_unless_told_not_to() -> None:
    """``SLAM_MALLOC_ARENAS`` (default 2) reaches ``mallopt(M_ARENA_MAX)``; 0 leaves glibc alone."""
    import ctypes.util

    from metricslam_slam.service.memory import limit_malloc_arenas
    from metricslam_slam.service.settings import SlamServiceSettings

    assert SlamServiceSettings().malloc_arenas == 2
    assert SlamServiceSettings(malloc_arenas=0).malloc_arenas == 0
    assert limit_malloc_arenas(0) is False
    if not (ctypes.util.find_library("c") or "").startswith("libc.so"):
        pytest.skip("not glibc: there is no arena cap to set")
    assert limit_malloc_arenas(8) is True  # this test process: glibc's own default count per core is larger
