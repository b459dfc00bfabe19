"""``GlobalPoseGraph``: Sim(3) keyframe poses ``S_world_kf`` (``gtsam.Similarity3`` keyed
``symbol('s', kf_id)``; scale: metres per keyframe VO unit) solved incrementally with ISAM2.

Factors: ``BetweenFactorSimilarity3`` odometry (eq. 11), the same form for loops (robust kernel,
Mahalanobis gate against the current marginals, removed again if still inconsistent after the
solve), unary log-scale priors (eq. 12, :mod:`metricslam.slam.graph.scale_factor`). ISAM2 bounds
each solve's cost: only the cliques touched by new factors are re-eliminated. Gauge: a prior on
the first keyframe's rotation and translation (and scale with ``anchor_scale=True``, the
``--no-scale`` ablation). Not thread-safe: :class:`~metricslam.slam.graph.backend.GlobalBackend`
serializes access.
"""

from __future__ import annotations

import logging
from typing import Callable

import gtsam
import numpy as np

from metricslam.errors import GraphError
from metricslam.slam.graph import batch_solve, scale_factor
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.gtsam_sim3 import from_gtsam, key, to_gtsam
from metricslam.slam.graph.records import LoopDecision

log = logging.getLogger(__name__)

#: chi-square gate (7 dof) on a loop's innovation against the predicted relative-pose covariance.
LOOP_GATE_CHI2 = 200.0
#: sigma of the gauge prior on the first keyframe: firm, but not so firm that Cholesky on
#: 1e12-vs-1e2 information becomes indeterminate.
ANCHOR_SIGMA = 1e-3


class GlobalPoseGraph:
    """Incremental Sim(3) pose graph.

    Args:
        config: graph parameters.
        anchor_scale: fix the first keyframe's scale too (7-D gauge); use when no scale factors
            will be added.
    """

    def __init__(self, config: GraphConfig | None = None, anchor_scale: bool = False) -> None:
        self.config = config or GraphConfig()
        self.anchor_scale = anchor_scale
        params = gtsam.ISAM2Params()
        # QR, not Cholesky: gtsam's Cholesky treats pivots below an absolute 1e-6 as zero, and the
        # far end of a long loop-free chain has less information than that in its horizontal
        # position (σ of hundreds of metres): "IndeterminateLinearSystem" on a well-posed graph
        params.setFactorization(self.config.factorization)
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        params.relinearizeSkip = self.config.relinearize_skip
        self._params = params
        self._isam = gtsam.ISAM2(params)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._pending_kinds: list[str] = []
        self._factor_kinds: dict[int, str] = {}  # isam factor index -> kind
        self._loop_indices: dict[int, tuple] = {}  # isam index -> (old, new, sigmas, measured)
        self._keyframes: list[int] = []
        self._latest: dict[int, gtsam.Similarity3] = {}  # best known estimate per keyframe
        self._scale_noise = scale_factor.scale_noise(self.config)
        self.n_scale_factors = 0
        self.n_loops_accepted = 0
        self.n_loops_rejected = 0
        self.n_rebuilds = 0
        self.n_stabilized = 0
        self._corrupt_at: int | None = None  # factors committed before a failed ISAM2 update
        self._uncommitted: list[int] = []  # keyframes added since the last successful update
        self._drop, self._reseed = (), {}  # the next rebuild's: kinds left out, starts (replace_factor)

    # -- construction -------------------------------------------------------------------------
    def has(self, kf_id: int) -> bool:
        return int(kf_id) in self._latest

    def add_keyframe(
        self,
        kf_id: int,
        S_world_kf_guess: np.ndarray,
        prev_kf_id: int | None = None,
        S_prev_kf: np.ndarray | None = None,
        information: np.ndarray | None = None,
        prior_sigmas: np.ndarray | None = None,
        link_kind: str = "odometry",
    ) -> None:
        """Insert a keyframe variable with its odometry factor to ``prev_kf_id`` (or a prior).

        Args:
            kf_id: new keyframe id (unique).
            S_world_kf_guess: (4, 4) initial estimate.
            prev_kf_id / S_prev_kf: odometry ``Ŝ_prev_kf`` (4, 4) and its 7x7 ``information``.
            prior_sigmas: (7,) sigmas of a prior at the guess, for a keyframe without odometry
                (the very first one gets the gauge prior automatically).
            link_kind: the odometry factor's label (:meth:`replace_factor` can drop it later).
        """
        kf_id = int(kf_id)
        if self.has(kf_id):
            raise GraphError(f"keyframe {kf_id} is already in the global graph; ids must be unique")
        S_guess = to_gtsam(S_world_kf_guess)
        self._new_values.insert(key(kf_id), S_guess)
        self._latest[kf_id] = S_guess
        self._uncommitted.append(kf_id)
        first = not self._keyframes
        self._keyframes.append(kf_id)
        if first:
            free = scale_factor.FREE_SIGMA if not self.anchor_scale else ANCHOR_SIGMA
            sig = np.array([ANCHOR_SIGMA] * 6 + [min(free, 10.0)])
            self._add(gtsam.PriorFactorSimilarity3(key(kf_id), S_guess,
                                                   gtsam.noiseModel.Diagonal.Sigmas(sig)), "anchor")
        elif prior_sigmas is not None:
            self._add(gtsam.PriorFactorSimilarity3(
                key(kf_id), S_guess, gtsam.noiseModel.Diagonal.Sigmas(np.asarray(prior_sigmas, float))),
                "segment_prior")
        if prev_kf_id is not None:
            if not self.has(prev_kf_id) or S_prev_kf is None or information is None:
                raise GraphError(f"odometry to keyframe {prev_kf_id} needs a known keyframe, a "
                                 "measurement and its information")
            noise = gtsam.noiseModel.Gaussian.Information(np.asarray(information, dtype=float))
            self._add(gtsam.BetweenFactorSimilarity3(key(prev_kf_id), key(kf_id),
                                                     to_gtsam(S_prev_kf), noise), link_kind)

    def add_scale_measurements(self, kf_id: int, scales: np.ndarray) -> int:
        """Add the log-scale measurements ``s_j`` of keyframe ``kf_id`` (one Huber factor each,
        or their per-keyframe M-estimate; ``GraphConfig.scale_factor_mode``). Returns how many
        measurements were used."""
        if not self.has(kf_id):
            raise GraphError(f"scale factors for unknown keyframe {kf_id}; add the keyframe first")
        s = np.asarray(scales, dtype=float).reshape(-1)
        s = s[np.isfinite(s) & (s > 0)]
        if s.size == 0:
            return 0
        if self.config.scale_factor_mode == "per_keyframe":
            self._add(scale_factor.make_keyframe_scale_factor(key(kf_id), self._latest[int(kf_id)], s,
                                                              self.config), "scale")
        else:
            for f in scale_factor.make_scale_factors(key(kf_id), self._latest[int(kf_id)], s,
                                                     self._scale_noise):
                self._add(f, "scale")
        self.n_scale_factors += int(s.size)
        return int(s.size)

    def add_unary(self, kf_id: int, make: Callable[[int, gtsam.Similarity3], gtsam.NonlinearFactor], kind: str) -> None:
        """Add keyframe ``kf_id``'s factor ``make(key, S_world_kf now)`` labelled ``kind`` (:mod:`.ground_factor`)."""
        if not self.has(kf_id):
            raise GraphError(f"{kind} factor for unknown keyframe {kf_id}; add the keyframe first")
        self._add(make(key(kf_id), self._latest[int(kf_id)]), kind)

    def add_loop(self, kf_old: int, kf_new: int, S_old_new: np.ndarray, sigmas: np.ndarray,
                 gate: bool = True) -> LoopDecision:
        """Add a loop factor ``Ŝ_old_new`` if it passes the Mahalanobis gate.

        The innovation ``Log(Ŝ⁻¹ · S_old⁻¹ S_new)`` is tested against the loop noise plus the
        relative-pose covariance from ISAM2's joint marginal (chi² ≤ ``LOOP_GATE_CHI2``): a false
        loop between places the graph knows are far apart is refused before it can pull.
        """
        for k in (kf_old, kf_new):
            if not self.has(k):
                raise GraphError(f"loop references unknown keyframe {k}")
        sigmas = np.asarray(sigmas, dtype=float)
        meas = to_gtsam(S_old_new)
        d2 = self._loop_mahalanobis_sq(kf_old, kf_new, meas, sigmas) if gate else 0.0
        if gate and not (np.isfinite(d2) and d2 <= LOOP_GATE_CHI2):
            self.n_loops_rejected += 1
            return LoopDecision(False, kf_old, kf_new, d2, "inconsistent with the graph (gate)")
        base = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
        k = self.config.loop_kernel_param
        if gate:
            # gated consistent, the innovation can still be 100 loop sigmas after a long drift: keep
            # it in the kernel's quadratic zone (a fixed one left a 2 km loop 5 m open)
            S_old, S_new = self._current(kf_old), self._current(kf_new)
            innov = gtsam.Similarity3.Logmap(meas.inverse().compose(S_old.between(S_new)))
            k = max(k, 1.5 * float(np.linalg.norm(innov / sigmas)))
        est = {"dcs": gtsam.noiseModel.mEstimator.DCS, "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
               "huber": gtsam.noiseModel.mEstimator.Huber}[self.config.loop_kernel].Create(k)
        noise = gtsam.noiseModel.Robust.Create(est, base)
        self._add(gtsam.BetweenFactorSimilarity3(key(kf_old), key(kf_new), meas, noise),
                  ("loop", int(kf_old), int(kf_new), sigmas, meas))
        self.n_loops_accepted += 1
        return LoopDecision(True, kf_old, kf_new, d2, "accepted")

    def _loop_mahalanobis_sq(self, kf_old: int, kf_new: int, meas: gtsam.Similarity3,
                             sigmas: np.ndarray) -> float:
        S_old, S_new = self._current(kf_old), self._current(kf_new)
        rel = S_old.between(S_new)
        innov = gtsam.Similarity3.Logmap(meas.inverse().compose(rel))
        cov = np.diag(sigmas**2)
        if self._corrupt_at is None and self._isam.valueExists(key(kf_old)) and self._isam.valueExists(key(kf_new)):
            kl = gtsam.KeyVector([key(kf_old), key(kf_new)])
            try:
                joint = self._isam.jointMarginalCovariance(kl).fullMatrix()
                J = np.hstack([-rel.inverse().AdjointMap(), np.eye(7)])
                cov = cov + J @ joint @ J.T
            except (RuntimeError, IndexError) as exc:  # indeterminate: fall back to the loop noise
                log.debug("joint marginal failed: %s", exc)
        try:
            return float(innov @ np.linalg.solve(cov, innov))
        except np.linalg.LinAlgError:
            return float("inf")

    def _current(self, kf_id: int) -> gtsam.Similarity3:
        """Current estimate of one keyframe (``_latest`` is refreshed only for the newest ones
        between loops; an old loop end must be read from ISAM2)."""
        k = key(int(kf_id))
        if self._corrupt_at is None and self._isam.valueExists(k):
            return self._isam.calculateEstimateSimilarity3(k)
        return self._latest[int(kf_id)]

    def replace_factor(self, kind: str, reseed: dict[int, np.ndarray]) -> None:
        """Leave the factor labelled ``kind`` out from the next solve on, a batch rebuild (add a
        loop first) from ``reseed``'s estimates (kf_id -> (4, 4) ``S_world_kf``)."""
        self._drop += (kind,)
        self._reseed.update({int(k): to_gtsam(S) for k, S in reseed.items()})

    def _add(self, factor: gtsam.NonlinearFactor, kind: object) -> None:
        self._new_factors.add(factor)
        self._pending_kinds.append(kind)

    # -- solving ------------------------------------------------------------------------------
    def solve(self, extra_iterations: int | None = None) -> dict:
        """Push pending factors into ISAM2 and iterate (with a new loop: batch LM + fresh ISAM2);
        re-check new loops afterwards. Returns ``{"loops_removed", "iterations", "batch": whether
        ISAM2 was rebuilt}``."""
        extra = self.config.extra_iterations if extra_iterations is None else extra_iterations
        kinds = self._pending_kinds
        has_loop = any(isinstance(k, tuple) for k in kinds)
        n_iter = 1
        batch = has_loop or self._corrupt_at is not None
        if batch:
            # a loop moves the whole map: one batch LM beats many relinearized updates; after a
            # failed update the ISAM2 object is unusable until a rebuild succeeds
            self._rebuild()
        else:
            # a failed ISAM2 update has already taken in the new factors and values: rebuild from
            # the factors committed before it (plus the pending ones), never from its leftovers
            n_committed = self._isam.getFactorsUnsafe().size()
            try:
                result = self._isam.update(self._new_factors, self._new_values)
                self._uncommitted = []
                for idx, kind in zip(list(result.getNewFactorsIndices()), kinds):
                    self._factor_kinds[idx] = kind
            except RuntimeError as exc:  # ill-conditioned incremental step: rebuild from batch
                log.warning("ISAM2 update failed (%s); rebuilding from a batch solve",
                            " ".join(str(exc).split())[:160] or type(exc).__name__)
                self.n_rebuilds += 1
                self._corrupt_at, batch = n_committed, True
                self._rebuild()
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._pending_kinds = []
        if not has_loop:
            n_iter += self._iterate(extra, stop_when_converged=False)
        removed = self._reject_inconsistent_loops() if has_loop else 0
        self._refresh_latest(all_keys=has_loop or removed > 0)
        return {"loops_removed": removed, "iterations": n_iter, "batch": batch}

    def _rebuild(self) -> None:
        """Batch LM on every factor (ISAM2's, only those committed before a failed update, and the
        pending ones), then a fresh ISAM2 seeded with the result (the old one freed first: both
        were a 1000-keyframe session's memory peak). Indeterminate keyframes get weak priors
        (``n_stabilized``); a state that cannot be rebuilt raises :class:`GraphError` and leaves
        the committed factors at their estimate before the call (pending ones kept)."""
        committed, committed_kinds = batch_solve.committed_factors(self._isam, self._corrupt_at,
                                                                   self._factor_kinds, self._drop)
        graph, kinds = gtsam.NonlinearFactorGraph(committed), list(committed_kinds)
        for i in range(self._new_factors.size()):
            graph.add(self._new_factors.at(i))
            kinds.append(self._pending_kinds[i])
        theta = self._isam.getLinearizationPoint()
        solved = self._corrupt_at is None and self._isam.size() > 0
        estimate = self._isam.calculateEstimate() if solved else None  # kept for a failed rebuild
        uncommitted = set(self._uncommitted)
        values, committed_estimate = gtsam.Values(), gtsam.Values()
        for kf in self._keyframes:
            k = key(kf)
            guess = self._reseed[kf] if kf in self._reseed else (theta.atSimilarity3(k) if theta.exists(k) else self._latest[kf])
            values.insert(k, guess)
            if kf not in uncommitted:
                committed_estimate.insert(k, estimate.atSimilarity3(k) if solved else guess)
        del theta, estimate  # theta would keep the old ISAM2 alive; estimate is copied above
        self._isam = gtsam.ISAM2(self._params)
        try:
            isam, result, values, stabilized = batch_solve.solve_batch(
                graph, values, self._params, self.config.factorization, self._uncommitted)
        except GraphError:
            self._restore(committed, committed_kinds, committed_estimate)
            raise
        kinds.extend(["stabilizer"] * len(stabilized))
        self.n_stabilized += len(stabilized)
        self._adopt(isam, result.getNewFactorsIndices(), kinds)
        self._uncommitted, self._drop, self._reseed = [], (), {}
        for kf in self._keyframes:
            self._latest[kf] = values.atSimilarity3(key(kf))

    def _adopt(self, isam: gtsam.ISAM2, indices: object, kinds: list, corrupt_at: int | None = None) -> None:
        """Make a freshly built ISAM2 this graph's (``kinds``: of its factors at ``indices``)."""
        self._isam, self._corrupt_at = isam, corrupt_at
        self._factor_kinds, self._loop_indices = {}, {}
        for idx, kind in zip(list(indices), kinds):
            self._factor_kinds[idx] = kind
            if isinstance(kind, tuple):
                self._loop_indices[idx] = kind[1:]

    def _restore(self, committed: gtsam.NonlinearFactorGraph, kinds: list, estimate: gtsam.Values) -> None:
        """After a failed rebuild: a fresh ISAM2 with the committed factors at their estimate.
        If even that fails, the factors it took in are kept as committed-before-a-failure, for
        the next rebuild to start from (as after a failed incremental update)."""
        isam = gtsam.ISAM2(self._params)
        try:
            self._adopt(isam, isam.update(committed, estimate).getNewFactorsIndices(), kinds)
        except RuntimeError as exc:
            log.warning("the global graph could not be restored after a failed rebuild (%s); the "
                        "next solve rebuilds it", " ".join(str(exc).split())[:160])
            self._adopt(isam, range(committed.size()), kinds, corrupt_at=committed.size())

    def _iterate(self, max_updates: int, stop_when_converged: bool) -> int:
        """Extra Gauss-Newton steps with forced relinearization (a loop moves the whole map); the
        number done (``stop_when_converged``: stops once an update relinearizes no variable)."""
        for i in range(max_updates):
            res = self._isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), force_relinearize=True)
            if stop_when_converged and res.getVariablesRelinearized() == 0:
                return i + 1
        return max_updates

    def _reject_inconsistent_loops(self) -> int:
        est = self._isam.calculateEstimate()
        bad = []
        for idx, (a, b, sig, meas) in self._loop_indices.items():
            rel = est.atSimilarity3(key(a)).between(est.atSimilarity3(key(b)))
            r = gtsam.Similarity3.Logmap(meas.inverse().compose(rel)) / sig
            if float(r @ r) > self.config.loop_reject_chi2:
                bad.append(idx)
        if bad:
            log.info("removing %d loop factor(s) inconsistent after the solve", len(bad))
            self._isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), bad)
            self._rebuild()  # re-solve without them (batch, fresh ISAM2, loop indices renumbered)
            self.n_loops_accepted -= len(bad)
            self.n_loops_rejected += len(bad)
        return len(bad)

    def _refresh_latest(self, all_keys: bool) -> None:
        if all_keys:
            est = self._isam.calculateEstimate()
            for kf in self._keyframes:
                self._latest[kf] = est.atSimilarity3(key(kf))
        else:  # bounded cost: refresh only the newest keyframes
            for kf in self._keyframes[-8:]:
                self._latest[kf] = self._isam.calculateEstimateSimilarity3(key(kf))

    # -- queries ------------------------------------------------------------------------------
    def estimate(self, kf_id: int) -> np.ndarray:
        """Latest ``S_world_kf`` (4, 4) of one keyframe."""
        if not self.has(kf_id):
            raise GraphError(f"keyframe {kf_id} is not in the global graph")
        if self._corrupt_at is None and self._isam.valueExists(key(kf_id)):
            return from_gtsam(self._isam.calculateEstimateSimilarity3(key(kf_id)))
        return from_gtsam(self._latest[int(kf_id)])

    def scale_sigma_log(self, kf_id: int) -> float | None:
        """σ of keyframe ``kf_id``'s ``log s`` from ISAM2's marginal (None: not solved yet)."""
        usable = self._corrupt_at is None and self._isam.valueExists(key(int(kf_id)))
        return scale_factor.marginal_sigma_log(self._isam, key(int(kf_id))) if usable else None

    def estimates(self) -> dict[int, np.ndarray]:
        """``kf_id -> S_world_kf`` (4, 4) for every keyframe (full back-substitution, O(n))."""
        est = self._isam.calculateEstimate() if self._isam.size() and self._corrupt_at is None else gtsam.Values()
        out = {}
        for kf in self._keyframes:
            S = est.atSimilarity3(key(kf)) if est.exists(key(kf)) else self._latest[kf]
            out[kf] = from_gtsam(S)
        return out

    def factor_graph(self, include_anchor: bool = True) -> gtsam.NonlinearFactorGraph:
        """All factors currently in ISAM2 (optionally without the gauge anchor), for analysis."""
        g = gtsam.NonlinearFactorGraph()
        factors = self._isam.getFactorsUnsafe()
        for i in range(factors.size()):
            f = factors.at(i)
            if f is None or (not include_anchor and self._factor_kinds.get(i) == "anchor"):
                continue
            g.add(f)
        return g

    def values(self) -> gtsam.Values:
        return self._isam.calculateEstimate()

    @property
    def n_keyframes(self) -> int:
        return len(self._keyframes)

    @property
    def n_loops(self) -> int:
        return self.n_loops_accepted

    def loop_pairs(self) -> set[tuple[int, int]]:
        """``(kf_old, kf_new)`` of every loop factor now in the graph."""
        return {(v[0], v[1]) for v in self._loop_indices.values()}

