"""Held-out validation of own-map relocalization after tracking loss, second candidate (rule_segment_reloc2_session23.md).

Usage: PYTHONPATH=<tree>/shared:<tree>/cli:<tree>:<tree>/services/slam python val.py TAG OUT.jsonl
"""
import sys

from val import K01, K13, K13_POSES, loops150, main, per_seed

SEEDS = list(range(165, 175))


def scenarios():
    out = per_seed(SEEDS)
    out.append(("real revisit 0013 b", "kidnap", [(K13, range(0, 143, 2), K13_POSES), (K13, range(61, 122, 2), K13_POSES)], 72, True))
    out.append(("real foreign 0001->0013", "foreign", [(K01, range(0, 54), None), (K13, range(0, 60), None)], 54, True))
    return out


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], scenarios)
