"""Held-out validation of own-map relocalization after tracking loss, fourth candidate (rule_segment_reloc4_session23.md).

Usage: PYTHONPATH=<tree>/shared:<tree>/cli:<tree>:<tree>/services/slam python val.py TAG OUT.jsonl
"""
import sys

from val import K01, K13, K13_POSES, loops150, main, per_seed

SEEDS, SHORT_SEEDS = list(range(195, 205)), range(205, 215)


def scenarios():
    out = per_seed(SEEDS) + loops150(SHORT_SEEDS)
    out.append(("real revisit 0013 d", "kidnap", [(K13, range(0, 143, 2), K13_POSES), (K13, range(1, 60, 2), K13_POSES)], 72, True))
    out.append(("real foreign 0001->0013 d", "foreign", [(K01, range(0, 54), None), (K13, range(80, 143, 2), None)], 54, True))
    return out


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], scenarios)
