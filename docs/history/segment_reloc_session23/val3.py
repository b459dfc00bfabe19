"""Held-out validation of own-map relocalization after tracking loss, third candidate (rule_segment_reloc3_session23.md).

Usage: PYTHONPATH=<tree>/shared:<tree>/cli:<tree>:<tree>/services/slam python val.py TAG OUT.jsonl
"""
import sys

from val import K01, K13, K13_POSES, main, world

SEEDS, SHORT_SEEDS = range(175, 185), range(185, 195)


def scenarios():
    out = []
    for s in SEEDS:
        w = world(s)
        p = w / "poses" / "00.txt"
        out.append((f"kidnap {s}", "kidnap", [(w, range(0, 120), p), (w, range(265, 300), p)], 120, False))
        out.append((f"short gap {s}", "short", [(w, range(0, 100), p), (w, range(108, 300), p)], 100, False))
        w2 = world(s + 1 if s < 184 else 175)
        out.append((f"foreign {s}->{s + 1 if s < 184 else 175}", "foreign", [(w, range(0, 150), None), (w2, range(150, 300), None)], 150, False))
    for s in SHORT_SEEDS:  # 150-frame loops, the gaps of bench.tracking_loss's "other"
        w = world(s, 150)
        p = w / "poses" / "00.txt"
        for a, b in ((40, 47), (90, 99)):
            out.append((f"loop150 {s} drop {a}-{b - 1}", "short", [(w, range(0, a), p), (w, range(b, 150), p)], a, False))
    out.append(("real revisit 0013 c", "kidnap", [(K13, range(1, 144, 2), K13_POSES), (K13, range(40, 101, 2), K13_POSES)], 72, True))
    out.append(("real foreign 0013 odd->0001", "foreign", [(K13, range(1, 100, 2), None), (K01, range(0, 54), None)], 50, True))
    return out


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], scenarios)
