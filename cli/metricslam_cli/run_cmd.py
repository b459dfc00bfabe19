"""``metricslam run``: the whole system offline on a dataset folder.

Example::

    metricslam run ../shared/data/kitti_odometry/sequences/06 --out est06.txt --json stats.json
    metricslam run SEQ --no-scale --out est.txt       # baseline: nothing learned anywhere
    metricslam run SEQ --vo-only --out est.txt        # local VO alone, no global graph
    metricslam run SEQ --deterministic --out est.txt  # no worker threads: reproducible
    metricslam run TUM_SEQ --calib cam.yaml --format tum --out est.tum   # your intrinsics
    metricslam run SEQ --out est.txt --rerun run.rrd  # plus a Rerun recording (viz extra)
    metricslam run SEQ --out est.txt --mcap run.mcap  # plus an MCAP file for Foxglove (ros extra)
    metricslam run SEQ --out est.txt --live-out live.txt --continuous-out cont.txt  # the streams

Writes one KITTI pose line (``T_world_cam``, 3x4 row-major) per input frame (``--format tum``:
one ``t tx ty tz qx qy qz qw`` line per frame that has a pose). A frame that cannot be read
(missing, truncated, corrupt, wrong size) is logged and processed as an invalid frame
(:class:`~metricslam.datasets.frame_reader.FrameReader`); frames without a pose of their own
are interpolated or marked (:meth:`SlamPipeline.trajectory`; docs/usage.md says what each output
format does with them). ``--live-out`` writes every frame's pose as it was published live (before
later optimization moved it) and ``--continuous-out`` the continuous odometry stream beside it
(:mod:`metricslam.trajectory.continuous`; an observer: ``--out`` is the same with or without it). ``--json`` writes the run statistics (:meth:`SlamPipeline.stats`:
counters, ms per stage, back end), the frames that were unreadable, interpolated or left without
a pose (:func:`pose_gap_stats`), plus the scale estimate over time
(:meth:`SlamPipeline.scale_history`, units in :mod:`metricslam.slam.scale_history`):

* ``scale_history`` — one dict per marginalized keyframe: ``frame_index``, ``t_ns``;
  ``scale_live``, the running product of the warp scales applied to the VO until then (world
  units per unit of the VO's initial frame ``VO₀``: the live VO→metric factor); the keyframe's
  final optimized Sim(3) scale ``scale_kf_optimized`` (of ``S_world_kf``: world units per
  keyframe VO unit) and ``scale_optimized = scale_kf_optimized · scale_live`` (per ``VO₀``
  unit); ``scale_factors`` (how many learned scale measurements ``ξ_j/z_j`` the keyframe got; 0
  when its depth request was dropped or failed) and their median ``scale_measured_median``
  (metres per keyframe VO unit); ``step_vo`` (VO distance from the previous keyframe, keyframe
  VO units; for a ground-truth reference). World units are metres in metric mode, and the
  first keyframe's VO units with ``--no-scale`` / ``--vo-only`` (the VO's arbitrary scale).
* ``vo_suspect_frames`` / ``vo_suspect_ranges`` — frames whose VO tracks may be aliased on
  repeating texture (or inside a two-view start its frames do not confirm), and their
  ``[first, last]`` ranges (``metricslam.slam.vo.aliasing``; a warning line names them).
* ``scale_corrections`` — one dict per applied warp: ``frame_index``, ``t_ns``, its scale ``s``
  and ``scale_live`` after it.
* ``scale_states`` — how many frames' poses were ``unscaled`` / ``provisional`` / ``metric`` when
  processed (:class:`~metricslam.slam.types.ScaleState`), ``first_metric_frame``, and
  ``initial_scale`` (the provisional scale at VO initialization; None when off, as it is offline
  unless the config's ``initial_scale`` section turns it on).
* ``scale_engaged`` (metric mode only) — whether the learned scale fixed the metric scale by the
  end of the run (:attr:`GlobalBackend.scale_established`: ``scale_factors_solved`` learned
  scale factors in the final solve, at least ``scale_factors_needed``).

Nothing is silently non-metric: a depth model that cannot be loaded is an error before the first
frame, and a metric run (no ``--no-scale`` / ``--vo-only``) whose learned scale never engaged
still writes its files but says so (``scale: NOT metric`` in the summary, one error line) and
exits with code 1. Output paths are checked before the first frame too.
"""

from __future__ import annotations

import argparse

from metricslam_cli.map_options import MapRun, add_map_options
from metricslam_cli.scale_options import add_scale_options, log_scale_sources, scale_flags


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run",
        help="run SLAM offline on a sequence folder and write its trajectory",
        description="Runs the local VO and the global Sim(3) graph in-process on a sequence "
        "folder (KITTI odometry, EuRoC MAV, TUM RGB-D, metricslam synth output), writing one KITTI "
        "pose line per input frame (or a TUM trajectory file, --format tum) and optional run statistics. By default learned scale factors "
        "make the trajectory metric; --no-scale is the geometric baseline.",
    )
    p.add_argument("seq_dir", metavar="SEQ_DIR",
                   help="sequence folder: KITTI odometry (image_0/), EuRoC MAV (mav0/), TUM RGB-D (rgb.txt), "
                        "or `metricslam synth` output")
    p.add_argument("--out", required=True, metavar="EST.txt", help="pose file to write")
    p.add_argument("--format", choices=("kitti", "tum"), default="kitti",
                   help="kitti (default): one line per input frame, a placeholder for a frame "
                        "without a pose (listed in --json); tum: timestamped lines, frames without "
                        "a pose left out (the TUM RGB-D trajectory format: t tx ty tz qx qy qz qw)")
    p.add_argument("--json", metavar="STATS.json", help="write run statistics as JSON")
    p.add_argument("--calib", metavar="FILE.yaml",
                   help="camera calibration (metricslam, OpenCV FileStorage or EuRoC sensor.yaml "
                        "YAML; docs/calibration.md) replacing whatever the dataset reader would "
                        "use; images are undistorted once at load when it has distortion. Needed "
                        "for a TUM-layout folder whose name names no Freiburg camera")
    p.add_argument("--rerun", metavar="OUT.rrd",
                   help="also write a Rerun recording (rerun-sdk, the viz extra) with the SLAM "
                        "service's entities: camera, image, trajectory, keyframes, landmarks, "
                        "keyframe depth maps; open it with `rerun OUT.rrd`")
    p.add_argument("--mcap", metavar="OUT.mcap",
                   help="also write an MCAP recording for Foxglove (the ros extra): every frame's "
                        "pose, the optimized path, keyframe images, coarse depth maps and "
                        "landmarks as ROS 2 messages (docs/recordings.md)")
    p.add_argument("--live-out", metavar="LIVE.txt",
                   help="also write every frame's live pose, as the SLAM service publishes it on "
                        "…/pose (one line per frame, in --format)")
    p.add_argument("--continuous-out", metavar="CONT.txt",
                   help="also write the continuous odometry stream (…/odom: corrections blended "
                        "in over --continuous-horizon; metricslam.trajectory.continuous)")
    p.add_argument("--continuous-horizon", type=float, default=None, metavar="S",
                   help="seconds over which the continuous stream blends a correction in "
                        "(default: ContinuousOdometryConfig's)")
    p.add_argument("--no-scale", action="store_true",
                   help="no learned scale factors (scale fixed by the monocular initialization)")
    p.add_argument("--vo-only", action="store_true",
                   help="local VO only, no global graph (implies --no-scale)")
    p.add_argument("--preset", default=None, choices=("kitti", "euroc", "tum", "synth"),
                   help="VO parameter preset (default: the config's vo.preset, else from the "
                        "dataset format)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="process only the first N frames")
    p.add_argument("--model", default=None, metavar="PATH",
                   help="ONNX depth model (default: the config's depth.model_path, else the "
                        "shipped one)")
    p.add_argument("--depth-queue", type=int, default=None, metavar="N",
                   help="keyframes that may wait for depth (default: the config's "
                        "graph.depth_queue_size, else OFFLINE_DEPTH_QUEUE_SIZE of "
                        "metricslam.slam.graph.config, 256). Offline runs wait instead of "
                        "dropping, so results do not depend on machine load; the live service "
                        "keeps a short queue and drops the oldest")
    p.add_argument("--config", metavar="FILE.yaml",
                   help="system configuration (sections vo, graph, depth, queues; see "
                        "metricslam.slam.config_file; default $METRICSLAM_CONFIG); METRICSLAM_* "
                        "environment variables and these flags override it; checked before any "
                        "frame is processed")
    p.add_argument("--deterministic", action="store_true",
                   help="run bundle adjustment, depth and the global solve in the frame loop "
                        "instead of worker threads: the same input gives the same trajectory, "
                        "byte for byte (benchmarks, regression checks); slower, and unlike the "
                        "live system every keyframe's scale arrives before the next frame")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_scale_options(p)
    add_map_options(p)
    p.set_defaults(func=run)
    return p


def config_from_args(args: argparse.Namespace):
    """The run's :class:`~metricslam.slam.system_config.SystemConfig`: class defaults → the
    offline depth queue → ``--config`` (or ``$METRICSLAM_CONFIG``) → ``METRICSLAM_*`` → flags."""
    from metricslam.slam.config_file import load_system_config
    from metricslam.slam.graph.config import OFFLINE_DEPTH_QUEUE_SIZE

    flags: dict = {}
    if args.preset is not None:
        flags["vo"] = {"preset": args.preset}
    if args.depth_queue is not None:
        flags["graph"] = {"depth_queue_size": args.depth_queue}
    if args.model is not None:
        flags.setdefault("depth", {})["model_path"] = args.model
    if args.no_scale:
        flags.setdefault("depth", {})["use_scale"] = False
    if args.vo_only:
        flags["vo_only"] = True
    if args.deterministic:
        flags["deterministic"] = True
    calib_height = None
    if getattr(args, "calib", None):
        from metricslam.calibration import load_calibration

        calib_height = load_calibration(args.calib).mount_height_m
    scale_profile, scale_overrides = scale_flags(args, calib_height)
    return load_system_config(args.config, profile={"graph": {"depth_queue_size": OFFLINE_DEPTH_QUEUE_SIZE},
                                                    **scale_profile},
                              overrides={**flags, **scale_overrides})


def run(args: argparse.Namespace) -> int:
    import json
    import logging
    import time
    from pathlib import Path

    import numpy as np
    from tqdm import tqdm

    from metricslam.calibration import load_calibration
    from metricslam.datasets import open_sequence
    from metricslam.datasets.frame_reader import FrameReader
    from metricslam.errors import ConfigError, ScaleError
    from metricslam.ros2.session_log import SessionRecorder
    from metricslam.slam.depth_source import OnnxDepthSource
    from metricslam.slam.session_builder import build_session, preset_for
    from metricslam.slam.vo.aliasing import describe_ranges
    from metricslam.trajectory.io import write_kitti_poses, write_tum

    config = config_from_args(args)
    log_scale_sources(config, logging.getLogger("metricslam.run"))
    for flag, path in (("--out", args.out), ("--json", args.json), ("--live-out", args.live_out),
                       ("--continuous-out", args.continuous_out)):
        if path:
            check_output_path(path, flag)  # not after the whole sequence was processed
    depth_source = None
    if config.use_scale:  # a model that cannot load fails here, not once per keyframe
        depth_source = OnnxDepthSource(config.depth.model_path).load()
    viewer = open_recording(args.rerun) if args.rerun else None
    calibration = load_calibration(args.calib) if args.calib else None
    seq = open_sequence(args.seq_dir, calibration=calibration)
    preset = config.vo.preset or preset_for(args.seq_dir)
    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f"--max-frames must be >= 1, got {args.max_frames}")
    n = len(seq) if args.max_frames is None else min(len(seq), args.max_frames)
    frames = FrameReader(seq)
    maps = MapRun(args, config, seq.camera) if (args.map or args.save_map) else None
    mcap_log = open_mcap(args.mcap, camera_id(seq.name)) if args.mcap else None  # before any thread
    pipeline = build_session(seq.camera, config, depth_source=depth_source, default_preset=preset)
    logging.getLogger("metricslam.run").info("VO config (%s preset): %s", preset,
                                             pipeline.vo.config.model_dump())
    logging.getLogger("metricslam.run").info("camera%s: %s", f" (from {args.calib})" if args.calib else "",
                                             seq.camera)
    if maps is not None:
        maps.attach(pipeline)
    if viewer is not None:
        viewer.attach(pipeline, camera_id(seq.name))  # depth maps and scale records: back-end events
    recorder = (SessionRecorder(mcap_log, pipeline, maps.localization if maps is not None else None)
                if mcap_log is not None else None)  # with --map, the final path in the map frame too
    streams = None
    if args.live_out or args.continuous_out:
        from metricslam_cli.live_streams import LiveStreams

        streams = LiveStreams(pipeline, args.continuous_horizon)
    t0 = time.perf_counter()
    try:
        for i in tqdm(range(n), desc=f"run {Path(args.seq_dir).name}", unit="frame",
                      disable=args.no_progress):
            frame = frames[i]
            est = pipeline.process(frame)
            if viewer is not None:
                viewer.log(camera_id(seq.name), frame, est, pipeline)
            if recorder is not None:
                recorder.after_frame(frame, est)
            if streams is not None:
                streams.after_frame(est)
    finally:
        pipeline.close()
        if viewer is not None:
            viewer.close()
        if recorder is not None:
            recorder.close()  # the final optimized path, after the last solve; closes the file
    wall_s = time.perf_counter() - t0
    traj = pipeline.trajectory()
    if maps is not None:  # the map saved; with --map, map-frame poses from the relocalized frame on
        traj = maps.finish(pipeline, traj)
    if args.format == "tum":
        kept = [e for e in traj if e.pose_valid]
        write_tum(args.out, np.array([e.t_ns for e in kept], dtype=np.int64),
                  np.array([e.T_world_cam for e in kept]).reshape(-1, 4, 4))
    else:
        write_kitti_poses(args.out, np.array([e.T_world_cam for e in traj]).reshape(-1, 4, 4))
    if streams is not None:
        streams.write(args.live_out, args.continuous_out, args.format)
    stats = pipeline.stats()
    if streams is not None:
        stats["continuous"] = streams.stats()
    stats.update(pose_gap_stats(traj, frames.unreadable))
    stats.update(pipeline.scale_history())
    if maps is not None:
        stats.update(maps.stats())
    stats.update({"sequence": str(args.seq_dir), "preset": preset, "wall_s": wall_s,
                  "fps": n / wall_s if wall_s > 0 else None, "mode": config.mode,
                  "deterministic": config.deterministic,
                  "config": config.model_dump(mode="json")})
    if config.use_scale:
        stats["scale_engaged"] = bool(pipeline.backend.scale_established)
        stats["scale_factors_needed"] = config.graph_config().min_scale_factors_established
        stats["scale_factors_solved"] = pipeline.backend.scale_factors_solved
    print(f"{n} frames, {stats['keyframes']} keyframes, {stats['tracking_losses']} tracking "
          f"losses, {stats['fps']:.1f} frames/s (including image loading) -> {args.out}")
    if config.use_scale:
        print(scale_summary(stats))
    if maps is not None and maps.summary():
        print(maps.summary())
    if stats["frames_unreadable"] or stats["interpolated"] or stats["pose_invalid"]:
        print(f"{stats['frames_unreadable']} unreadable frames, {stats['interpolated']} poses "
              f"interpolated, {stats['pose_invalid']} frames without a pose (frame lists in --json)")
    if relocated := stats.get("backend", {}).get("relocalized_segments"):
        print(f"{len(relocated)} tracking segment(s) relocalized in this run's own map after a tracking loss (at frames "
              f"{', '.join(map(str, relocated.values()))}): placed there, not where the camera's last motion led")
    if stats["vo_suspect_frames"]:
        print(f"warning: {stats['vo_suspect_frames']} frames whose VO tracks may be aliased on repeating texture "
              f"(frames {describe_ranges(stats['vo_suspect_ranges'])}): the trajectory's shape may be wrong from "
              "there (docs/vo.md, 'Aliased tracks')")
    if args.json:
        out = Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(stats, indent=2, default=float) + "\n")
    if maps is not None:
        maps.raise_if_not_relocalized()
    if config.use_scale and not stats["scale_engaged"]:
        raise ScaleError(f"learned scale never engaged, so {args.out} is not metric (the VO's arbitrary "
                         f"scale, not metres; {scale_summary(stats)}). Check the depth model "
                         "(--model, the config's depth.model_path) and the warnings above, or give a "
                         "longer sequence; pass --no-scale if an unscaled trajectory is what you want")
    return 0


def scale_summary(stats: dict) -> str:
    """One line on the learned scale of a metric-mode run, from its :meth:`SlamPipeline.stats`
    plus ``scale_engaged`` / ``scale_factors_solved`` / ``scale_factors_needed``: metric from
    which frame, or why not."""
    backend = stats.get("backend") or {}
    states = stats.get("scale_states") or {}
    requests = (f"{backend.get('depth_requests', 0)} depth requests ({backend.get('depth_failures', 0)} "
                f"failed, {backend.get('depth_dropped', 0)} dropped)")
    if not stats.get("scale_engaged"):
        return (f"scale: NOT metric, {stats.get('scale_factors_solved', 0)} learned scale factors in "
                f"the final solve, {stats.get('scale_factors_needed')} needed; {requests}")
    first = stats.get("first_metric_frame")
    when = "after the final solve" if first is None else f"from frame {first}"
    return (f"scale: metric {when} ({states.get('metric', 0)} of {stats.get('frames', 0)} frames "
            f"metric when processed), {stats.get('scale_factors_solved', 0)} learned scale factors; "
            f"{requests}")


def check_output_path(path: str, flag: str) -> None:
    """Refuse, before any frame is processed, an output path that cannot be written: a folder,
    a path through a file, a folder without write permission. Creates missing parent folders
    (the writers would) and leaves an existing file as it is.

    Raises:
        ConfigError: naming the flag, the path and what to do.
    """
    import os
    from pathlib import Path

    from metricslam.errors import ConfigError

    out = Path(path)
    if out.is_dir():
        raise ConfigError(f"{flag} {path} is a folder: name a file to write, e.g. "
                          f"{out / ('stats.json' if flag == '--json' else 'est.txt')}")
    existed = out.exists()
    above = next((p for p in out.parents if p.exists()), None)
    if above is not None and not above.is_dir():
        raise ConfigError(f"{flag} {path} cannot be written: {above} is a file, not a folder")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with out.open("ab"):
            pass
    except OSError as exc:
        raise ConfigError(f"{flag} {path} cannot be written ({exc.strerror or exc}): choose a "
                          "file in a folder you can write to") from exc
    if not existed:
        os.unlink(out)


def open_recording(target: str):
    """The ``--rerun`` recording: a :class:`metricslam.rerun_view.RerunView` writing ``target``
    (a ``.rrd`` path; an offline run has no live viewer to serve). Raises ConfigError, before
    any frame is read, for another target or when rerun-sdk is not installed."""
    from metricslam.errors import ConfigError
    from metricslam.rerun_view import RerunView

    if not target.endswith(".rrd"):
        raise ConfigError(f"run --rerun takes a recording path ending in .rrd, got {target!r} "
                          "(the live web viewer is the SLAM service's: slam-service --rerun web)")
    return RerunView(target)


def open_mcap(path: str, cam_id: str):
    """The ``--mcap`` file: a :class:`metricslam.ros2.mcap_log.McapLog` (a
    :class:`~metricslam.ros2.session_log.SessionRecorder` feeds it from the pipeline). Raises
    ConfigError, before any frame is read, when the ros extra is not installed."""
    from metricslam.ros2.mcap_log import McapLog

    return McapLog(path, camera_id=cam_id)


def camera_id(name: str) -> str:
    """The recording's camera id (``world/<id>/…``): the sequence name in key-safe characters."""
    import re

    return re.sub(r"[^A-Za-z0-9._-]", "_", name) or "cam0"


def pose_gap_stats(trajectory: list, unreadable: list[int]) -> dict:
    """JSON-ready counts and frame indices of the frames that needed help.

    ``frames_unreadable`` / ``unreadable_frame_indices``: image files that could not be read;
    ``interpolated`` / ``interpolated_frame_indices``: poses interpolated between neighbours;
    ``pose_invalid`` / ``pose_invalid_frame_indices``: frames left without a pose (a
    placeholder in KITTI files, left out of TUM files).
    """
    interp = [int(e.frame_index) for e in trajectory if e.interpolated]
    invalid = [int(e.frame_index) for e in trajectory if not e.pose_valid]
    return {"frames_unreadable": len(unreadable), "unreadable_frame_indices": sorted(unreadable),
            "interpolated": len(interp), "interpolated_frame_indices": interp,
            "pose_invalid": len(invalid), "pose_invalid_frame_indices": invalid}
