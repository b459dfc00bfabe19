"""``metricslam camera``: publish a live OpenCV camera as Zenoh frames.

Example::

    metricslam camera --device 0 --zenoh-endpoint tcp/127.0.0.1:7447 --calib my_camera.yaml
    metricslam camera --device 0 --fx 600                  # focal length known, no distortion
    metricslam camera --device 0 --assume-fov 60           # a guess: metric scale will be off

Frames go out gray on ``metricslam/<camera_id>/frame`` with best-effort congestion control
(a live stream drops rather than queues). The SLAM service's metric scale depends on the
intrinsics, so the command refuses to start without them: a ``--calib`` file (distortion is
undone on each frame before it is published, same K; docs/calibration.md), or ``--fx`` [``--fy
--cx --cy``], or an explicit guess ``--assume-fov DEG`` (horizontal field of view; logged as a
warning).

``--scale-sources`` / ``--mount-height`` are checked like ``run`` checks them before the device
opens, then against the SLAM service, which owns them (:mod:`metricslam_cli.scale_check`): when
its status shows other settings the camera stops with one error line saying how to restart the
service.
"""

from __future__ import annotations

import argparse
import logging

from metricslam.endpoints import DEFAULT_ZENOH_ENDPOINT
from metricslam_cli.extras import require
from metricslam_cli.scale_options import add_scale_options, log_scale_sources, scale_flags


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "camera", help="publish a live camera (OpenCV) as zenoh frames",
        description="Grabs frames from an OpenCV video device (or a video file) and publishes them "
        "on metricslam/<camera_id>/frame until Ctrl-C.")
    p.add_argument("--device", default="0", help="OpenCV device index or a video file/URL")
    p.add_argument("--zenoh-endpoint", default=DEFAULT_ZENOH_ENDPOINT, metavar="EP")
    p.add_argument("--camera-id", default="cam0", metavar="ID")
    p.add_argument("--calib", metavar="FILE.yaml",
                   help="camera calibration (metricslam, OpenCV FileStorage or EuRoC sensor.yaml "
                        "YAML; docs/calibration.md): intrinsics, and distortion undone per frame")
    p.add_argument("--assume-fov", type=float, metavar="DEG",
                   help="no calibration: assume this horizontal field of view (a guess; metric "
                        "scale is only as right as the guess)")
    p.add_argument("--fx", type=float, help="focal length x (px) at the capture resolution")
    p.add_argument("--fy", type=float, help="focal length y (px); default = fx")
    p.add_argument("--cx", type=float, help="principal point x (px); default = image centre")
    p.add_argument("--cy", type=float, help="principal point y (px); default = image centre")
    p.add_argument("--max-rate", type=float, default=30.0, metavar="HZ", help="publish at most this often")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="stop after N frames")
    add_scale_options(p, note="; the SLAM service owns it (up / slam-service): checked against "
                              "its status, and the camera stops when the service runs otherwise")
    p.set_defaults(func=run)
    return p


def check_scale_flags(args: argparse.Namespace, calibration_mount_height_m: float | None = None):
    """The :class:`~metricslam.slam.system_config.SystemConfig` whose ``scale`` section the
    calibration file's ``mount_height_m`` and ``--scale-sources`` / ``--mount-height`` give,
    checked as ``run`` checks them (ConfigError before the device opens). Frames do not carry
    them: the SLAM service owns them, and :func:`requested_scale` is compared with its status."""
    from metricslam.slam.config_file import load_system_config
    from metricslam.slam.system_config import LIVE_PROFILE

    profile, overrides = scale_flags(args, calibration_mount_height_m)
    return load_system_config(None, profile={**LIVE_PROFILE, **profile}, overrides=overrides)


def requested_scale(args: argparse.Namespace, calibration_mount_height_m: float | None = None):
    """The :class:`~metricslam_cli.scale_check.RequestedScale` of the flags (already checked)."""
    from metricslam.slam.ground.config import parse_scale_sources
    from metricslam_cli.scale_check import RequestedScale

    sources = parse_scale_sources(args.scale_sources) if args.scale_sources is not None else None
    return RequestedScale(sources, args.mount_height, calibration_mount_height_m)


def check_intrinsics_flags(args: argparse.Namespace) -> None:
    """Refuse to start without intrinsics, or with two sources of them (ConfigError)."""
    from metricslam.errors import ConfigError

    given = [name for name, on in (("--calib", args.calib), ("--fx", args.fx is not None),
                                   ("--assume-fov", args.assume_fov is not None)) if on]
    if not given:
        raise ConfigError(
            "no camera intrinsics: metric scale depends on them. Pass --calib FILE.yaml (calibrate "
            "with `metricslam calibrate`, docs/calibration.md), or --fx FX [--fy --cx --cy] if you "
            "know the focal length in pixels, or --assume-fov DEG to run on a guessed horizontal "
            "field of view")
    if len(given) > 1:
        raise ConfigError(f"{' and '.join(given)} both give intrinsics; pass one")
    if args.assume_fov is not None and not 1.0 <= args.assume_fov < 179.0:
        raise ConfigError(f"--assume-fov must be a horizontal field of view in degrees (1..179), "
                          f"got {args.assume_fov}")


def intrinsics(width_px: int, height_px: int, fx=None, fy=None, cx=None, cy=None, fov_deg=None):
    """PinholeCamera from flags: ``fx`` (px), or the horizontal field of view ``fov_deg``.

    Raises:
        CameraError: implausible intrinsics (:func:`metricslam.camera.check_intrinsics`).
    """
    import math

    from metricslam.camera import PinholeCamera, check_intrinsics

    if fx is None:
        fx = 0.5 * width_px / math.tan(math.radians(0.5 * fov_deg))
    values = {"fx_px": fx, "fy_px": fx if fy is None else fy, "cx_px": (width_px - 1) / 2 if cx is None else cx,
              "cy_px": (height_px - 1) / 2 if cy is None else cy,
              "width_px": width_px, "height_px": height_px}
    check_intrinsics(**values)  # CameraError naming the flag's value, before anything is published
    return PinholeCamera(**values)


def frame_calibration(args: argparse.Namespace, width_px: int, height_px: int):
    """The :class:`~metricslam.calibration.Calibration` of the captured frames, from the flags."""
    from metricslam.calibration import Calibration, load_calibration

    if args.calib:
        return load_calibration(args.calib).for_image(width_px, height_px)
    if args.assume_fov is not None:
        logging.getLogger("metricslam.camera").warning(
            "NO CALIBRATION: assuming a %g-degree horizontal field of view; metric scale is only as "
            "right as this guess (docs/calibration.md)", args.assume_fov)
    camera = intrinsics(width_px, height_px, args.fx, args.fy, args.cx, args.cy, args.assume_fov)
    return Calibration(camera=camera, source="--assume-fov" if args.fx is None else "--fx")


def run(args: argparse.Namespace) -> int:
    require("slam-service", command="camera")

    import signal
    import time

    import cv2

    from metricslam.errors import ServiceError
    from metricslam_slam.tools.client import FramePublisher
    from metricslam_slam.zenoh_config import open_client

    check_intrinsics_flags(args)
    calib_height = None
    if args.calib:  # a broken file is an error before the device opens
        from metricslam.calibration import load_calibration

        calib_height = load_calibration(args.calib).mount_height_m
    log = logging.getLogger("metricslam.camera")
    log_scale_sources(check_scale_flags(args, calib_height), log)
    requested = requested_scale(args, calib_height)
    source = int(args.device) if args.device.isdigit() else args.device
    capture = cv2.VideoCapture(source)
    if not capture.isOpened():
        raise ServiceError(f"cannot open video device {args.device!r}; check the index/path and permissions")
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    session = open_client(args.zenoh_endpoint)
    publisher = FramePublisher(session, args.camera_id, block=False)
    check = None
    if requested.anything:
        from metricslam_cli.scale_check import ServiceScaleCheck

        log.info("the SLAM service owns the scale settings: they are checked against its status")
        check = ServiceScaleCheck(session, args.camera_id, requested)
    camera = maps = None
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
                calib = frame_calibration(args, gray.shape[1], gray.shape[0])
                camera, maps = calib.camera, calib.undistort_maps()
                print(f"publishing {args.camera_id} from {args.device}: {camera}", flush=True)
            if maps is not None:
                gray = cv2.remap(gray, *maps, interpolation=cv2.INTER_LINEAR)
            publisher.publish(index, time.monotonic_ns() - t_first, gray, camera)
            index += 1
            if check is not None:
                check.poll()  # raises ConfigError when the service runs other scale settings
            rest = 1.0 / args.max_rate - (time.monotonic() - t_loop)
            if rest > 0:
                time.sleep(rest)
    finally:
        if check is not None:
            check.close()
        publisher.close()
        session.close()
        capture.release()
    print(f"published {index} frames")
    return 0
