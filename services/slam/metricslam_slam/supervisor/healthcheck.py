"""Container health check: exit 0 when the SLAM service answers ``metricslam/_service/health``.

``python -m metricslam_slam.supervisor.healthcheck [--zenoh-endpoint EP]`` (default: ``SLAM_ZENOH_ENDPOINT``).
"""

from __future__ import annotations

import argparse
import sys

from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.supervisor.launcher import slam_ready


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--zenoh-endpoint", default=None)
    args = parser.parse_args(argv)
    endpoint = args.zenoh_endpoint or SlamServiceSettings().zenoh_endpoint
    return 0 if slam_ready(endpoint) else 1


if __name__ == "__main__":
    sys.exit(main())
