"""Held-out validation of own-map relocalization after tracking loss, second candidate (rule_segment_reloc2_session23.md).

Usage: PYTHONPATH=<tree>/shared:<tree>/cli:<tree>:<tree>/services/slam python val.py TAG OUT.jsonl
"""
import sys

from val import K01, K13, K13_POSES, main, world

SEEDS = range(165, 175)


def scenarios():
    out = []
    for s in SEEDS:
        w = world(s)
        p = w / "poses" / "00.txt"
        out.append((f"kidnap {s}", "kidnap", [(w, range(0, 120), p), (w, range(265, 300), p)], 120, False))
        out.append((f"short gap {s}", "short", [(w, range(0, 100), p), (w, range(108, 300), p)], 100, False))
        w2 = world(s + 1 if s < 174 else 165)
        out.append((f"foreign {s}->{s + 1 if s < 174 else 165}", "foreign", [(w, range(0, 150), None), (w2, range(150, 300), None)], 150, False))
    out.append(("real revisit 0013 b", "kidnap", [(K13, range(0, 143, 2), K13_POSES), (K13, range(61, 122, 2), K13_POSES)], 72, True))
    out.append(("real foreign 0001->0013", "foreign", [(K01, range(0, 54), None), (K13, range(0, 60), None)], 54, True))
    return out


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], scenarios)
