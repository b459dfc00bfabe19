"""``metricslam depth-service``: serve the depth network over HTTP (FastAPI + uvicorn).

Example::

    metricslam depth-service --host 127.0.0.1 --port 8100
    curl -s -H 'Content-Type: image/png' --data-binary @000000.png \\
        'http://127.0.0.1:8100/v1/disparity?fx=718.856'

Settings not given as flags come from ``DEPTH_*`` environment variables (see
docs/depth_service.md); flags win over the environment.
"""

from __future__ import annotations

import argparse

from metricslam.endpoints import DEFAULT_DEPTH_HOST, DEFAULT_DEPTH_PORT
from metricslam_cli.extras import require


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "depth-service",
        help="serve the depth network over HTTP",
        description="Run the depth inference service (FastAPI + onnxruntime under uvicorn). "
        "Flags override DEPTH_* environment variables; see docs/depth_service.md.",
    )
    p.add_argument("--host", help=f"interface to bind (default {DEFAULT_DEPTH_HOST}; env DEPTH_HOST)")
    p.add_argument("--port", type=int, help=f"TCP port (default {DEFAULT_DEPTH_PORT}; env DEPTH_PORT)")
    p.add_argument("--model", dest="model_path", metavar="PATH",
                   help="ONNX model file (default: the shipped model; env DEPTH_MODEL_PATH)")
    p.add_argument("--threads", type=int, help="threads per request: onnxruntime intra-op and OpenCV (env DEPTH_THREADS)")
    p.add_argument("--max-concurrency", type=int,
                   help="requests inferred at once (env DEPTH_MAX_CONCURRENCY)")
    p.add_argument("--max-queue", type=int,
                   help="requests allowed to wait; more get 429 (env DEPTH_MAX_QUEUE)")
    p.add_argument("--log-level", choices=("critical", "error", "warning", "info", "debug"),
                   help="log level (env DEPTH_LOG_LEVEL)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    require("depth-service", command="depth-service")

    from metricslam_depth.server import serve
    from metricslam_depth.settings import load_settings

    settings = load_settings(
        host=args.host, port=args.port, model_path=args.model_path, threads=args.threads,
        max_concurrency=args.max_concurrency, max_queue=args.max_queue, log_level=args.log_level,
    )
    serve(settings)
    return 0
