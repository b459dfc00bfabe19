"""Soak a SLAM service: feed one camera a short sequence over and over, sample the service's RSS.

The sequence is played forwards then backwards (ping-pong: 0..n-1, n-2..1, 0..), so the camera
moves continuously and the VO keeps tracking across the seams, while frame indices and
timestamps keep increasing. Frames go out with back-pressure (at most ``max_in_flight`` without a
pose), as fast as the service takes them. Used by ``bench/slam_service_soak.py`` and
``tests/test_slam_service_soak.py``.

Example::

    session = open_client("tcp/127.0.0.1:7447")
    result = soak(session, "runs/synth_loop", "soak0", frames=1000, service_pid=pid)
    print(result["samples"][-1], growth_mib_per_1000_frames(result["samples"], after_frame=200))
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import zenoh

from metricslam.datasets import open_sequence
from metricslam.errors import ServiceError
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, describe_counters

FRAME_PERIOD_NS = 100_000_000  # timestamps as from a 10 Hz camera


def proc_status_value(pid: int, name: str) -> int:
    """The number on line ``name`` of Linux ``/proc/<pid>/status`` (e.g. ``VmRSS`` in KiB,
    ``Threads``)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{name}:"):
                return int(line.split()[1])
    except OSError as exc:
        raise ServiceError(f"cannot read the status of process {pid}: {exc}") from None
    raise ServiceError(f"/proc/{pid}/status has no {name} line")


def rss_mib(pid: int) -> float:
    """Resident set size of process ``pid`` in MiB (Linux ``/proc/<pid>/status``)."""
    return proc_status_value(pid, "VmRSS") / 1024.0


def ping_pong(n: int) -> Iterator[int]:
    """0, 1, .., n-1, n-2, .., 1, 0, 1, .. forever (n >= 2)."""
    period = list(range(n)) + list(range(n - 2, 0, -1))
    while True:
        yield from period


def soak(session: zenoh.Session, seq_dir: str | Path, camera_id: str, frames: int, service_pid: int,
         sample_every: int = 50, max_in_flight: int = 2, pose_timeout_s: float = 30.0) -> dict:
    """Publish ``frames`` frames of the looped sequence ``seq_dir`` as ``camera_id``.

    Returns:
        ``{"frames", "poses", "samples": [(frame, rss_mib), ...], "events": [status events],
        "tracking": fraction of poses in state tracking, "wall_s", "last_status"}``.
    """
    seq = open_sequence(seq_dir)
    if len(seq) < 2:
        raise ServiceError(f"{seq_dir} has {len(seq)} frame(s); a soak needs at least 2")
    images = [seq[i] for i in range(len(seq))]
    recorder = PoseRecorder(session, camera_id)
    publisher = FramePublisher(session, camera_id)
    samples: list[tuple[int, float]] = []
    order = ping_pong(len(images))
    t0 = time.monotonic()
    try:
        if not publisher.wait_for_subscriber(pose_timeout_s):
            raise ServiceError(f"no SLAM service subscribed to {camera_id}'s frames within "
                               f"{pose_timeout_s:.0f} s")
        for k in range(frames):
            _wait_poses(recorder, k - max_in_flight + 1, pose_timeout_s)
            frame = images[next(order)]
            publisher.publish(k, k * FRAME_PERIOD_NS, frame.image, frame.camera)
            if k % sample_every == 0:
                samples.append((k, round(rss_mib(service_pid), 1)))
        _wait_poses(recorder, frames, pose_timeout_s)
        samples.append((frames, round(rss_mib(service_pid), 1)))
        states = [p.state.value for p in recorder.poses.values()]
        status = recorder.latest_status()
        return {"frames": frames, "poses": len(recorder.poses), "samples": samples,
                "events": [(s.event, s.event_detail) for s in recorder.statuses if s.event],
                "tracking": states.count("tracking") / max(len(states), 1),
                "wall_s": round(time.monotonic() - t0, 1),
                "last_status": None if status is None else status.model_dump(mode="json")}
    finally:
        publisher.close()
        recorder.close()


def _wait_poses(recorder: PoseRecorder, n_frames: int, timeout_s: float) -> None:
    """Lock step: poses of frames ``0..n_frames-1`` have arrived, or the soak stops with the reason
    (a lost frame would otherwise cost ``timeout_s`` on every frame after it)."""
    if recorder.wait_frames(n_frames, timeout_s):
        return
    missing = sorted(set(range(n_frames)) - recorder.received_frames())
    status = recorder.latest_status()
    counts = "no status yet" if status is None else f"status: {describe_counters(status)}"
    raise ServiceError(f"no pose for {len(missing)} of the first {n_frames} frames after "
                       f"{timeout_s:.0f} s (frames {missing[:10]}); {counts}")


def growth_mib_per_1000_frames(samples: list[tuple[int, float]], after_frame: int = 0) -> float:
    """Least-squares slope of RSS over frames (MiB per 1000 frames), from ``after_frame`` on."""
    pts = np.array([(f, r) for f, r in samples if f >= after_frame], dtype=float)
    if len(pts) < 2:
        return float("nan")
    return float(np.polyfit(pts[:, 0], pts[:, 1], 1)[0] * 1000.0)
