"""Place-recognition recall of the loop detector's bag-of-words retrieval, offline, per vocabulary.

Every ``--step``-th frame of a rendered or KITTI sequence with revisits is a "keyframe": its ORB
descriptors are computed by the detector's own :func:`~metricslam.slam.loop.detector.retrieval_descriptors`
with the default ``LoopConfig`` (half-size image, 500 features) and added to a :class:`BowDatabase`;
each keyframe then queries the older ones (the most recent ``--skip`` excluded, as in
``LoopConfig.skip_recent_keyframes``). A query "has a true place" when some older keyframe is
within ``--radius-m`` by ground truth; we report recall@5 (a true place among the 5 candidates
the detector would verify) and the median rank of the best true place. Vocabularies: trained
online on the run's first 12 keyframes (what the detector does) and offline on training images
(``--train-glob``), each at several sizes. No verification, no SLAM: retrieval only.

Example::

    .venv/bin/python -m bench.loop_retrieval --seq /tmp/s3/val00 --seq /tmp/h12_synth00 \\
        --train-glob 'runs/synth_train/w2*/image_0/*.png' --out bench/results/loop_retrieval
"""

from __future__ import annotations

import argparse
import glob
import sys
from pathlib import Path

import cv2
import numpy as np
from bench.machine import command_line, describe, write_results
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.loop.detector import retrieval_descriptors, retrieval_orb
from metricslam.slam.loop.vocabulary import BinaryVocabulary, BowDatabase
from metricslam.trajectory.io import read_kitti_poses



def image_descriptors(path: str, orb: cv2.ORB, config: LoopConfig) -> np.ndarray:
    """Retrieval descriptors of one image file, computed by the detector's own function."""
    gray = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise SystemExit(f"cannot read {path}")
    return retrieval_descriptors(orb, gray, config.image_scale)


def recall(vocab: BinaryVocabulary, descs: list[np.ndarray], positions_m: np.ndarray, skip: int,
           radius_m: float) -> dict:
    """recall@5 and median rank of the best true place over queries that have one."""
    db = BowDatabase(vocab.size)
    ranks = []
    for i, d in enumerate(descs):
        v = vocab.bow(d)
        db.add(i, v)
        if i <= skip:
            continue
        _, scores = db.scores(v, upto=i - skip)
        true = np.flatnonzero(np.linalg.norm(positions_m[: i - skip] - positions_m[i], axis=1) < radius_m)
        if true.size:
            ranks.append(int(np.min(np.flatnonzero(np.isin(np.argsort(-scores), true)))))
    r = np.array(ranks)
    return {"queries": int(r.size), "recall_at_5": float(np.mean(r < 5)) if r.size else None,
            "median_rank": float(np.median(r)) if r.size else None}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, type=Path, help="folder with image_0/ and poses/00.txt")
    p.add_argument("--train-glob", action="append", default=[], help="offline vocabulary training images")
    p.add_argument("--train-stride", type=int, default=3)
    p.add_argument("--words", type=int, nargs="+", default=[400, 1000])
    p.add_argument("--step", type=int, default=4, help="every n-th frame is a keyframe (default 4)")
    p.add_argument("--skip", type=int, default=30, help="most recent keyframes not queried")
    p.add_argument("--radius-m", type=float, default=10.0)
    p.add_argument("--out", help="write OUT.md and OUT.json")
    args = p.parse_args(argv)

    config = LoopConfig()
    orb = retrieval_orb(config)
    train_files = [f for g in args.train_glob for f in sorted(glob.glob(g))[:: args.train_stride]]
    train = [image_descriptors(f, orb, config) for f in train_files]
    rows = []
    for seq in args.seq:
        files = sorted((seq / "image_0").glob("*.png"))[:: args.step]
        pos = read_kitti_poses(seq / "poses" / "00.txt")[:: args.step, :3, 3][: len(files)]
        descs = [image_descriptors(str(f), orb, config) for f in files]
        for k in args.words:
            n_online = config.vocabulary_train_keyframes
            vocabs = {f"online, first {n_online} keyframes": BinaryVocabulary.train(descs[:n_online], k)}
            if train:
                vocabs[f"offline, {len(train)} training images"] = BinaryVocabulary.train(train, k)
            for name, vocab in vocabs.items():
                rows.append({"sequence": seq.name, "vocabulary": name, "words": k,
                             **recall(vocab, descs, pos, args.skip, args.radius_m)})
                print(rows[-1], flush=True)
    lines = ["| sequence | vocabulary | words | queries with a true place | recall@5 | median rank |",
             "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['sequence']} | {r['vocabulary']} | {r['words']} | {r['queries']} | {r['recall_at_5']:.2f} | "
              f"{r['median_rank']:.0f} |" for r in rows if r["queries"]]
    if args.out:
        command = command_line("bench.loop_retrieval", argv)
        md = (f"# Loop retrieval recall per vocabulary\n\nCommand: `{command}`  \nMachine: {describe()}\n\n"
              + "\n".join(lines) + "\n")
        write_results(args.out, {"command": command, "rows": rows}, md)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
