"""Test support: a KITTI-layout sequence folder cut out of another (frames renumbered from 0).

A second session "starting elsewhere" on a rendered loop is frames ``start .. stop-1`` of the same
render, as its own folder: the same world, a different first frame. Its ``poses/00.txt`` stays in
the source's world frame (the first source frame's camera), which is the frame a map built from
the source's first frames lives in, so it is that session's ground truth *in the map frame*.
"""

from __future__ import annotations

import shutil
from pathlib import Path


def cut_sequence(src: Path, dst: Path, start: int, stop: int) -> Path:
    """Copy frames ``start .. stop-1`` of the KITTI-layout folder ``src`` to ``dst``."""
    src, dst = Path(src), Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    for sub in ("image_0", "image_1", "depth_0"):
        if (src / sub).is_dir():
            (dst / sub).mkdir(exist_ok=True)
            for j, i in enumerate(range(start, stop)):
                shutil.copy(src / sub / f"{i:06d}.png", dst / sub / f"{j:06d}.png")
    times = (src / "times.txt").read_text().split()[start:stop]
    (dst / "times.txt").write_text("".join(f"{t}\n" for t in times))
    if (src / "poses" / "00.txt").is_file():
        (dst / "poses").mkdir(exist_ok=True)
        lines = (src / "poses" / "00.txt").read_text().splitlines()[start:stop]
        (dst / "poses" / "00.txt").write_text("".join(f"{ln}\n" for ln in lines))
    return dst
