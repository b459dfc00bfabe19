"""``python -m metricslam_depth``: the depth service with settings from ``DEPTH_*`` variables."""

from __future__ import annotations

import logging
import sys

from metricslam.errors import MetricSlamError

from .server import serve
from .settings import load_settings


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        serve(load_settings())
    except MetricSlamError as exc:
        print(f"depth-service: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
