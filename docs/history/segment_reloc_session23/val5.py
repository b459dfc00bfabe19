"""Held-out validation of own-map relocalization after tracking loss, fifth candidate (rule_segment_reloc5_session23.md).

Usage: PYTHONPATH=<tree>/shared:<tree>/cli:<tree>:<tree>/services/slam python val.py TAG OUT.jsonl
"""
import sys

from val import K01, K13, K13_POSES, loops150, main, per_seed

SEEDS, SHORT_SEEDS = list(range(215, 225)), range(225, 235)
GAP_S = 14.5  # a camera carried (or covered) that long: the loss is longer than the coasting covers


def scenarios():
    out = per_seed(SEEDS, GAP_S, 0.8) + loops150(SHORT_SEEDS, timed=True)
    out.append(("real revisit 0013 e", "kidnap", [(K13, range(0, 143, 2), K13_POSES), (K13, range(21, 100, 2), K13_POSES, GAP_S)], 72, True))
    out.append(("real foreign 0013->0001 e", "foreign", [(K13, range(0, 100, 2), None), (K01, range(0, 54), None, GAP_S)], 50, True))
    return out


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], scenarios)
