"""Container health checks of the SLAM service.

``python -m metricslam_slam.supervisor.healthcheck [--zenoh-endpoint EP]`` (readiness; compose's
health check, the Kubernetes readiness probe): exit 0 when the SLAM service answers
``metricslam/_service/health`` through the router (default endpoint: ``SLAM_ZENOH_ENDPOINT``).

``python -m metricslam_slam.supervisor.healthcheck --alive [--max-age S]`` (liveness; the
Kubernetes liveness probe): exit 0 when the service's watchdog rewrote its heartbeat file
(``SLAM_HEARTBEAT_FILE``) within ``S`` seconds. It reads only a local file, so a router outage
never fails it (a restart would drop every camera's map); a hung or frozen process does
(:mod:`metricslam_slam.service.watchdog`).
"""

from __future__ import annotations

import argparse
import sys

from metricslam_slam.service.settings import SlamServiceSettings

#: default --max-age: a few watchdog periods (at most 5 s each) and a slow probe start
DEFAULT_MAX_AGE_S = 30.0


def alive(max_age_s: float, settings: SlamServiceSettings) -> tuple[bool, str]:
    """``(alive, why)`` from the heartbeat file of ``settings``."""
    from metricslam_slam.service.watchdog import heartbeat_age_s

    if settings.heartbeat_file is None:
        return False, "SLAM_HEARTBEAT_FILE is not set: no heartbeat to check"
    age = heartbeat_age_s(settings.heartbeat_file)
    if age is None:
        return False, f"no heartbeat in {settings.heartbeat_file}"
    if age > max_age_s:
        return False, f"heartbeat {age:.0f} s old (> {max_age_s:g} s): the service is hung or frozen"
    return True, f"heartbeat {age:.1f} s old"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--zenoh-endpoint", default=None,
                        help="router endpoint (default: SLAM_ZENOH_ENDPOINT, else the service default)")
    parser.add_argument("--alive", action="store_true",
                        help="liveness: check the heartbeat file (SLAM_HEARTBEAT_FILE), not the router")
    parser.add_argument("--max-age", type=float, default=DEFAULT_MAX_AGE_S, metavar="S",
                        help="--alive: the oldest heartbeat that still counts (default: %(default)s)")
    args = parser.parse_args(argv)
    settings = SlamServiceSettings()
    if args.alive:
        ok, why = alive(args.max_age, settings)
        print(why, file=sys.stdout if ok else sys.stderr)
        return 0 if ok else 1
    from metricslam_slam.supervisor.launcher import slam_ready

    endpoint = args.zenoh_endpoint or settings.zenoh_endpoint
    return 0 if slam_ready(endpoint) else 1


if __name__ == "__main__":
    sys.exit(main())
