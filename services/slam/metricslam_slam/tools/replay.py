"""Publish a :class:`metricslam.datasets.base.Sequence` as zenoh frames (``replay``, ``demo``)
and count what the SLAM service confirmed.

The service acknowledges a frame by publishing its pose (``…/pose``, one per processed frame,
invalid ones included); a frame it dropped (full queue), could not decode, or never received gets
none. :func:`replay_sequence` subscribes to the poses before the first frame goes out and, after
the last, waits until every published frame has its pose or none arrived for
``confirm_timeout_s``; its :class:`ReplayReport` says how many were confirmed and, from the
service's ``…/status``, why the others were not: a service that restarted meanwhile (its health
answer's ``instance`` changed, or it published a continuing ``session_restarted``) is named as
the cause instead of its queue counters. It also reports a new session the service started for
the camera (the frames went back from its earlier ones, or ``new_session`` asked for a reset).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import zenoh

from metricslam.datasets.base import Sequence
from metricslam.datasets.frame_reader import FrameReader
from metricslam.errors import ConfigError, ServiceError
from metricslam.wire.codec import StatusMessage
from metricslam_slam.tools.client import (
    FramePublisher, PoseRecorder, describe_counters, new_sessions, query_health, reset_camera, service_restart,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplayReport:
    """Frames a replay sent and the SLAM service confirmed (a pose each).

    Attributes:
        camera_id: the camera the frames went to.
        sent: frames published.
        confirmed: of those, frames whose pose arrived.
        missing: frame indices without a pose (sorted).
        status: the service's latest ``…/status`` for the camera (its counters are since the
            session started, not per replay), or None if none arrived.
        new_sessions: details of the fresh sessions the service started for the camera meanwhile
            (``session_restarted`` "new session …": why it did not continue the earlier trajectory).
        restart: why the SLAM service looks restarted during the replay, or None.
    """

    camera_id: str
    sent: int
    confirmed: int
    missing: list[int] = field(default_factory=list)
    status: StatusMessage | None = None
    new_sessions: list[str] = field(default_factory=list)
    restart: str | None = None

    @property
    def complete(self) -> bool:
        return self.confirmed == self.sent

    def describe(self) -> str:
        """One line for people: the counts, the first missing frames, the service's counters."""
        text = (f"sent {self.sent} frames to metricslam/{self.camera_id}/frame; the SLAM service "
                f"confirmed {self.confirmed} (a pose each)")
        if self.missing:
            more = "" if len(self.missing) <= 10 else f" and {len(self.missing) - 10} more"
            text += f"; {len(self.missing)} without a pose: frames {self.missing[:10]}{more}"
        for detail in self.new_sessions:
            text += f"; the SLAM service started a {detail}"
        st = self.status
        if self.restart is not None and self.missing:
            text += (f"; the SLAM service restarted during the replay ({self.restart}): frames sent while it "
                     "was down or queued in it have no pose")
        elif st is not None and self.missing:
            text += f"; its status: {describe_counters(st)} (counted since its session started)"
        return text


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
                    max_in_flight: int = 0, progress: bool = True,
                    confirm_timeout_s: float = 10.0, subscriber_timeout_s: float = 10.0,
                    new_session: bool = False) -> ReplayReport:
    """Publish frames ``start..stop-1`` at ``rate_hz`` (0 = as fast as possible) and count the
    service's confirmations (module docstring).

    ``max_in_flight > 0`` adds back-pressure: frame ``k`` goes out only once poses of all but
    ``max_in_flight`` of the frames published before it arrived; after one 10 s wait without
    progress back-pressure is switched off, so dropped frames or a dead service cannot stall the
    replay. A frame whose image cannot be read is logged and published black, which the SLAM
    service treats as an invalid frame. After the last frame, waits for the missing poses until
    none arrived for ``confirm_timeout_s`` (0: report what arrived by then). Before the first
    frame, waits up to ``subscriber_timeout_s`` until zenoh knows the service's subscription: a
    fresh publisher drops puts until then (seconds on a loaded machine). ``new_session``: first
    ask the service to start a fresh session at the camera's first frame (:func:`reset_camera`;
    raises :class:`ServiceError` when no service answers), whatever the frame indices.
    """
    from tqdm import tqdm

    stop = len(seq) if stop is None else min(stop, len(seq))
    if not 0 <= start < stop:
        raise ConfigError(f"frame range [{start}, {stop}) is empty or outside 0..{len(seq) - 1}")
    if rate_hz < 0:
        raise ConfigError(f"rate must be >= 0 Hz, got {rate_hz}")
    frames = FrameReader(seq)
    health_before = query_health(session, timeout_s=2.0)
    if new_session:
        answer = reset_camera(session, camera_id, "metricslam replay --new-session")
        log.info("camera %s reset: its next frame starts a new session (%s earlier poses not continued)",
                 camera_id, answer.get("earlier_poses"))
    publisher = FramePublisher(session, camera_id, block=True)
    recorder = PoseRecorder(session, camera_id)  # before the first frame: no pose is missed
    if subscriber_timeout_s > 0 and not publisher.wait_for_subscriber(subscriber_timeout_s):
        log.warning("no subscriber of %s's frames known after %.0f s: frames may be lost (counted "
                    "below)", camera_id, subscriber_timeout_s)
    back_pressure = max_in_flight > 0
    period_s = 0.0 if rate_hz == 0 else 1.0 / rate_hz
    t_start = time.monotonic()
    sent: list[int] = []
    try:
        for k, i in enumerate(tqdm(range(start, stop), desc=f"replay {camera_id}", unit="frame",
                                   disable=not progress)):
            frame = frames[i]
            if period_s:
                delay = t_start + k * period_s - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if back_pressure and not recorder.wait_for(
                    lambda r, k=k: sum(j >= start for j in r.poses) >= k - max_in_flight, timeout_s=10.0):
                log.warning("no poses for 10 s: back-pressure off for the rest of the replay")
                back_pressure = False
            publisher.publish(frame.index, frame.t_ns, frame.image, frame.camera)
            sent.append(int(frame.index))
        _wait_confirmed(recorder, sent, confirm_timeout_s)
        missing = sorted(set(sent) - recorder.received_frames())
        if missing:  # a status published after the last frame explains them best
            n_status = len(recorder.statuses)
            recorder.wait_for(lambda r: len(r.statuses) > n_status, min(confirm_timeout_s, 2.0))
        statuses = recorder.statuses_so_far()
        restart = service_restart(health_before, query_health(session, timeout_s=2.0), statuses)
        return ReplayReport(camera_id, len(sent), len(sent) - len(missing), missing,
                            recorder.latest_status(), new_sessions(statuses), restart)
    finally:
        publisher.close()
        recorder.close()


def _wait_confirmed(recorder: PoseRecorder, sent: list[int], quiet_s: float) -> None:
    """Wait until every frame in ``sent`` has a pose, or no new pose arrived for ``quiet_s``."""
    want = set(sent)
    while quiet_s > 0:
        n_before = len(recorder.poses)
        if recorder.wait_for(lambda r: want <= set(r.poses), quiet_s):
            return
        if len(recorder.poses) == n_before:  # nothing new for quiet_s: the rest is not coming
            return
