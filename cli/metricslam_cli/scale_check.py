"""``metricslam camera --scale-sources/--mount-height``: checked against the SLAM service.

The SLAM service owns the scale settings (``up`` / ``slam-service --scale-sources …
--mount-height …``; its sessions are built from its own configuration, docs/ground_scale.md);
frames carry intrinsics, not scale settings. So the camera does not forward them: it reads the
scale block of the service's status for its camera (``metricslam/<id>/status``,
:class:`~metricslam.wire.scale_status.ScaleHealthStatus`) once it arrives and stops with one
clear error when the service runs other sources or another mounting height than the flags ask
for — instead of publishing under settings the user did not get. A mounting height that only
the calibration file gives is compared too, but a difference is a warning.

Example::

    check = ServiceScaleCheck(session, "cam0", RequestedScale(("learned", "ground"), 1.65))
    ...                      # publish frames
    check.poll()             # None until the service's status arrived; raises on a mismatch
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

from metricslam.errors import CodecError, ConfigError
from metricslam.wire import keys
from metricslam.wire.codec import StatusMessage, decode_as

log = logging.getLogger("metricslam.camera")


@dataclass(frozen=True)
class RequestedScale:
    """What the camera's user asked for.

    Attributes:
        sources: ``--scale-sources`` (None: not given).
        mount_height_m: ``--mount-height`` (None: not given).
        calibration_mount_height_m: the calibration file's ``mount_height_m`` (None: none).
    """

    sources: tuple[str, ...] | None = None
    mount_height_m: float | None = None
    calibration_mount_height_m: float | None = None

    @property
    def anything(self) -> bool:
        return any(v is not None for v in (self.sources, self.mount_height_m, self.calibration_mount_height_m))


def _describe(sources: tuple[str, ...], mount_height_m: float | None) -> str:
    names = ",".join(sources) if sources else "none"
    height = "no mounting height" if mount_height_m is None else f"the camera {mount_height_m:g} m above the road"
    return f"scale sources {names} with {height}"


def _same_height(a: float | None, b: float | None) -> bool:
    return a is not None and b is not None and abs(a - b) <= 1e-6 * max(abs(a), abs(b), 1.0)


def scale_mismatch(requested: RequestedScale, service_sources: tuple[str, ...],
                   service_mount_height_m: float | None, camera_id: str = "cam0") -> tuple[str, str]:
    """``(error, warning)`` texts comparing ``requested`` with the service's settings ("" each
    when there is nothing to say): an error for a ``--scale-sources`` / ``--mount-height`` the
    service does not run, a warning for a calibration height it does not use."""
    service = _describe(tuple(service_sources), service_mount_height_m)
    wrong = []
    if requested.sources is not None and tuple(requested.sources) != tuple(service_sources):
        wrong.append(f"--scale-sources {','.join(requested.sources)}")
    if requested.mount_height_m is not None and not _same_height(requested.mount_height_m, service_mount_height_m):
        wrong.append(f"--mount-height {requested.mount_height_m:g}")
    if wrong:
        want_sources = requested.sources if requested.sources is not None else tuple(service_sources)
        want_height = requested.mount_height_m if requested.mount_height_m is not None else service_mount_height_m
        fix = f"--scale-sources {','.join(want_sources)}" + (
            f" --mount-height {want_height:g}" if want_height is not None else "")
        return (f"the SLAM service runs camera {camera_id} with {service}, not the {' and '.join(wrong)} "
                f"asked for here; the service owns the scale settings: restart it with them "
                f"(`metricslam up {fix}` or `metricslam slam-service {fix}`)"), ""
    h_cal = requested.calibration_mount_height_m
    if h_cal is not None and requested.mount_height_m is None and not _same_height(h_cal, service_mount_height_m):
        return "", (f"the calibration file puts the camera {h_cal:g} m above the road, but the SLAM "
                    f"service runs camera {camera_id} with {service}; for ground-plane scale start it "
                    f"with --scale-sources learned,ground --mount-height {h_cal:g}")
    return "", ""


class ServiceScaleCheck:
    """Watches one camera's status topic until the service's scale settings are known, then
    compares them with ``requested`` (:func:`scale_mismatch`).

    Args:
        session: an open zenoh session.
        camera_id: the camera whose status is read.
        requested: the flags (see :class:`RequestedScale`).
        timeout_s: after this long without a status, one warning that the settings are unconfirmed.
    """

    def __init__(self, session: object, camera_id: str, requested: RequestedScale, timeout_s: float = 15.0) -> None:
        self.camera_id = camera_id
        self.requested = requested
        self.done = False
        self._deadline = time.monotonic() + timeout_s
        self._lock = threading.Lock()
        self._block: tuple[tuple[str, ...], float | None] | None = None
        self._sub = session.declare_subscriber(keys.key(camera_id, "status"), self._on_status)

    def _on_status(self, sample: object) -> None:
        try:
            status = decode_as(sample.payload.to_bytes(), StatusMessage)
        except CodecError:
            return
        health = status.scale_health
        if health is None:  # no session yet, or a session without a back end
            return
        with self._lock:
            self._block = (tuple(health.sources), health.mount_height_m)

    def poll(self) -> bool:
        """True once the comparison is made (logged; a warning on timeout).

        Raises:
            ConfigError: the service runs other scale settings than the flags ask for.
        """
        if self.done:
            return True
        with self._lock:
            block = self._block
        if block is None:
            if time.monotonic() > self._deadline:
                log.warning("no status from the SLAM service for camera %s yet: its scale settings "
                            "are unconfirmed", self.camera_id)
                self.done = True
            return self.done
        self.done = True
        error, warning = scale_mismatch(self.requested, *block, camera_id=self.camera_id)
        if error:
            raise ConfigError(error)
        if warning:
            log.warning("%s", warning)
        else:
            log.info("the SLAM service runs camera %s with %s, as asked", self.camera_id, _describe(*block))
        return True

    def close(self) -> None:
        self._sub.undeclare()
