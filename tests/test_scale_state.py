"""Issue #19 item 1: every pose says what its scale rests on (unscaled / provisional / metric).

On the wire the state is an optional field of the pose message (a message from an older sender,
without it, still decodes and reads as ``scale_established``); ``metricslam poses`` records only
poses with a metric scale by default (TUM: the others left out; KITTI: a placeholder line each,
so the file still pairs with the ground truth line by line)."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from metricslam.errors import ServiceError
from metricslam.slam.types import ScaleState, TrackingState
from metricslam.trajectory.io import read_kitti_poses, read_tum
from metricslam.wire.codec import MAGIC, PoseMessage, decode, encode
from metricslam_slam.tools.recording import unscaled_frames, write_poses


def _pose(i: int, state: ScaleState | None, established: bool = False) -> PoseMessage:
    T = np.eye(4)
    T[2, 3] = float(i)
    return PoseMessage(camera_id="cam0", frame_index=i, t_ns=i * 100_000_000,
                       state=TrackingState.TRACKING, scale_established=established,
                       scale_state=state, scale_factors=None if state is None else 3 * i, T_world_cam=T)


def _without(payload: bytes, *fields: str) -> bytes:
    """``payload`` as an older sender would have written it: header body without ``fields``."""
    n = struct.unpack_from("<I", payload, 4)[0]
    header = json.loads(payload[8:8 + n])
    for name in fields:
        del header["body"][name]
    raw = json.dumps(header).encode()
    return MAGIC + struct.pack("<I", len(raw)) + raw + payload[8 + n:]


def test_scale_state_round_trips_and_old_messages_still_decode() -> None:
    msg = _pose(4, ScaleState.PROVISIONAL)
    back = decode(encode(msg))
    assert back.scale_state is ScaleState.PROVISIONAL and back.scale_factors == 12
    old = decode(_without(encode(_pose(4, ScaleState.METRIC, True)), "scale_state", "scale_factors"))
    assert old.scale_state is None and old.scale_factors is None
    assert old.effective_scale_state() is ScaleState.METRIC
    old_unscaled = decode(_without(encode(_pose(4, ScaleState.UNSCALED)), "scale_state", "scale_factors"))
    assert old_unscaled.effective_scale_state() is ScaleState.UNSCALED


def test_poses_skips_unscaled_frames(tmp_path) -> None:
    states = [ScaleState.UNSCALED, ScaleState.UNSCALED, ScaleState.PROVISIONAL, ScaleState.UNSCALED,
              ScaleState.METRIC, ScaleState.METRIC]
    poses = {i: _pose(i, s, s is ScaleState.METRIC) for i, s in enumerate(states)}
    skip = unscaled_frames(poses, None, len(states))
    assert skip == [0, 1, 3]

    n = write_poses(tmp_path / "est.tum", "tum", poses, None, len(states), skip)
    t_ns, T = read_tum(tmp_path / "est.tum")
    assert n == 3 and list(np.round(T[:, 2, 3])) == [2, 4, 5]

    n = write_poses(tmp_path / "est.txt", "kitti", poses, None, len(states), skip)
    z = read_kitti_poses(tmp_path / "est.txt")[:, 2, 3]
    assert n == 3 and list(np.round(z)) == [0, 0, 2, 2, 4, 5]  # origin, then the previous kept pose

    n = write_poses(tmp_path / "all.txt", "kitti", poses, None, len(states))
    assert n == 6 and list(np.round(read_kitti_poses(tmp_path / "all.txt")[:, 2, 3])) == list(range(6))


def test_poses_refuses_a_recording_without_any_scale(tmp_path) -> None:
    poses = {i: _pose(i, ScaleState.UNSCALED) for i in range(3)}
    with pytest.raises(ServiceError, match="all 3 poses are unscaled.*--all"):
        write_poses(tmp_path / "x.txt", "kitti", poses, None, 3, unscaled_frames(poses, None, 3))
    old = {i: decode(_without(encode(_pose(i, ScaleState.METRIC, True)), "scale_state", "scale_factors"))
           for i in range(3)}
    assert unscaled_frames(old, None, 3) == []


def test_poses_writes_what_arrived_when_frames_are_missing(tmp_path) -> None:
    """A lossy run (a fault mid-replay) keeps the poses that did arrive; the caller still fails."""
    poses = {i: _pose(i, ScaleState.METRIC, True) for i in (0, 1, 3, 4)}  # frame 2 never came
    with pytest.raises(ServiceError, match="1 of 5 frames have no pose"):
        write_poses(tmp_path / "strict.txt", "kitti", poses, None, 5)
    assert not (tmp_path / "strict.txt").exists()
    n = write_poses(tmp_path / "est.tum", "tum", poses, None, 5, missing_ok=True)
    assert n == 4 and list(np.round(read_tum(tmp_path / "est.tum")[1][:, 2, 3])) == [0, 1, 3, 4]
    n = write_poses(tmp_path / "est.txt", "kitti", poses, None, 5, missing_ok=True)
    assert n == 4 and list(np.round(read_kitti_poses(tmp_path / "est.txt")[:, 2, 3])) == [0, 1, 1, 3, 4]
    with pytest.raises(ServiceError, match="5 of 5 frames have no pose"):
        write_poses(tmp_path / "none.txt", "kitti", {}, None, 5, missing_ok=True)
