"""``metricslam replay``: publish a dataset folder as Zenoh frames at a fixed rate.

Example::

    metricslam replay ../shared/data/kitti_odometry/sequences/06 --zenoh-endpoint tcp/127.0.0.1:7447 --rate 10

Waits (``--wait``) until a SLAM service answers and zenoh knows its frame subscription (a fresh
publisher drops frames until then), so no frame is published into the void, then
publishes every frame on ``metricslam/<camera_id>/frame`` (reliable, blocking congestion
control) with a progress bar, then counts the frames the SLAM service confirmed (a pose each,
waiting up to ``--confirm-timeout`` seconds without news for the last ones) and prints
``sent N …; the SLAM service confirmed M``. Exit code 1 when they differ (frames dropped from
the service's full queue, malformed, lost), unless ``--allow-loss``. ``--max-in-flight N`` adds
back-pressure (never more than N frames ahead of the poses) for runs where every frame must be
processed on a slow machine.

A second replay under the same ``--camera-id`` starts a new SLAM session by itself when its frame
indices or timestamps go back (said in the service's log, on ``…/status`` and here);
``--new-session`` asks for one whatever the frames (e.g. a sequence whose frames go on from
the last one's). When the SLAM service restarted during the replay, the error names the
restart instead of the rate.
"""

from __future__ import annotations

import argparse

from metricslam.endpoints import DEFAULT_ZENOH_ENDPOINT
from metricslam_cli.extras import require


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "replay", help="publish a sequence folder as zenoh frames",
        description="Publishes a dataset folder (KITTI, EuRoC, TUM, synth output) frame by frame "
        "on metricslam/<camera_id>/frame at --rate Hz, then exits.")
    p.add_argument("seq_dir", metavar="SEQ_DIR",
                   help="dataset folder: KITTI sequence, EuRoC mav0, TUM RGB-D or `metricslam synth` output")
    p.add_argument("--zenoh-endpoint", default=DEFAULT_ZENOH_ENDPOINT, metavar="EP",
                   help="zenoh router to publish through")
    p.add_argument("--rate", type=float, default=10.0, metavar="HZ", help="frames per second (0: as fast as possible)")
    p.add_argument("--camera-id", default="cam0", metavar="ID",
                   help="camera id of the frames (metricslam/<ID>/frame): one SLAM session per id")
    p.add_argument("--calib", metavar="FILE.yaml",
                   help="camera calibration replacing the reader's (as `run --calib`; "
                        "docs/calibration.md); frames are undistorted before they are published")
    p.add_argument("--start", type=int, default=0, metavar="K", help="first frame to publish")
    p.add_argument("--max-frames", type=int, metavar="N", help="publish at most N frames")
    p.add_argument("--max-in-flight", type=int, default=0, metavar="N",
                   help="back-pressure: publish frame i only once poses of all but N earlier "
                   "frames arrived (0: off, a pure fixed-rate stream)")
    p.add_argument("--wait", type=float, default=30.0, metavar="S",
                   help="seconds to wait for a SLAM service to answer (then give up) and for zenoh to "
                        "know its frame subscription (then warn; 0: do not wait)")
    p.add_argument("--confirm-timeout", type=float, default=10.0, metavar="S",
                   help="after the last frame, wait for missing poses until none arrived for S "
                        "seconds (default 10; 0: count what arrived by then)")
    p.add_argument("--allow-loss", action="store_true",
                   help="exit 0 even when the SLAM service confirmed fewer frames than were sent")
    p.add_argument("--new-session", action="store_true",
                   help="first reset the camera id: the SLAM service starts a fresh session at its next "
                        "frame instead of continuing its earlier trajectory (one starts anyway when the "
                        "frame indices or timestamps go back)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    require("slam-service", command="replay")

    from metricslam.calibration import load_calibration
    from metricslam.datasets import open_sequence
    from metricslam.errors import ServiceError
    from metricslam_slam.tools.replay import replay_sequence, wait_for_service
    from metricslam_slam.zenoh_config import open_client

    seq = open_sequence(args.seq_dir, calibration=load_calibration(args.calib) if args.calib else None)
    stop = None if args.max_frames is None else args.start + args.max_frames
    session = open_client(args.zenoh_endpoint)
    try:
        if args.wait > 0:
            wait_for_service(session, args.wait, args.zenoh_endpoint)
        report = replay_sequence(session, seq, args.camera_id, args.rate, args.start, stop,
                                 args.max_in_flight, progress=not args.no_progress,
                                 confirm_timeout_s=args.confirm_timeout, subscriber_timeout_s=args.wait,
                                 new_session=args.new_session)
    finally:
        session.close()
    if not report.complete and not args.allow_loss:
        if report.restart is not None:
            raise ServiceError(report.describe() + "; replay again once it is up (`metricslam up` restarts "
                               "it), or pass --allow-loss to accept the gap")
        raise ServiceError(report.describe() + "; lower --rate, add --max-in-flight N, or pass "
                           "--allow-loss to accept it")
    print(report.describe(), flush=True)
    return 0
