"""Graph solvers: batch Gauss-Newton / LM with QR and post-fit gating, ISAM2, fixed-lag smoother.

Each solver takes a :class:`~polins.fusion.graph.problem.Problem`, appends one
:class:`~polins.fusion.items.UpdateRecord` per yaw/sun/zero-velocity factor to ``records`` and its
diagnostics to ``info``, and returns the keyframe
:class:`~polins.fusion.graph.problem.Estimates`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X
from numpy.typing import NDArray

from polins.fusion.config import MAX_GATE_ROUNDS, MAX_ITERATIONS
from polins.fusion.graph.factors import pose_cov_nav_from_body
from polins.fusion.graph.problem import Estimates, Problem
from polins.fusion.items import HEADING_KINDS, UpdateRecord, gate_limit
from polins.fusion.measurement import ATT, N_ERROR, VEL

FloatArray = NDArray[np.float64]

# [s] The post-fit gate compares an exceedance with those this close in time: an outlier
# inflates the residuals of its neighbours in the smoothed solution, not those further off.
GATE_SPAN_S = 30.0


class DivergedError(RuntimeError):
    """Gauss-Newton reached a non-finite cost."""


def gauss_newton_qr(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    *,
    max_iterations: int = 20,
    rel_tol: float = 1e-6,
) -> tuple[gtsam.Values, int, gtsam.GaussianFactorGraph]:
    """Gauss-Newton with sparse multifrontal QR until the cost changes by < ``rel_tol``;
    returns the values, the iterations and the graph linearized at the values.

    Why not GTSAM's Levenberg-Marquardt or Cholesky: without position (and, with yaw-only
    aiding, velocity) measurements the position and velocity marginals grow to km and tens
    of m/s while the bias random-walk links between 0.2 s keyframes carry an information
    of ~1e14; the normal equations then have condition numbers beyond 1e16 (Cholesky
    reports an "indeterminate system") and LM's ``lambda I`` damping dominates the weakly
    observed directions, so LM creeps for a hundred iterations. QR on the Jacobian meets
    only the square root of that condition number, and the problem is nearly linear (the
    nonlinearity is the attitude), so undamped Gauss-Newton converges in 3-10 iterations.
    The first step from dead reckoning may raise the cost; convergence is judged on the
    change of the cost, not on a decrease. (The loop is written out: it is ~10x faster
    than ``gtsam.GaussNewtonOptimizer.iterate`` from Python on these graphs.) The cost at
    each iterate is that of the graph linearized there at a zero step (equal for Gaussian
    noise models): the Python factors are evaluated once per iteration, and the last
    linearization serves the marginals. Raises :class:`DivergedError` on a non-finite cost.
    """
    ordering = graph.orderingCOLAMD()
    previous = graph.error(values)
    linear = graph.linearize(values)
    for iteration in range(1, max_iterations + 1):
        delta = linear.eliminateMultifrontal(ordering, gtsam.EliminateQR).optimize()
        values = values.retract(delta)
        linear = graph.linearize(values)
        zero = gtsam.VectorValues(delta)
        zero.setZero()
        error = linear.error(zero)
        if not np.isfinite(error):
            raise DivergedError("Gauss-Newton diverged (non-finite cost)")
        if iteration > 1 and abs(previous - error) <= rel_tol * max(error, 1.0):
            return values, iteration, linear
        previous = error
    return values, max_iterations, linear


def levenberg_marquardt_qr(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    *,
    max_iterations: int = 100,
    rel_tol: float = 1e-6,
) -> tuple[gtsam.Values, int, gtsam.GaussianFactorGraph]:
    """GTSAM's Levenberg-Marquardt with multifrontal QR (``optimizer="levenberg-marquardt"``,
    and the fallback if Gauss-Newton fails). Robust far from the solution, but its
    ``lambda I`` damping slows it down in the weakly observed directions (see
    :func:`gauss_newton_qr`): expect tens of iterations."""
    params = gtsam.LevenbergMarquardtParams()
    params.setLinearSolverType("MULTIFRONTAL_QR")
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(rel_tol)
    params.setAbsoluteErrorTol(0.0)
    params.setlambdaInitial(1e-9)
    params.setlambdaLowerBound(1e-15)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    return result, int(optimizer.iterations()), graph.linearize(result)


def marginal_covariance_qr(bayes_tree: gtsam.GaussianBayesTree, key: int) -> FloatArray:
    """Marginal covariance of one variable from a QR-eliminated Bayes tree.

    ``marginalFactor(key, EliminateQR)`` gives the square-root information ``R`` of the
    marginal; the covariance is ``R^-1 R^-T`` (never ``J^T J``).
    """
    conditional = bayes_tree.marginalFactor(key, gtsam.EliminateQR)
    # R() is a view into the conditional's memory: copy it while the conditional is alive.
    r = np.array(conditional.R(), dtype=float, order="C", copy=True)
    r_inv = np.linalg.inv(r)
    return r_inv @ r_inv.T


def marginal_covariances(
    bayes_tree: gtsam.GaussianBayesTree, dims: Mapping[int, int]
) -> dict[int, FloatArray]:
    """Marginal covariance of every variable of a QR-eliminated Bayes tree, in one pass from
    the roots (the result of :func:`marginal_covariance_qr` for each key).

    Each clique's conditional ``R x_F + S x_S = d`` (unit noise, ``F`` its frontal, ``S`` its
    separator variables, ``dims`` their sizes) gives the joint covariance of ``(F, S)`` from
    that of ``S``, which lies in the parent's joint (the running intersection property):
    ``P_FS = -A P_SS``, ``P_FF = R^-1 R^-T + A P_SS A^T`` with ``A = R^-1 S``. A parent's
    joint is kept until its children are done: the work is linear in the cliques.
    """
    out: dict[int, FloatArray] = {}
    # (clique, the parent's joint covariance and the offsets of its keys)
    stack: list[tuple[Any, FloatArray | None, dict[int, int] | None]]
    stack = [(root, None, None) for root in bayes_tree.roots()]
    while stack:
        clique, parent_cov, parent_at = stack.pop()
        cond = clique.conditional()
        r = np.array(cond.R(), dtype=float, copy=True)
        keys = list(cond.keys())
        at, offset, n_front = {}, 0, 0
        for key in keys:
            at[key] = offset
            offset += dims[key]
            n_front += offset <= r.shape[0]
        r_inv = np.linalg.inv(r)  # (upper triangular, small)
        cov = np.empty((offset, offset))
        cov[: r.shape[0], : r.shape[0]] = r_inv @ r_inv.T
        if offset > r.shape[0]:
            assert parent_cov is not None and parent_at is not None
            sep = np.concatenate([parent_at[k] + np.arange(dims[k]) for k in keys[n_front:]])
            p_ss = parent_cov[np.ix_(sep, sep)]
            a = r_inv @ np.array(cond.S(), dtype=float, copy=True)
            p_fs = -a @ p_ss
            cov[: r.shape[0], : r.shape[0]] += a @ p_ss @ a.T
            cov[: r.shape[0], r.shape[0] :] = p_fs
            cov[r.shape[0] :, : r.shape[0]] = p_fs.T
            cov[r.shape[0] :, r.shape[0] :] = p_ss
        for key in keys[:n_front]:
            sl = slice(at[key], at[key] + dims[key])
            out[key] = cov[sl, sl].copy()
        stack.extend((clique[j], cov, at) for j in range(clique.nrChildren()))
    return out


def optimize(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, prob: Problem
) -> tuple[gtsam.Values, int, gtsam.GaussianFactorGraph]:
    """The batch optimizer of ``prob.config``; Levenberg-Marquardt if Gauss-Newton fails.
    Returns the values, the iterations and the graph linearized at the values."""
    c = prob.config
    if c.graph.optimizer == "gauss-newton":
        try:
            return gauss_newton_qr(graph, values, max_iterations=MAX_ITERATIONS)
        except RuntimeError as exc:
            # DivergedError, or GTSAM's IndeterminantLinearSystemException (a RuntimeError
            # in Python, "Indeterminant linear system detected ..."): fall back to damping.
            if not isinstance(exc, DivergedError) and "Indeterminant" not in str(exc):
                raise
    return levenberg_marquardt_qr(graph, values, max_iterations=5 * MAX_ITERATIONS)


def batch_graph(
    prob: Problem, rejected: set[int], linearization: gtsam.Values | None
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Whole-log graph with initial values (dead reckoning, or ``linearization``, whose
    velocity, position and bias also set the transport rate and the bias of the
    preintegration)."""
    graph = gtsam.NonlinearFactorGraph()
    for f in prob.priors:
        graph.add(f)
    values = gtsam.Values()
    state, bias = prob.state0, prob.bias0
    values.insert(X(0), state.pose())
    values.insert(V(0), state.velocity())
    values.insert(B(0), bias)
    values.insert(prob.scale_values(0))
    values.insert(prob.states.initial(0, prob.states.guess))
    for k in range(len(prob.t_key)):
        for f in prob.factors_at(k, rejected) + prob.scale_factors_at(k):
            graph.add(f)
        if k == len(prob.t_key) - 1:
            break
        if linearization is not None:
            state = gtsam.NavState(linearization.atPose3(X(k)), linearization.atVector(V(k)))
            bias = linearization.atConstantBias(B(k))
        pim = prob.preintegrate(k, bias, prob.imu_correction(state))
        graph.add(prob.imu_factor(k, pim))
        if linearization is None:
            state = pim.predict(state, bias)
            values.insert(X(k + 1), state.pose())
            values.insert(V(k + 1), state.velocity())
            values.insert(B(k + 1), bias)
            values.insert(prob.states.initial(k + 1, prob.states.guess))
            values.insert(prob.scale_values(k + 1))
    return graph, (values if linearization is None else linearization)


def solve_batch(
    prob: Problem,
    records: list[UpdateRecord],
    info: dict[str, Any],
    causal: dict[int, tuple[float, str]] | None = None,
    progress: Callable[[str], None] | None = None,
    start: gtsam.Values | None = None,
) -> Estimates:
    """Gauss-Newton (QR) over the whole log, post-fit gating, QR marginals.

    The zero-velocity factors of the standstill detector (``Problem.detected``) are gated
    first by a causal pass, as the ESKF gates them: the detector also fires at constant
    speed, and so many wrong factors bend the whole solution, which a post-fit gate cannot
    undo. ``causal`` gives that pass's verdicts (index into ``prob.meas`` -> NIS, reason;
    :func:`polins.fusion.graph.fuse_graph` takes them from the ESKF's run); without it an
    ISAM2 pass (:func:`solve_incremental`) gates them. ``progress`` is told each stage.
    ``start``: initial values of every key, also the first linearization point of the
    preintegration (:func:`polins.fusion.graph.start.filter_values`); without them, dead
    reckoning, and with the Earth rate the first solve is repeated once, re-preintegrated
    with the transport rate and bias of the first.
    """
    rejected: dict[int, tuple[float, str]] = {}
    if prob.detected and causal is None:
        causal = {}
        # (without scale-factor variables: this pass only gates)
        solve_incremental(prob, [], {}, solver="isam2", rejected=causal, scale=False)
    if prob.detected and causal:
        rejected = {i: (nis, f"causal {why}") for i, (nis, why) in causal.items()
                    if i in prob.detected}  # fmt: skip
    result: gtsam.Values | None = None
    iterations: list[int] = []
    for gate_round in range(1 + MAX_GATE_ROUNDS):
        # A re-solve (after gating, or the repeat from dead reckoning with the Earth rate)
        # starts from the last result and is preintegrated there.
        repeat = prob.earth_rate and result is None and start is None
        for _ in range(2 if repeat else 1):
            if progress is not None:
                progress(f"gate round {gate_round + 1}, solve {len(iterations) + 1}")
            lin = result if result is not None else start
            graph, values = batch_graph(prob, set(rejected), lin)
            result, it, linear = optimize(graph, values, prob)
            iterations.append(it)
        assert result is not None
        if progress is not None:
            progress(f"gate round {gate_round + 1}, marginals")
        bayes_tree = linear.eliminateMultifrontal(graph.orderingCOLAMD(), gtsam.EliminateQR)
        zero = bayes_tree.optimize()  # (a zero step: the cost at the result is linear's)
        zero.setZero()
        error, n_factors = linear.error(zero), graph.size()
        del linear, graph  # (held only by the next round's solve: memory)
        est = Estimates.empty(len(prob.t_key), prob.states.n)
        dims = {key: zero.dim(key) for key in result.keys()}
        marginal = marginal_covariances(bayes_tree, dims).__getitem__
        # the scale factors are constants: one marginal (the last keyframe's) for all
        last = prob.scale_values(len(prob.t_key) - 1).keys()
        scale_cov = [marginal(key) for key in last]
        for k in range(len(prob.t_key)):
            est.store(
                k,
                result.atPose3(X(k)),
                result.atVector(V(k)),
                result.atConstantBias(B(k)),
                marginal(X(k)),
                marginal(V(k)),
                marginal(B(k)),
                prob.yaw_given or prob.n_headings > 0,
                prob.states.read(k, result.atVector, marginal),
            )
            if prob.scale_jac is not None:
                cov_of = dict(zip(prob.scale_values(k).keys(), scale_cov, strict=True))
                est.store_scale(k, result.atVector, cov_of.__getitem__)
        del bayes_tree, marginal
        new = post_fit_gate(prob, est, rejected, records, final=gate_round == MAX_GATE_ROUNDS)
        if not new:
            break
        rejected.update(new)
    assert result is not None
    info.update(iterations=iterations, error=error, n_factors=n_factors, rejected=sorted(rejected))
    return est


def post_fit_gate(
    prob: Problem,
    est: Estimates,
    rejected: dict[int, tuple[float, str]],
    records: list[UpdateRecord],
    *,
    final: bool,
) -> dict[int, tuple[float, str]]:
    """Post-fit chi-square gate of the yaw, sun and zero-velocity factors.

    The post-fit residual of a correct measurement has covariance ``R - H P H^T``
    (``P`` the smoothed covariance), so ``r^T (R - H P H^T)^-1 r`` is chi-square with
    ``dim`` degrees of freedom. An outlier also inflates its neighbours' residuals, so each
    round gates only the grossest exceedances (NIS at least half the largest within
    ``GATE_SPAN_S`` of it, :func:`local_worst`); the graph is re-solved and the gate
    repeated. Outliers further apart are gated in the same round: the rounds do not grow
    with the log's length. Returns the newly gated factors (empty: ``records``, one per
    factor, has been written).
    """
    rows: list[UpdateRecord] = []
    exceed: dict[int, tuple[float, str]] = {}
    for i, mf in enumerate(prob.meas):
        lin = prob.states.model(mf.item, est.mat_nb[mf.k], est.vel_n[mf.k], prob.tilt_coupling,
                                est.extra[mf.k], est.bias[mf.k, :3])  # fmt: skip
        if i in rejected:
            nis, reason = rejected[i]
            rows.append(UpdateRecord(mf.item.t, mf.item.kind, lin.dim, nis, False, reason))
            continue
        s = lin.R - lin.H @ est.cov[mf.k] @ lin.H.T
        s = 0.5 * (s + s.T) + 1e-6 * lin.R  # kept regular when the measurement dominates
        nis = float(lin.residual @ np.linalg.solve(s, lin.residual))
        limit = gate_limit(prob.config.gate_probability, lin.dim)
        if nis > limit and not final:
            reason = f"post-fit NIS {nis:.3g} > gate {limit:.3g} (chi2, {lin.dim} dof)"
            exceed[i] = (nis, reason)
        rows.append(UpdateRecord(mf.item.t, mf.item.kind, lin.dim, nis, True, ""))
    if not exceed:
        records.extend(rows)
        return {}
    index = np.array(sorted(exceed, key=lambda i: prob.meas[i].item.t))
    t_exceed = np.array([prob.meas[i].item.t for i in index])
    nis_exceed = np.array([exceed[i][0] for i in index])
    worst = local_worst(t_exceed, nis_exceed, GATE_SPAN_S)
    return {int(i): exceed[int(i)] for i in index[nis_exceed >= 0.5 * worst]}


def local_worst(t: FloatArray, nis: FloatArray, span_s: float) -> FloatArray:
    """The largest of ``nis`` within ``span_s`` [s] of each time ``t`` [s] (sorted)."""
    lo = np.searchsorted(t, t - span_s, side="left")
    hi = np.searchsorted(t, t + span_s, side="right")
    return np.array([nis[a:b].max() for a, b in zip(lo, hi, strict=True)])


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
        for f in list(prob.aux[k + 1]) + self.gated(k + 1, pred, cov_prev, extra, bias):
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
