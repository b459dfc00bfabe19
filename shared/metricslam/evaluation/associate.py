"""Associate two time-stamped trajectories by nearest timestamp (TUM ``associate.py`` style).

Each estimate stamp is matched to the nearest ground-truth stamp within ``max_diff_ns``; a
ground-truth stamp is used at most once (greedy by smallest difference, like TUM's tool and
evo's ``sync``). Stamps are int64 nanoseconds.
"""

from __future__ import annotations

import numpy as np

from metricslam.errors import EvaluationError

#: default association tolerance: 20 ms (TUM's tool uses 20 ms, evo 10 ms).
DEFAULT_MAX_DIFF_NS = 20_000_000


def associate(
    t_ns_gt: np.ndarray, t_ns_est: np.ndarray, max_diff_ns: int = DEFAULT_MAX_DIFF_NS
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i_gt (M,), i_est (M,))`` sorted by estimate time.

    Raises:
        EvaluationError: no pair is within ``max_diff_ns``.
    """
    a = np.asarray(t_ns_gt, dtype=np.int64)
    b = np.asarray(t_ns_est, dtype=np.int64)
    # Candidate pairs: for each estimate stamp, the two ground-truth neighbours.
    order = np.argsort(a, kind="stable")
    a_sorted = a[order]
    pos = np.searchsorted(a_sorted, b)
    cands = []
    for j, p in enumerate(pos):
        for k in (p - 1, p):
            if 0 <= k < a_sorted.shape[0]:
                d = abs(int(a_sorted[k]) - int(b[j]))
                if d <= max_diff_ns:
                    cands.append((d, int(order[k]), j))
    cands.sort()
    used_gt: set[int] = set()
    used_est: set[int] = set()
    pairs = []
    for _, i, j in cands:
        if i not in used_gt and j not in used_est:
            used_gt.add(i)
            used_est.add(j)
            pairs.append((i, j))
    if not pairs:
        raise EvaluationError(
            f"no estimate timestamp is within {max_diff_ns / 1e6:.1f} ms of a ground-truth "
            "timestamp; are both in seconds of the same clock?"
        )
    pairs.sort(key=lambda p: p[1])
    arr = np.array(pairs, dtype=np.int64)
    return arr[:, 0], arr[:, 1]
