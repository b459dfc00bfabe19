"""The SLAM service's per-camera command queryables (``metricslam/_service/<command>/<camera_id>``).

* ``reset``: the camera's next frame starts a fresh session, not continuing its trajectory.
* ``finish``: close the camera now, as an idle close does: its local window is marginalized into
  the global graph (those keyframes' scale factors too), the final solve runs, and the final
  trajectory stays on ``…/trajectory`` for ``closed_trajectory_ttl_s`` — what ``metricslam run``
  writes at the end of a sequence. A later frame of the camera continues it in a new session.

Both answer JSON naming the camera and the service ``instance``; a service that does not serve
the camera (``frame_key_expr``) or is stopping stays silent; the payload, if any, is the reason
(for the log and the camera's status event).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from typing import Any, Callable

from metricslam.wire import keys
from metricslam_slam.service.cameras import Cameras
from metricslam_slam.service.service_map import camera_of_query

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraCommands:
    """The two queryables' handlers over the service's cameras.

    Attributes:
        cameras: the service's :class:`Cameras`.
        serves: ``camera_id -> bool``: whether this service takes that camera's frames.
        stopping: ``() -> bool``: the service is stopping (commands are then not answered).
        instance: the service instance id, echoed in every answer.
    """

    cameras: Cameras
    serves: Callable[[str], bool]
    stopping: Callable[[], bool]
    instance: str

    def _command(self, query: Any, command: str) -> tuple[str, str] | None:
        """``(camera_id, why)`` of a command query this service serves, else None."""
        camera_id = camera_of_query(query)
        if camera_id is None or not self.serves(camera_id) or self.stopping():
            return None
        given = query.payload.to_bytes().decode(errors="replace").strip() if query.payload is not None else ""
        return camera_id, f"{command} requested ({given[:200] or 'no reason given'})"

    def on_reset_query(self, query: Any) -> None:
        """``…/_service/reset/<camera_id>``: answers ``{"camera_id", "earlier_poses", "instance"}``."""
        if (command := self._command(query, "reset")) is None:
            return
        camera_id, why = command
        earlier = self.cameras.reset(camera_id, why)
        log.warning("camera %s: %s; its next frame starts a new session (%d earlier poses not continued)",
                    camera_id, why, earlier)
        query.reply(keys.reset_key(camera_id), json.dumps(
            {"camera_id": camera_id, "earlier_poses": earlier, "instance": self.instance}).encode())

    def on_finish_query(self, query: Any) -> None:
        """``…/_service/finish/<camera_id>``: answers ``{"camera_id", "finished", "instance"}`` once
        the camera is closed (``finished`` False: it had no running session)."""
        if (command := self._command(query, "finish")) is None:
            return
        camera_id, why = command
        finished = self.cameras.finish(camera_id, why)
        query.reply(keys.finish_key(camera_id), json.dumps(
            {"camera_id": camera_id, "finished": finished, "instance": self.instance}).encode())
