"""Publish a :class:`metricslam.datasets.base.Sequence` as zenoh frames (``replay``, ``demo``)."""

from __future__ import annotations

import logging
import time

import zenoh

from metricslam.datasets.base import Sequence
from metricslam.datasets.frame_reader import FrameReader
from metricslam.errors import ConfigError, ServiceError
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, query_health

log = logging.getLogger(__name__)


def wait_for_service(session: zenoh.Session, timeout_s: float, endpoint: str = "") -> None:
    """Block until a SLAM service answers the health query (so no frame goes into the void)."""
    deadline = time.monotonic() + timeout_s
    while not query_health(session, timeout_s=1.0):
        if time.monotonic() > deadline:
            raise ServiceError(f"no SLAM service answered on {endpoint or 'the router'} within "
                               f"{timeout_s:.0f} s; start one with `metricslam up`")
        time.sleep(0.2)


def replay_sequence(session: zenoh.Session, seq: Sequence, camera_id: str = "cam0",
                    rate_hz: float = 10.0, start: int = 0, stop: int | None = None,
                    max_in_flight: int = 0, progress: bool = True) -> int:
    """Publish frames ``start..stop-1`` at ``rate_hz`` (0 = as fast as possible).

    ``max_in_flight > 0`` adds back-pressure: frame ``k`` goes out only once poses of all but
    ``max_in_flight`` of the frames published before it arrived; after one 10 s wait without
    progress back-pressure is switched off, so dropped frames or a dead service cannot stall the
    replay. A frame whose image cannot be read is logged and published black, which the SLAM
    service treats as an invalid frame. Returns the number of frames published.
    """
    from tqdm import tqdm

    stop = len(seq) if stop is None else min(stop, len(seq))
    if not 0 <= start < stop:
        raise ConfigError(f"frame range [{start}, {stop}) is empty or outside 0..{len(seq) - 1}")
    if rate_hz < 0:
        raise ConfigError(f"rate must be >= 0 Hz, got {rate_hz}")
    frames = FrameReader(seq)
    publisher = FramePublisher(session, camera_id, block=True)
    recorder = PoseRecorder(session, camera_id) if max_in_flight > 0 else None
    period_s = 0.0 if rate_hz == 0 else 1.0 / rate_hz
    t_start = time.monotonic()
    try:
        for k, i in enumerate(tqdm(range(start, stop), desc=f"replay {camera_id}", unit="frame",
                                   disable=not progress)):
            frame = frames[i]
            if period_s:
                delay = t_start + k * period_s - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if recorder is not None and not recorder.wait_for(
                    lambda r, k=k: sum(j >= start for j in r.poses) >= k - max_in_flight, timeout_s=10.0):
                log.warning("no poses for 10 s: back-pressure off for the rest of the replay")
                recorder.close()
                recorder = None
            publisher.publish(frame.index, frame.t_ns, frame.image, frame.camera)
    finally:
        publisher.close()
        if recorder is not None:
            recorder.close()
    return stop - start
