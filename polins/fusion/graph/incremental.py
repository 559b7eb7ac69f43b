"""Incremental graph solvers: ISAM2 (causal estimates) and the fixed-lag smoother (lagged estimates).

Each keyframe's factors are added as the keyframe arrives; the measurement factors are
gated on their predicted residuals with the previous keyframe's covariance (docs/filter.md
§9). :func:`solve_incremental` appends one :class:`~polins.fusion.items.UpdateRecord` per
yaw/sun/zero-velocity factor to ``records`` and returns the keyframe
:class:`~polins.fusion.graph.estimates.Estimates`.
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X
from numpy.typing import NDArray

from polins.fusion.graph.estimates import Estimates
from polins.fusion.graph.factors import pose_cov_nav_from_body
from polins.fusion.graph.problem import Problem
from polins.fusion.items import HEADING_KINDS, UpdateRecord, gate_limit
from polins.fusion.measurement import ATT, N_ERROR, VEL

FloatArray = NDArray[np.float64]


def solve_incremental(
    prob: Problem,
    records: list[UpdateRecord],
    info: dict[str, Any],
    *,
    solver: str | None = None,
    rejected: dict[int, tuple[float, str]] | None = None,
    scale: bool = True,
    progress: Any = None,
) -> Estimates:
    """ISAM2 (causal estimates) or the incremental fixed-lag smoother (lagged estimates).

    ``solver`` overrides ``prob.config.graph.solver``; ``rejected`` (if given) receives the
    gated factors: index into ``prob.meas`` -> (NIS, reason); ``scale=False`` leaves the
    scale-factor variables out; ``progress`` (a tqdm bar) counts the keyframes.
    """
    run = _IncrementalRun(
        prob, records, solver or prob.config.graph.solver, rejected,
        scale and prob.scale_jac is not None,
    )  # fmt: skip
    run.start()
    if progress is not None:
        progress.reset(total=len(prob.t_key) - 1)
    for k in range(len(prob.t_key) - 1):
        run.step(k)
        if progress is not None:
            progress.update(1)
    for k in run.pending:
        run.record(k)
    info.update(n_keyframes=len(prob.t_key))
    return run.est


def _isam2_params(prob: Problem, solver: str) -> gtsam.ISAM2Params:
    """ISAM2 parameters of an incremental solve: QR, per-variable relinearization
    thresholds, and for the fixed-lag smoother all deltas kept current."""
    isam_params = gtsam.ISAM2Params()
    isam_params.setFactorization("QR")
    # Relinearize on attitude and velocity changes only: the IMU factors are linear in
    # position, whose (unobserved) values keep moving; relinearizing on them re-eliminates
    # most of the tree at every check. The velocity enters through the attitude
    # (R^T (v_j - v_i - g dt)): on the hand-held BROAD trial 15, whose unaided velocity
    # drifts by m/s, a velocity never relinearized left the tilt at rest after the motion
    # 1 deg off with a 0.14 deg sigma (pitch RMS(err/sigma) 2.97; 0.43 with the 1 m/s threshold); a
    # finer threshold relinearizes a UGV's drifting along-track velocity at every check.
    thresholds = gtsam.ISAM2ThresholdMap()
    thresholds.insert(("x", np.array([1e-2, 1e-2, 1e-2, 1e6, 1e6, 1e6])))
    thresholds.insert(("v", np.full(3, 1.0)))
    thresholds.insert(("b", np.full(6, 1e6)))
    # the IMU factors and the links are linear in the scale factors
    thresholds.insert(("g", np.full(3, 1e6)))
    thresholds.insert(("a", np.full(3, 1e6)))
    for letter, threshold in prob.states.thresholds():
        thresholds.insert((letter, threshold))
    isam_params.setRelinearizeThreshold(thresholds)
    isam_params.relinearizeSkip = 10
    if solver == "fixed_lag":
        # GTSAM's default "wildfire" threshold (1e-3) leaves the deltas of older variables
        # stale by up to 1e-3 rad, a sizeable fraction of a sigma, and the fixed-lag
        # smoother reports them late: update them all (cheap in a bounded window). ISAM2
        # reports the newest keyframe, whose delta is always current.
        isam_params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(0.0))
    return isam_params


class _IncrementalRun:
    """One incremental solve (:func:`solve_incremental`): its engine, the estimates
    reported so far and the gate's state; keyframe by keyframe."""

    def __init__(
        self,
        prob: Problem,
        records: list[UpdateRecord],
        solver: str,
        rejected: dict[int, tuple[float, str]] | None,
        scale: bool,
    ) -> None:
        self.prob, self.records, self.solver = prob, records, solver
        self.rejected, self.scale = rejected, scale
        params = _isam2_params(prob, solver)
        self.engine: Any = (
            gtsam.ISAM2(params)
            if solver == "isam2"
            else gtsam.IncrementalFixedLagSmoother(prob.config.graph.lag_s, params)
        )
        self.est = Estimates.empty(len(prob.t_key), prob.states.n)
        self.seen_aiding = False
        self.pending: list[int] = []  # fixed lag: keyframes not reported yet

    def record(self, k: int) -> None:
        """Store the engine's estimates and marginals of keyframe ``k``."""
        prob, engine = self.prob, self.engine
        self.est.store(
            k,
            engine.calculateEstimatePose3(X(k)),
            engine.calculateEstimateVector(V(k)),
            engine.calculateEstimateConstantBias(B(k)),
            engine.marginalCovariance(X(k)),
            engine.marginalCovariance(V(k)),
            engine.marginalCovariance(B(k)),
            self.seen_aiding or prob.yaw_given,
            prob.states.read(k, engine.calculateEstimateVector, engine.marginalCovariance),
        )
        if self.scale:
            self.est.store_scale(k, engine.calculateEstimateVector, engine.marginalCovariance)

    def gated(
        self,
        k: int,
        state: gtsam.NavState,
        cov_prev: FloatArray,
        extra: FloatArray,
        bias: gtsam.imuBias.ConstantBias,
    ) -> list[gtsam.NonlinearFactor]:
        """Measurement factors at keyframe k that pass the chi-square gate (``bias``: the
        bias estimate, for the zero-rate factors)."""
        prob, records = self.prob, self.records
        out = []
        mat = state.attitude().matrix()
        for i in prob.meas_at[k]:
            mf = prob.meas[i]
            heading = mf.item.kind in HEADING_KINDS
            lin = prob.states.model(mf.item, mat, state.velocity(), prob.tilt_coupling, extra,
                                    bias.gyroscope())  # fmt: skip
            if not np.isfinite(cov_prev).all():
                nis = np.nan  # first keyframe
            else:
                s = lin.H @ cov_prev @ lin.H.T + lin.R
                nis = float(lin.residual @ np.linalg.solve(s, lin.residual))
            limit = gate_limit(prob.config.gate_probability, lin.dim)
            if (self.seen_aiding or not heading) and nis > limit:
                reason = f"NIS {nis:.3g} > gate {limit:.3g} (chi2, {lin.dim} dof)"
                records.append(UpdateRecord(mf.item.t, mf.item.kind, lin.dim, nis, False, reason))
                if self.rejected is not None:
                    self.rejected[i] = (nis, reason)
                continue
            # The first heading (yaw/sun) is not gated: it aligns the yaw.
            records.append(UpdateRecord(mf.item.t, mf.item.kind, lin.dim, nis, True, ""))
            out.append(mf.factor)
            self.seen_aiding = self.seen_aiding or heading
        return out

    def update(self, k: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """Add keyframe ``k``'s factors and values; ISAM2 reports it at once, the fixed-lag
        smoother the keyframes about to leave its window."""
        prob, engine, pending = self.prob, self.engine, self.pending
        if self.solver == "isam2":
            engine.update(graph, values)
            self.record(k)
            return
        t_k = float(prob.t_key[k])
        while pending and prob.t_key[pending[0]] < t_k - prob.config.graph.lag_s:
            self.record(pending.pop(0))  # last chance before it is marginalized
        stamps = {X(k): t_k, V(k): t_k, B(k): t_k, **prob.states.timestamps(k, t_k)}
        if self.scale:
            stamps.update(dict.fromkeys(prob.scale_values(k).keys(), t_k))
        engine.update(graph, values, stamps)
        pending.append(k)

    def start(self) -> None:
        """The first keyframe: the priors, its constraints and its gated measurements."""
        prob = self.prob
        graph = gtsam.NonlinearFactorGraph()
        n_cov = N_ERROR + prob.states.n
        guess = prob.states.guess
        first = self.gated(0, prob.state0, np.full((n_cov, n_cov), np.nan), guess, prob.bias0)
        for f in prob.priors + list(prob.aux[0]) + first:
            graph.add(f)
        values = gtsam.Values()
        values.insert(X(0), prob.state0.pose())
        values.insert(V(0), prob.state0.velocity())
        values.insert(B(0), prob.bias0)
        if self.scale:
            values.insert(prob.scale_values(0))
            for f in prob.scale_factors_at(0):
                graph.add(f)
        values.insert(prob.states.initial(0, guess))
        self.update(0, graph, values)

    def current(
        self, k: int
    ) -> tuple[gtsam.NavState, gtsam.imuBias.ConstantBias, FloatArray, FloatArray]:
        """Keyframe ``k``'s state, bias, error covariance and variables' estimates."""
        prob, engine = self.prob, self.engine
        if self.solver == "isam2":
            state, bias = self.est.values(k)
            return state, bias, self.est.cov[k], self.est.extra[k]
        state = gtsam.NavState(
            engine.calculateEstimatePose3(X(k)), engine.calculateEstimateVector(V(k))
        )
        bias = engine.calculateEstimateConstantBias(B(k))
        cov_prev = fixed_lag_cov(engine, k, state, prob)
        extra = prob.states.read(k, engine.calculateEstimateVector)[0]
        return state, bias, cov_prev, extra

    def step(self, k: int) -> None:
        """Keyframe ``k + 1``: the IMU factor from ``k``, its constraints and its gated
        measurements, at the IMU prediction."""
        prob = self.prob
        state, bias, cov_prev, extra = self.current(k)
        extra = prob.states.predict(extra, k)
        pim = prob.preintegrate(k, bias, prob.imu_correction(state))
        pred = pim.predict(state, bias)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(prob.imu_factor(k, pim, self.scale))
        gated = self.gated(k + 1, pred, cov_prev, extra, bias)
        for f in [*prob.aux[k + 1], *prob.links[k + 1], *gated]:
            graph.add(f)
        values = gtsam.Values()
        values.insert(X(k + 1), pred.pose())
        values.insert(V(k + 1), pred.velocity())
        values.insert(B(k + 1), bias)
        values.insert(prob.states.initial(k + 1, extra))
        if self.scale:
            values.insert(prob.scale_values(k + 1))
            for f in prob.scale_factors_at(k + 1):
                graph.add(f)
        self.update(k + 1, graph, values)


def fixed_lag_cov(engine: Any, k: int, state: gtsam.NavState, prob: Problem) -> FloatArray:
    """Attitude and velocity blocks of the current marginal of keyframe ``k`` (for the
    gate), ESKF order, and those of ``prob.states``' variables."""
    n = prob.states.n
    cov = np.zeros((N_ERROR + n, N_ERROR + n))
    if n:
        cov[N_ERROR:, N_ERROR:] = prob.states.read(
            k, engine.calculateEstimateVector, engine.marginalCovariance
        )[1]
    pose = pose_cov_nav_from_body(state.attitude().matrix(), engine.marginalCovariance(X(k)))
    cov[ATT, ATT] = pose[:3, :3]
    cov[VEL, VEL] = engine.marginalCovariance(V(k))
    return cov
