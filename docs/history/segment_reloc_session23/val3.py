"""Held-out validation of own-map relocalization after tracking loss, third candidate (rule_segment_reloc3_session23.md).

Usage: PYTHONPATH=<tree>/shared:<tree>/cli:<tree>:<tree>/services/slam python val.py TAG OUT.jsonl
"""
import sys

from val import K01, K13, K13_POSES, loops150, main, per_seed

SEEDS, SHORT_SEEDS = list(range(175, 185)), range(185, 195)


def scenarios():
    out = per_seed(SEEDS) + loops150(SHORT_SEEDS)
    out.append(("real revisit 0013 c", "kidnap", [(K13, range(1, 144, 2), K13_POSES), (K13, range(40, 101, 2), K13_POSES)], 72, True))
    out.append(("real foreign 0013 odd->0001", "foreign", [(K13, range(1, 100, 2), None), (K01, range(0, 54), None)], 50, True))
    return out


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], scenarios)
