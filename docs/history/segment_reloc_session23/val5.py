"""Held-out validation of own-map relocalization after tracking loss, fifth candidate (rule_segment_reloc5_session23.md).

Usage: PYTHONPATH=<tree>/shared:<tree>/cli:<tree>:<tree>/services/slam python val.py TAG OUT.jsonl
"""
import sys

from val import K01, K13, K13_POSES, main, world

SEEDS, SHORT_SEEDS = range(215, 225), range(225, 235)
GAP_S = 14.5  # a camera carried (or covered) that long: the loss is longer than the coasting covers


def scenarios():
    out = []
    for s in SEEDS:
        w = world(s)
        p = w / "poses" / "00.txt"
        out.append((f"kidnap {s}", "kidnap", [(w, range(0, 120), p), (w, range(265, 300), p, GAP_S)], 120, False))
        out.append((f"short gap {s}", "short", [(w, range(0, 100), p), (w, range(108, 300), p, 0.8)], 100, False))
        w2 = world(s + 1 if s < 224 else 215)
        out.append((f"foreign {s}->{s + 1 if s < 224 else 215}", "foreign", [(w, range(0, 150), None), (w2, range(150, 300), None, GAP_S)], 150, False))
    for s in SHORT_SEEDS:  # 150-frame loops, the gaps of bench.tracking_loss's "other"
        w = world(s, 150)
        p = w / "poses" / "00.txt"
        for a, b in ((40, 47), (90, 99)):
            out.append((f"loop150 {s} drop {a}-{b - 1}", "short", [(w, range(0, a), p), (w, range(b, 150), p, 0.1 * (b - a))], a, False))
    out.append(("real revisit 0013 e", "kidnap", [(K13, range(0, 143, 2), K13_POSES), (K13, range(21, 100, 2), K13_POSES, GAP_S)], 72, True))
    out.append(("real foreign 0013->0001 e", "foreign", [(K13, range(0, 100, 2), None), (K01, range(0, 54), None, GAP_S)], 50, True))
    return out


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], scenarios)
