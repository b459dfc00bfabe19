"""``metricslam map info MAP [--json]`` and ``metricslam map keyframes MAP --out FILE``.

A saved map (``run --save-map``, the SLAM service's ``…/map/save``; format in docs/maps.md)
without running SLAM: ``info`` loads it — every file checked against its checksum, dtype and
shape, so a corrupt or foreign map fails here with the same one-line error a run would give —
and prints what it holds (counts, camera, depth model, the sessions that built it, the keyframes'
time span and extent, its size); ``--json`` writes the same as JSON to stdout. ``keyframes`` writes
each keyframe's map-frame pose ``T_map_kf`` (ordered by keyframe id) as a TUM file (its timestamps)
or a KITTI file, to plot the map or score it against ground truth with ``metricslam eval`` (a map
extended by later sessions has one clock per session: KITTI only).

Examples::

    metricslam map info maps/street
    metricslam map keyframes maps/street --out street_keyframes.txt --format tum
"""

from __future__ import annotations

import argparse
import json


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("map", help="inspect a saved map (info) or write its keyframe poses",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="map_command", metavar="MAP_COMMAND", required=True,
                           help="info: check the map and print what it holds; keyframes: write its keyframe poses")
    info = sub.add_parser("info", help="check a map and print what it holds")
    info.add_argument("map", help="the map folder")
    info.add_argument("--json", action="store_true", help="print the summary as JSON instead")
    info.set_defaults(func=run_info)
    kfs = sub.add_parser("keyframes", help="write the map's keyframe poses T_map_kf")
    kfs.add_argument("map", help="the map folder")
    kfs.add_argument("--out", required=True, help="output trajectory file")
    kfs.add_argument("--format", choices=["tum", "kitti"], default="tum",
                     help="tum: timestamped lines; kitti: one 3x4 line per keyframe")
    kfs.set_defaults(func=run_keyframes)
    return p


def run_info(args: argparse.Namespace) -> int:
    from metricslam.slam.map.format import load_map
    from metricslam.slam.map.summary import map_summary, summary_lines

    summary = map_summary(load_map(args.map), args.map)
    print(json.dumps(summary, indent=1) if args.json else "\n".join(summary_lines(summary)))
    return 0


def run_keyframes(args: argparse.Namespace) -> int:
    import numpy as np

    from metricslam.errors import MapError
    from metricslam.slam.map.format import load_map
    from metricslam.trajectory.io import write_kitti_poses, write_tum

    from metricslam_cli.run_cmd import check_output_path

    kf = load_map(args.map).arrays["keyframes"]
    check_output_path(args.out, "--out")
    order = np.argsort(kf["kf_id"], kind="stable")
    if args.format == "tum":
        if np.any(np.diff(kf["t_ns"][order]) <= 0):
            raise MapError(f"map {args.map}: its keyframe timestamps do not increase with their ids (a map "
                           "extended by later sessions, each on its own clock): use --format kitti")
        write_tum(args.out, kf["t_ns"][order], kf["T_map_kf"][order])
    else:
        write_kitti_poses(args.out, kf["T_map_kf"][order])
    print(f"{len(order)} keyframe poses ({args.format}) -> {args.out}")
    return 0
