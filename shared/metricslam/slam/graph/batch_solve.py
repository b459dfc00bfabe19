"""Batch solve of the whole global graph and a fresh ISAM2 seeded with it (loops, recovery).

Used by :meth:`metricslam.slam.graph.sim3_graph.GlobalPoseGraph._rebuild`: after a new loop
(it moves the whole map: one Levenberg-Marquardt over all factors beats many relinearized ISAM2
steps) and after an ISAM2 update failed. If even a fresh ISAM2 cannot factor the batch result
(indeterminate near a keyframe), the newest keyframes, then the keyframe gtsam names and its
neighbours, get a weak prior at their solved pose (:data:`STABILIZER_SIGMAS`) and the solve is
retried. See ``docs/global_graph.md`` (why QR, not Cholesky) for when that used to happen.
"""

from __future__ import annotations

import logging
import re
import time

import gtsam
import numpy as np

from metricslam.errors import GraphError
from metricslam.slam.graph.gtsam_sim3 import key

log = logging.getLogger(__name__)

#: sigmas ``[ω, u, λ]`` of the weak prior that makes an indeterminate keyframe solvable again.
STABILIZER_SIGMAS = np.array([0.1] * 3 + [100.0] * 3 + [1.0])


def lm_params(factorization: str) -> gtsam.LevenbergMarquardtParams:
    """Levenberg-Marquardt parameters with QR or Cholesky elimination (``GraphConfig.factorization``).

    gtsam's Python calls keep the GIL for their whole run, so a batch solve of a few hundred
    keyframes after a loop (~40-80 ms) stalled the tracking thread of a live session; the
    iteration hook lets a waiting thread in between iterations (the solve itself is unchanged)."""
    lm = gtsam.LevenbergMarquardtParams()
    lm.setLinearSolverType("MULTIFRONTAL_QR" if factorization == "QR" else "MULTIFRONTAL_CHOLESKY")
    lm.iterationHook = _let_other_threads_run
    return lm


def _let_other_threads_run(iteration: int, error_before: float, error_after: float) -> None:
    time.sleep(0)  # releases the GIL: a thread waiting for it takes it now


def indeterminate_keyframe(exc: Exception) -> int | None:
    """Keyframe id named in gtsam's IndeterminateLinearSystem message ("Symbol: s913"), or None."""
    m = re.search(r"Symbol: s(\d+)", str(exc))
    return int(m.group(1)) if m else None


def committed_factors(isam: gtsam.ISAM2, corrupt_at: int | None, kinds: dict[int, object],
                      drop: tuple = ()) -> tuple[gtsam.NonlinearFactorGraph, list]:
    """The factors ``isam`` holds (only the first ``corrupt_at`` slots, those committed before a
    failed update, when that is not None; empty slots and those whose kind is in ``drop``
    skipped) and their ``kinds``, in order."""
    factors = isam.getFactorsUnsafe()
    n = factors.size() if corrupt_at is None else min(corrupt_at, factors.size())
    graph, out = gtsam.NonlinearFactorGraph(), []
    for i in range(n):
        f = factors.at(i)
        if f is not None and not any(kinds.get(i) == d for d in drop):
            graph.add(f)
            out.append(kinds.get(i))
    return graph, out


def solve_batch(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, isam_params: gtsam.ISAM2Params,
                factorization: str, newest: list[int]) -> tuple[gtsam.ISAM2, object, gtsam.Values, list[int]]:
    """LM on ``graph`` from ``values``, then a fresh ISAM2 holding the graph at the LM result.

    Args:
        graph: every factor (stabilizer priors are appended to it in place).
        values: initial estimate of every variable.
        newest: keyframe ids added since the last successful solve (stabilized first).
    Returns:
        ``(isam, update_result, solved_values, stabilized_keyframe_ids)``; the stabilizer
        factors sit at the end of ``graph``, one per stabilized keyframe, in that order.
    Raises:
        GraphError: when no fresh ISAM2 could be built.
    """
    last_exc: Exception | None = None
    stabilized: list[int] = []
    for _ in range(4):
        try:
            values = gtsam.LevenbergMarquardtOptimizer(graph, values, lm_params(factorization)).optimize()
            isam = gtsam.ISAM2(isam_params)
            result = isam.update(graph, values)
            return isam, result, values, stabilized
        except RuntimeError as exc:
            last_exc = exc
            near = indeterminate_keyframe(exc)
            if near is None:
                break
            # gtsam names the variable being eliminated, maybe a neighbour of the culprit; the
            # culprit is new (the committed graph was solvable): the new keyframes and the named
            # one first, then its neighbours too
            todo = [*newest, near] if not stabilized else [near - 1, near, near + 1]
            todo = [k for k in dict.fromkeys(todo) if k not in stabilized and values.exists(key(k))]
            if not todo:
                break
            log.warning("global graph indeterminate near keyframe %d; weak prior on %s", near, todo)
            for kf in todo:
                graph.add(gtsam.PriorFactorSimilarity3(key(kf), values.atSimilarity3(key(kf)),
                                                       gtsam.noiseModel.Diagonal.Sigmas(STABILIZER_SIGMAS)))
                stabilized.append(kf)
    raise GraphError(f"global graph could not be solved even in batch ({last_exc}); a keyframe is "
                     "probably unconstrained") from last_exc
