"""Averages over several sequences, both ways papers report them.

* **pooled** — the devkit's way: t_rel / r_rel are means over *all segments of all sequences*;
  ATE and RPE are RMSEs over all frames (pairs) of all sequences (each sequence aligned on its
  own); ``scale_ratio`` is the frame-weighted mean of the per-sequence ratios.
* **mean of sequences** — the plain mean of each per-sequence number.
"""

from __future__ import annotations

import math

import numpy as np

from metricslam.errors import EvaluationError
from metricslam.evaluation.kitti_metric import SegmentErrors
from metricslam.evaluation.result import EvalReport, EvalResult


def _rms_weighted(values: list[float | None], weights: list[int]) -> float | None:
    """Weighted RMS of per-sequence RMSEs (= RMSE over all their samples), skipping None."""
    pairs = [(v, w) for v, w in zip(values, weights) if v is not None]
    if not pairs:
        return None
    v, w = (np.asarray(x, dtype=float) for x in zip(*pairs))
    return float(np.sqrt(np.sum(w * v**2) / np.sum(w)))


def _average(values: list[float | None], weights: list[int]) -> float | None:
    pairs = [(v, w) for v, w in zip(values, weights) if v is not None]
    if not pairs:
        return None
    v, w = zip(*pairs)
    return float(np.average(v, weights=w))


def _mean_or_none(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def pooled_result(evaluations: list) -> EvalResult:
    """Pool :class:`~metricslam.evaluation.evaluator.SequenceEvaluation` objects."""
    if not evaluations:
        raise EvaluationError("nothing to pool: no sequences were evaluated")
    res = [e.result for e in evaluations]
    seg = SegmentErrors.concatenate([e.segments for e in evaluations])
    n = [r.n_frames for r in res]
    n_pairs = [e.rpe.n_pairs for e in evaluations]
    t_rel = seg.t_rel_pct
    notes = [f"{r.name}: {note}" for r in res for note in r.notes]
    return EvalResult(
        name="pooled",
        t_rel_pct=None if not math.isfinite(t_rel) else t_rel,
        r_rel_deg_per_100m=None if not math.isfinite(t_rel) else seg.r_rel_deg_per_100m,
        ate_rmse_m=_rms_weighted([r.ate_rmse_m for r in res], n),
        ate_rmse_sim3_m=_rms_weighted([r.ate_rmse_sim3_m for r in res], n),
        scale_ratio=_average([r.scale_ratio for r in res], n),
        scale_error_pct=_average([r.scale_error_pct for r in res], n),
        n_frames=int(sum(n)),
        path_length_m=float(sum(r.path_length_m for r in res)),
        t_rel_lengths_m=seg.used_lengths_m,
        ate_rmse_unaligned_m=_rms_weighted([r.ate_rmse_unaligned_m for r in res], n),
        rpe_trans_rmse_m=_rms_weighted([r.rpe_trans_rmse_m for r in res], n_pairs),
        rpe_rot_rmse_deg=_rms_weighted([r.rpe_rot_rmse_deg for r in res], n_pairs),
        rpe_delta_frames=res[0].rpe_delta_frames,
        n_segments=len(seg),
        t_rel_by_length={f"{L:g}": [t, r, float(k)] for L, (t, r, k) in seg.by_length().items()},
        short_sequence=any(r.short_sequence for r in res),
        notes=notes,
    )


def mean_result(evaluations: list) -> EvalResult:
    """Plain mean of the per-sequence numbers."""
    if not evaluations:
        raise EvaluationError("nothing to average: no sequences were evaluated")
    res = [e.result for e in evaluations]
    mean = lambda key: _mean_or_none([getattr(r, key) for r in res])  # noqa: E731
    return EvalResult(
        name="mean of sequences",
        t_rel_pct=_mean_or_none([r.t_rel_pct for r in res]),
        r_rel_deg_per_100m=_mean_or_none([r.r_rel_deg_per_100m for r in res]),
        ate_rmse_m=mean("ate_rmse_m"),
        ate_rmse_sim3_m=mean("ate_rmse_sim3_m"),
        scale_ratio=mean("scale_ratio"),
        scale_error_pct=mean("scale_error_pct"),
        n_frames=int(sum(r.n_frames for r in res)),
        path_length_m=float(sum(r.path_length_m for r in res)),
        t_rel_lengths_m=sorted({L for r in res for L in r.t_rel_lengths_m}),
        ate_rmse_unaligned_m=mean("ate_rmse_unaligned_m"),
        rpe_trans_rmse_m=mean("rpe_trans_rmse_m"),
        rpe_rot_rmse_deg=mean("rpe_rot_rmse_deg"),
        rpe_delta_frames=res[0].rpe_delta_frames,
        n_segments=int(sum(r.n_segments for r in res)),
        short_sequence=any(r.short_sequence for r in res),
    )


def build_report(evaluations: list) -> EvalReport:
    """Per-sequence results, pooled, and (for more than one sequence) the mean of sequences."""
    per_seq = [e.result for e in evaluations]
    if len(evaluations) == 1:
        return EvalReport(pooled=per_seq[0], mean_of_sequences=None, per_sequence=per_seq)
    return EvalReport(pooled=pooled_result(evaluations), mean_of_sequences=mean_result(evaluations),
                      per_sequence=per_seq)
