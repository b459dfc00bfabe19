"""Render the synthetic stereo training set of the depth network: many short, varied worlds.

Each world is its own seed (buildings, cars, textures, sun, traffic density, overpasses) laid
along a short piece of a real KITTI ground-truth trajectory (realistic speed and turning), taking
every ``--pose-step``-th pose so consecutive training pairs are metres apart, not centimetres.

Hold-out policy: the synthetic *test* sequences of the SLAM benchmarks use seeds < 1000 and no
traffic; this set uses seeds from ``--seed0`` (default 2000) and never KITTI 00's trajectory
(the 2 km synthetic benchmark drives along 00).

Run from the repository root (the data folder lives beside it)::

    python training/make_synth_set.py runs/synth_train --worlds 120 --frames 12
    python training/make_synth_set.py runs/synth_static --worlds 240 --seed0 3000 --no-traffic

Output: ``OUT/w{seed}/`` KITTI-layout folders that ``metricslam train`` configs list with a glob
(``runs/synth_train/w*``).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

#: KITTI GT trajectories used as paths (00 excluded: the 2 km synthetic SLAM benchmark uses it)
_TRAJECTORIES = ("01", "02", "03", "04", "05", "07", "08", "09", "10")


def main(argv: list[str] | None = None) -> int:
    from metricslam.trajectory.io import read_kitti_poses, write_kitti_poses
    from metricslam.synth import SynthConfig, generate_sequence
    from metricslam.synth.world import WorldConfig

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out_dir")
    p.add_argument("--worlds", type=int, default=120)
    p.add_argument("--frames", type=int, default=12, help="frames per world")
    p.add_argument("--pose-step", type=int, default=3, help="take every N-th GT pose")
    p.add_argument("--seed0", type=int, default=2000)
    p.add_argument("--poses-dir", default="../shared/data/kitti_gt_poses_full")
    p.add_argument("--no-traffic", action="store_true",
                   help="empty roads and no overpasses (the SLAM benchmark worlds' kind); building "
                        "and parked-car density still vary per world")
    args = p.parse_args(argv)

    out = Path(args.out_dir)
    tmp = out / "_paths"
    tmp.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for i in range(args.worlds):
        seed = args.seed0 + i
        folder = out / f"w{seed}"
        if (folder / "image_1" / f"{args.frames - 1:06d}.png").is_file():
            continue  # resumable
        rng = np.random.default_rng([seed, 77])
        name = _TRAJECTORIES[i % len(_TRAJECTORIES)]
        poses = read_kitti_poses(Path(args.poses_dir) / f"{name}.txt")
        span = args.frames * args.pose_step
        start = int(rng.integers(0, max(1, len(poses) - span)))
        sub = poses[start:start + span:args.pose_step]
        path_file = tmp / f"w{seed}.txt"
        write_kitti_poses(path_file, sub)
        # drawn with or without --no-traffic, so a seed's other draws (buildings, cars) stay the same
        traffic = float(rng.choice([0.0, rng.uniform(3, 25)], p=[0.15, 0.85]))
        bridges = float(rng.choice([0.0, rng.uniform(5, 30)], p=[0.5, 0.5]))
        world = WorldConfig(traffic_per_100m=0.0 if args.no_traffic else traffic,
                            bridges_per_km=0.0 if args.no_traffic else bridges,
                            building_probability=float(rng.uniform(0.4, 0.95)),
                            car_probability=float(rng.uniform(0.2, 0.9)))
        if folder.exists():  # a world interrupted half-way: render it again
            shutil.rmtree(folder)
        generate_sequence(folder, len(sub), seed, trajectory=path_file, config=SynthConfig(world=world))
        print(f"[{i + 1}/{args.worlds}] {folder} along KITTI {name} from pose {start} "
              f"traffic {world.traffic_per_100m:.1f}/100m bridges {world.bridges_per_km:.1f}/km "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
