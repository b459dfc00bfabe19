"""``metricslam camera``: publish a live OpenCV camera as Zenoh frames.

Example::

    metricslam camera --device 0 --zenoh-endpoint tcp/127.0.0.1:7447 --fx 600

Frames go out gray on ``metricslam/<camera_id>/frame`` with best-effort congestion control
(a live stream drops rather than queues). Intrinsics come from ``--fx/--fy/--cx/--cy``
(calibrate your camera!); without them a 60-degree horizontal field of view is assumed.
"""

from __future__ import annotations

import argparse

from metricslam.endpoints import DEFAULT_ZENOH_ENDPOINT


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "camera", help="publish a live camera (OpenCV) as zenoh frames",
        description="Grabs frames from an OpenCV video device (or a video file) and publishes them "
        "on metricslam/<camera_id>/frame until Ctrl-C.")
    p.add_argument("--device", default="0", help="OpenCV device index or a video file/URL")
    p.add_argument("--zenoh-endpoint", default=DEFAULT_ZENOH_ENDPOINT, metavar="EP")
    p.add_argument("--camera-id", default="cam0", metavar="ID")
    p.add_argument("--fx", type=float, help="focal length x (px) at the capture resolution")
    p.add_argument("--fy", type=float, help="focal length y (px); default = fx")
    p.add_argument("--cx", type=float, help="principal point x (px); default = image centre")
    p.add_argument("--cy", type=float, help="principal point y (px); default = image centre")
    p.add_argument("--max-rate", type=float, default=30.0, metavar="HZ", help="publish at most this often")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="stop after N frames")
    p.set_defaults(func=run)
    return p


def intrinsics(width_px: int, height_px: int, fx=None, fy=None, cx=None, cy=None):
    """PinholeCamera from flags; unknown focal length -> 60 deg horizontal field of view."""
    import math

    from metricslam.camera import PinholeCamera

    fx = fx if fx else 0.5 * width_px / math.tan(math.radians(30.0))
    return PinholeCamera(fx_px=fx, fy_px=fy or fx, cx_px=(width_px - 1) / 2 if cx is None else cx,
                         cy_px=(height_px - 1) / 2 if cy is None else cy,
                         width_px=width_px, height_px=height_px)


def run(args: argparse.Namespace) -> int:
    import logging
    import signal
    import time

    import cv2

    from metricslam.errors import ServiceError
    from metricslam_slam.client import FramePublisher
    from metricslam_slam.zenoh_config import open_client

    log = logging.getLogger("metricslam.camera")
    source = int(args.device) if args.device.isdigit() else args.device
    capture = cv2.VideoCapture(source)
    if not capture.isOpened():
        raise ServiceError(f"cannot open video device {args.device!r}; check the index/path and permissions")
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    session = open_client(args.zenoh_endpoint)
    publisher = FramePublisher(session, args.camera_id, block=False)
    camera = None
    index = 0
    t_first = time.monotonic_ns()
    try:
        while not stop and (args.max_frames is None or index < args.max_frames):
            t_loop = time.monotonic()
            ok, bgr = capture.read()
            if not ok:
                log.warning("camera %s: no frame (end of stream?)", args.device)
                break
            gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if bgr.ndim == 3 else bgr
            if camera is None:
                camera = intrinsics(gray.shape[1], gray.shape[0], args.fx, args.fy, args.cx, args.cy)
                print(f"publishing {args.camera_id} from {args.device}: {camera}", flush=True)
            publisher.publish(index, time.monotonic_ns() - t_first, gray, camera)
            index += 1
            rest = 1.0 / args.max_rate - (time.monotonic() - t_loop)
            if rest > 0:
                time.sleep(rest)
    finally:
        publisher.close()
        session.close()
        capture.release()
    print(f"published {index} frames")
    return 0
