"""The evaluator's result: a frozen pydantic model whose JSON keys are the contract of
``DESIGN.md`` (``eval --json``) plus extras.

Contract keys (lower is better unless said): ``t_rel_pct``, ``r_rel_deg_per_100m``,
``ate_rmse_m`` (SE(3)-aligned), ``ate_rmse_sim3_m``, ``scale_ratio`` (estimate size / true
size, 1.0 is metric), ``scale_error_pct`` (``100·|scale_ratio − 1|``), ``n_frames``,
``path_length_m``, ``t_rel_lengths_m`` (segment lengths actually used). A metric that cannot
be computed (no segment fits; a straight-line ground truth cannot be aligned) is ``null`` and
``notes`` says why.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class EvalResult(BaseModel):
    """Metrics of one sequence, or an average over several (``name`` says which)."""

    model_config = ConfigDict(frozen=True, extra="forbid", ser_json_inf_nan="null")

    name: str = Field(description="sequence name, or 'pooled' / 'mean of sequences'")
    t_rel_pct: float | None = Field(description="KITTI devkit translational error, percent")
    r_rel_deg_per_100m: float | None = Field(description="KITTI devkit rotational error, deg/100 m")
    ate_rmse_m: float | None = Field(description="ATE RMSE after SE(3) alignment, metres")
    ate_rmse_sim3_m: float | None = Field(description="ATE RMSE after Sim(3) alignment, metres")
    scale_ratio: float | None = Field(description="estimate size / true size from the Sim(3) alignment")
    scale_error_pct: float | None = Field(description="100·|scale_ratio − 1|")
    n_frames: int = Field(description="number of evaluated (associated) frames")
    path_length_m: float = Field(description="ground-truth path length, metres")
    t_rel_lengths_m: list[float] = Field(description="segment lengths used for t_rel/r_rel")
    # extras
    ate_rmse_unaligned_m: float = Field(description="ATE RMSE without any alignment, metres")
    rpe_trans_rmse_m: float = Field(description="RPE translation RMSE, metres, over rpe_delta_frames")
    rpe_rot_rmse_deg: float = Field(description="RPE rotation RMSE, degrees, over rpe_delta_frames")
    rpe_delta_frames: int = Field(description="frame offset of the RPE pairs")
    n_segments: int = Field(description="number of devkit segments averaged")
    t_rel_by_length: dict[str, list[float]] = Field(
        default_factory=dict,
        description="segment length (m) -> [t_rel_pct, r_rel_deg_per_100m, n_segments]",
    )
    short_sequence: bool = Field(False, description="True when lengths 10..50 m replaced 100..800 m")
    notes: list[str] = Field(default_factory=list)


class EvalReport(BaseModel):
    """What ``metricslam eval --json`` writes.

    The top-level keys are those of :class:`EvalResult` for the pooled result (identical to the
    single sequence when only one is given), so a reader of the contract keys never has to care
    how many sequences there were. ``per_sequence`` and ``mean_of_sequences`` add the rest.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    pooled: EvalResult
    mean_of_sequences: EvalResult | None = None
    per_sequence: list[EvalResult]

    def to_json_dict(self) -> dict:
        """Flat contract keys of ``pooled`` at top level, plus the breakdown."""
        out = self.pooled.model_dump(mode="json")
        if len(self.per_sequence) > 1:
            out["per_sequence"] = [r.model_dump(mode="json") for r in self.per_sequence]
            out["mean_of_sequences"] = (
                self.mean_of_sequences.model_dump(mode="json") if self.mean_of_sequences else None
            )
        return out
