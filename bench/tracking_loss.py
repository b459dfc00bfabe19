"""Tracking loss (issue #34 item 3; rule ``docs/history/rule_tracking_loss_session18.md``): frames
dropped from a sequence (the times kept, so the gap is real), ``metricslam run --deterministic``
with the default VO (the new segment starts where the mean motion of the last tracked frames,
kept up for the gap, takes the camera; ``coast_max_s``) and with ``coast_max_s: 0`` (it starts
at the last tracked pose). ATE SE(3) over every frame with a pose; tracking losses; segments
relocalized in the session's own map (``docs/maps.md``: loop drops 120-264 and 150-269 put the
camera down on lap two, where lap one mapped); ``set``: held out by a rule, or looked at in design.

Example::

    .venv/bin/python -m bench.tracking_loss --work /tmp/loss_bench --out bench/results/tracking_loss
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bench.machine import command_line, publish
from bench.maps import RENDERED, _ate_se3_m, cut, run
from metricslam.synth.scene import generate_sequence
from metricslam.trajectory.io import read_kitti_poses

#: name -> (source, first dropped frame, first frame after the gap, set); source: kitti06,
#: k13 (KITTI raw 0013, frames 0-143), loop (rendered, seed 3, 300 frames), other (seed 5, 150)
SCENARIOS = {
    **{f"kitti06 drop {a}-{b - 1}": ("kitti06", a, b, "held out") for a, b in ((15, 22), (30, 37))},
    **{f"loop drop {a}-{b - 1}": ("loop", a, b, "held out") for a, b in ((40, 47), (180, 191), (260, 269))},
    **{f"other drop {a}-{b - 1}": ("other", a, b, "held out") for a, b in ((40, 47), (90, 99))},
    "kitti06 no gap": ("kitti06", 0, 0, "held out"), "other no gap": ("other", 0, 0, "held out"),
    **{f"k13 drop {a}-{b - 1}": ("k13", a, b, "design") for a, b in ((20, 27), (50, 58), (70, 78), (100, 108))},
    **{f"loop drop {a}-{b - 1}": ("loop", a, b, "design")
       for a, b in ((60, 66), (60, 75), (100, 112), (120, 126), (150, 160), (200, 215), (230, 240), (120, 265),
                    (150, 270))},
    "loop no gap": ("loop", 0, 0, "design"),
}


def sources(work: Path, data: Path) -> dict[str, Path]:
    """The scenario sources as KITTI-layout folders with ``poses/00.txt``."""
    out = {"loop": work / "loop300", "other": work / "other150"}
    for name, seed, n in (("loop", 3, 300), ("other", 5, 150)):
        if not (out[name] / "poses" / "00.txt").is_file():
            generate_sequence(out[name], n, seed=seed, size=(620, 188), path="loop")
    odo, raw = data / "kitti_odometry", data / "kitti_raw_stereo"
    out["kitti06"] = cut(odo / "sequences" / "06", work / "kitti06", 0, 51, odo / "poses" / "06.txt")
    out["k13"] = cut(raw / "sequences" / "2011_09_26_drive_0013", work / "k13", 0, 144,
                     raw / "poses" / "2011_09_26_drive_0013.txt")
    return out


def scenario(seq: Path, no_coast: Path | None, kitti: bool) -> dict:
    """One run of ``seq`` (``no_coast``: that VO config file): ATE SE(3) (m), tracking losses."""
    # a cut folder is not recognized as a render; renders run with the model for rendered worlds
    flags = ("--preset", "kitti") if kitti else ("--model", RENDERED)
    if no_coast is not None:
        flags += ("--config", str(no_coast))
    out = seq.parent / f"{seq.name}_{'no_coast' if no_coast else 'coast'}.txt"
    _, st = run(seq, out, *flags)
    gt, est = read_kitti_poses(seq / "poses" / "00.txt"), read_kitti_poses(out)
    ok = [i for i in range(len(gt)) if i not in set(st["pose_invalid_frame_indices"])]
    return {"ate_se3_m": _ate_se3_m(est[ok], gt[ok]), "tracking_losses": st["tracking_losses"],
            "relocalized": len(st["backend"]["relocalized_segments"])}


def render(r: dict, command: str, machine: str) -> str:
    lines = ["# Tracking loss: where a new segment starts (bench/tracking_loss.py)", "",
             f"Command: `{command}`  ", f"Machine: {machine}", "", __doc__.split("\n\n")[0].replace("\n", " "), "",
             "| scenario | set | losses | relocalized | ATE SE(3), default | ATE SE(3), coast_max_s 0 |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, row in r["scenarios"].items():
        lines.append(f"| {name} | {row['set']} | {row['coast']['tracking_losses']} | {row['coast']['relocalized']} | "
                     f"{row['coast']['ate_se3_m']:.2f} m | {row['no_coast']['ate_se3_m']:.2f} m |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="scratch folder")
    ap.add_argument("--out", required=True, help="results path stem (writes .json and .md)")
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    args = ap.parse_args(argv)
    src = sources(args.work, args.data)
    no_coast = args.work / "no_coast.yaml"
    no_coast.write_text("vo:\n  coast_max_s: 0\n")
    rows = {}
    for name, (source, a, b, which) in SCENARIOS.items():
        n = len((src[source] / "times.txt").read_text().split())
        seq = cut(src[source], args.work / name.replace(" ", "_"), 0, n, skip=range(a, b))
        kitti = source in ("kitti06", "k13")
        rows[name] = {"set": which, "coast": scenario(seq, None, kitti), "no_coast": scenario(seq, no_coast, kitti)}
    publish(args.out, {"scenarios": rows}, command_line("bench.tracking_loss", argv), render)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
