"""``metricslam poses``: record the live pose stream of one camera to a trajectory file.

Example::

    metricslam poses --zenoh-endpoint tcp/127.0.0.1:7447 --out est.txt --frames 300 --timeout 120
    metricslam poses --out est.txt --frames 300 --mcap live.mcap   # plus an MCAP file for Foxglove
    metricslam poses --out est.txt                                  # until Ctrl-C

Writes one line per frame in frame order (KITTI: 3x4 ``T_world_cam`` row-major; TUM:
``t tx ty tz qx qy qz qw``). ``--trajectory`` writes the service's optimized trajectory
(queried at the end) instead of the live poses. Fails if fewer than ``--frames`` poses arrived.
Without ``--frames`` it records until Ctrl-C (or ``--timeout``) and writes frames 0 up to the
last one that arrived (frames missing among them are reported, not an error: nobody said how many
to expect).

Only poses with a metric scale are recorded: ``provisional`` (the initial estimate, or fewer
learned scale factors than needed to call it established) and ``metric``. ``unscaled`` poses
(the VO's arbitrary units: no depth source, or the VO had no map yet) are skipped and counted —
left out of a TUM file, a placeholder line in a KITTI file (one line per frame;
:func:`~metricslam_slam.tools.recording.write_poses`) — unless ``--all``.

Says when the SLAM service started a new session for the camera during the recording (and why:
``session_restarted`` "new session …", e.g. a second replay whose frames went back), and when the
service restarted (its health answer's ``instance`` changed, or a continuing
``session_restarted``): frames missing then are blamed on the restart, not the replay rate.

With a saved map in the SLAM service (``SLAM_MAP``, docs/maps.md), once poses arrive in the map
frame (``frame_id "map"``) only those are written, as ``run --map`` writes them: the frames before
the first map-frame one are in the session's own frame, are counted and left out (a KITTI file's
first line is then that frame, which is printed).
"""

from __future__ import annotations

import argparse

from metricslam.endpoints import DEFAULT_ZENOH_ENDPOINT
from metricslam.errors import ConfigError
from metricslam_cli.extras import require

#: --timeout with --frames
DEFAULT_TIMEOUT_S = 120.0


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "poses", help="record live poses from zenoh into a KITTI/TUM file",
        description="Subscribes to metricslam/<camera_id>/pose until --frames poses arrived, "
        "--timeout passed or Ctrl-C, and writes them in frame order.")
    p.add_argument("--zenoh-endpoint", default=DEFAULT_ZENOH_ENDPOINT, metavar="EP",
                   help="zenoh router to subscribe through")
    p.add_argument("--out", required=True, metavar="FILE", help="trajectory file to write")
    p.add_argument("--frames", type=int, metavar="N",
                   help="poses (frames 0..N-1) to wait for; fails if some never arrive (default: none, "
                        "record until Ctrl-C or --timeout)")
    p.add_argument("--timeout", type=float, metavar="S",
                   help=f"give up waiting after S seconds (default: {DEFAULT_TIMEOUT_S:g} with --frames, "
                        "no limit without)")
    p.add_argument("--format", choices=("kitti", "tum"), default="kitti",
                   help="kitti: 3x4 T_world_cam per line, one line per frame; tum: t tx ty tz qx qy qz qw")
    p.add_argument("--camera-id", default="cam0", metavar="ID", help="the camera whose poses to record")
    p.add_argument("--all", dest="include_unscaled", action="store_true",
                   help="also record unscaled poses (the VO's arbitrary units); by default they are "
                        "skipped and counted (KITTI: a placeholder line each, TUM: left out)")
    p.add_argument("--trajectory", action="store_true",
                   help="write the optimized trajectory instead of live poses (asked at the end, once "
                        "three answers 0.5 s apart agree, at most 10 s)")
    p.add_argument("--finish", action="store_true",
                   help="with --trajectory: first close the camera in the service (its newest "
                        "keyframes join the global graph, the final solve runs), then write its final "
                        "trajectory, as `metricslam run` does at the end; its next frame continues it")
    p.add_argument("--mcap", metavar="OUT.mcap",
                   help="also write an MCAP recording for Foxglove (ros extra): poses, path updates, "
                        "keyframe images (if the service sends them), depth maps, landmarks "
                        "(docs/recordings.md)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    require("slam-service", command="poses")
    if args.finish and not args.trajectory:
        raise ConfigError("--finish closes the camera to write its final trajectory: it needs --trajectory")

    import time

    from metricslam_slam.tools.client import (
        PoseRecorder, finish_camera, new_sessions, query_health, query_trajectory, service_restart,
        settled_trajectory,
    )
    from metricslam_slam.tools.recording import missing_error, missing_frames, unscaled_frames, write_mcap, write_poses
    from metricslam_slam.zenoh_config import open_client

    session = open_client(args.zenoh_endpoint)
    try:
        recorder = PoseRecorder(session, args.camera_id, map_topics=bool(args.mcap))
        health_before = query_health(session, timeout_s=2.0)
        print(f"recording metricslam/{args.camera_id}/pose ..."
              + (" (Ctrl-C to stop)" if args.frames is None else ""), flush=True)
        interrupted = _record(recorder, args.frames, args.timeout)
        if args.mcap and not interrupted:  # the last keyframe's landmarks, depth and path follow its pose
            time.sleep(1.0)
        recorder.close()
        statuses = recorder.statuses_so_far()
        restart = service_restart(health_before, query_health(session, timeout_s=2.0), statuses)
        trajectory = None
        if args.trajectory and args.finish:  # closed: the answer is final, nothing left to settle
            finish_camera(session, args.camera_id, "metricslam poses --trajectory --finish")
            trajectory = query_trajectory(session, args.camera_id)
        elif args.trajectory:  # after the last pose its keyframe's depth and solve may still run
            trajectory = settled_trajectory(lambda: query_trajectory(session, args.camera_id))
    finally:
        session.close()
    n_frames = args.frames if args.frames is not None else _frames_seen(recorder.poses, trajectory)
    poses, recorded, first_map = recorder.poses, trajectory, _first_map_frame(recorder.poses, trajectory)
    if first_map is not None:  # relocalized into the service's map: write the map frame only
        poses, trajectory, n_frames = _from_frame(poses, trajectory, n_frames, first_map)
        print(f"poses in the map frame from frame {first_map} on (the file's first "
              f"{'line' if args.format == 'kitti' else 'timestamp'} is that frame); the {first_map} frames "
              "before it are in the session's own frame and left out", flush=True)
    for detail in new_sessions(statuses):
        print(f"the SLAM service started a {detail} (camera {args.camera_id})", flush=True)
    if restart is not None:
        print(f"the SLAM service restarted during the recording: {restart}", flush=True)
    if args.mcap:  # before the pose file, which fails when frames are missing
        counts = write_mcap(args.mcap, args.camera_id, recorder, recorded)
        print(f"wrote {sum(counts.values())} messages on {len(counts)} topics to {args.mcap}")
    unscaled = unscaled_frames(poses, trajectory, n_frames)
    skip = [] if args.include_unscaled else unscaled
    n_written = write_poses(args.out, args.format, poses, trajectory, n_frames, skip, missing_ok=True)
    print(f"wrote {n_written} poses to {args.out} ({_states(poses, trajectory, n_frames)})")
    where = "left out" if args.format == "tum" else "a placeholder line each"
    if skip:
        print(f"skipped {len(skip)} unscaled poses (frames {_ranges(skip)}; {where}); --all records them")
    missing = missing_frames(poses, trajectory, n_frames)
    if missing and args.frames is None:  # nothing was expected: say what is missing, no failure
        print(f"{len(missing)} of frames 0-{n_frames - 1} have no pose (frames {_ranges(missing)}; {where}; "
              "sent before the recording started?)")
    elif missing:  # what arrived is written; the run still fails, naming what did not
        raise missing_error(missing, args.frames, restart)
    return 0


def _record(recorder, n_frames: int | None, timeout_s: float | None) -> bool:
    """Wait for ``n_frames`` poses (None: until Ctrl-C) or ``timeout_s`` (None: the default with
    ``n_frames``, no limit without). True if Ctrl-C ended it (then the poses so far are kept).

    Ctrl-C sets a flag (a SIGINT handler) instead of raising KeyboardInterrupt wherever the main
    thread happens to be (inside a zenoh call or a lock), so stopping is always clean and prompt.
    """
    import signal
    import threading
    import time

    if timeout_s is None and n_frames is not None:
        timeout_s = DEFAULT_TIMEOUT_S
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    stop = threading.Event()

    def finished(r) -> bool:
        return stop.is_set() or (n_frames is not None and len(r.poses) >= n_frames)

    # only the main thread may install a handler (a caller running the CLI in a thread keeps
    # Python's default: KeyboardInterrupt)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set()) if main_thread else None
    try:
        while deadline is None or time.monotonic() < deadline:
            left = 0.5 if deadline is None else min(0.5, deadline - time.monotonic())
            if recorder.wait_for(finished, max(left, 0.0)):
                break
    except KeyboardInterrupt:
        stop.set()
    finally:
        if main_thread:
            signal.signal(signal.SIGINT, previous)
    if stop.is_set():
        print("stopped (Ctrl-C); writing what arrived", flush=True)
        return True
    return False


def _first_map_frame(poses: dict, trajectory) -> int | None:
    """The first frame in the saved map's frame (``frame_id "map"``), or None when none is."""
    if trajectory is not None:
        in_map = trajectory.frame_id == "map" and len(trajectory.frame_index)
        return int(min(trajectory.frame_index)) if in_map else None
    return min((i for i, p in poses.items() if p.frame_id == "map"), default=None)


def _from_frame(poses: dict, trajectory, n_frames: int, first: int) -> tuple:
    """``(poses, trajectory, n_frames)`` renumbered so that frame ``first`` is frame 0, the frames
    before it dropped (map-frame poses only: world-frame ones after ``first`` are dropped too)."""
    kept = {i - first: p for i, p in poses.items() if i >= first and p.frame_id == "map"}
    if trajectory is not None:
        trajectory = trajectory.model_copy(update={"frame_index": trajectory.frame_index - first})
    return kept, trajectory, max(n_frames - first, 0)


def _frames_seen(poses: dict, trajectory) -> int:
    """Frames 0..K-1 up to the last one that has a pose (live, or in the optimized trajectory)."""
    indices = list(poses) if trajectory is None else [int(i) for i in trajectory.frame_index]
    return max(indices) + 1 if indices else 0


def _states(poses: dict, trajectory, n_frames: int) -> str:
    """``"2 unscaled, 22 provisional, 27 metric"`` over frames ``0..n_frames-1``."""
    from collections import Counter

    if trajectory is not None:
        return "optimized trajectory, scale " + ("established" if trajectory.scale_established else "not established")
    counts = Counter(poses[i].effective_scale_state().value for i in range(n_frames) if i in poses)
    return ", ".join(f"{counts.get(k, 0)} {k}" for k in ("unscaled", "provisional", "metric"))


def _ranges(frames: list[int]) -> str:
    """``[0, 1, 2, 7]`` -> ``"0-2, 7"``."""
    out: list[str] = []
    start = prev = None
    for i in sorted(frames) + [None]:
        if start is not None and (i is None or i != prev + 1):
            out.append(f"{start}" if start == prev else f"{start}-{prev}")
            start = None
        if i is not None and start is None:
            start = i
        prev = i
    return ", ".join(out)
