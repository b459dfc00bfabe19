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
from typing import Any

from metricslam.wire import keys
from metricslam_slam.service.service_map import camera_of_query

log = logging.getLogger(__name__)


def _command(service: Any, query: Any, command: str) -> tuple[str, str] | None:
    """``(camera_id, why)`` of a command query this service serves, else None."""
    camera_id = camera_of_query(query)
    if camera_id is None or not service._serves(camera_id) or service._stopped.is_set():
        return None
    given = query.payload.to_bytes().decode(errors="replace").strip() if query.payload is not None else ""
    return camera_id, f"{command} requested ({given[:200] or 'no reason given'})"


def on_reset_query(service: Any, query: Any) -> None:
    """``…/_service/reset/<camera_id>``: answers ``{"camera_id", "earlier_poses", "instance"}``."""
    if (command := _command(service, query, "reset")) is None:
        return
    camera_id, why = command
    earlier = service._cameras.reset(camera_id, why)
    log.warning("camera %s: %s; its next frame starts a new session (%d earlier poses not continued)",
                camera_id, why, earlier)
    query.reply(keys.reset_key(camera_id), json.dumps(
        {"camera_id": camera_id, "earlier_poses": earlier, "instance": service.instance}).encode())


def on_finish_query(service: Any, query: Any) -> None:
    """``…/_service/finish/<camera_id>``: answers ``{"camera_id", "finished", "instance"}`` once the
    camera is closed (``finished`` False: it had no running session)."""
    if (command := _command(service, query, "finish")) is None:
        return
    camera_id, why = command
    finished = service._cameras.finish(camera_id, why)
    query.reply(keys.finish_key(camera_id), json.dumps(
        {"camera_id": camera_id, "finished": finished, "instance": service.instance}).encode())
