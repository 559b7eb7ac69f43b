"""The batch graph solver: Gauss-Newton / LM with QR over the whole log, QR marginals, post-fit gating.

:func:`solve_batch` takes a :class:`~polins.fusion.graph.problem.Problem`, appends one
:class:`~polins.fusion.items.UpdateRecord` per yaw/sun/zero-velocity factor to ``records`` and its
diagnostics to ``info``, and returns the keyframe
:class:`~polins.fusion.graph.estimates.Estimates`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X
from numpy.typing import NDArray
from scipy.linalg.lapack import dtrtri

from polins.fusion.config import MAX_GATE_ROUNDS, MAX_ITERATIONS
from polins.fusion.graph.batched import FactorBatch, ScaleImuBatch
from polins.fusion.graph.batched import linearize as batched_linearize
from polins.fusion.graph.estimates import Estimates
from polins.fusion.graph.incremental import solve_incremental
from polins.fusion.graph.problem import Problem
from polins.fusion.items import UpdateRecord, gate_limit

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
    linearize: Callable[[gtsam.Values], gtsam.GaussianFactorGraph] | None = None,
) -> tuple[gtsam.Values, int, gtsam.GaussianBayesTree, float]:
    """Gauss-Newton with sparse multifrontal QR until the step's predicted decrease of the
    cost is < ``rel_tol`` of the cost; returns the values after that step, the iterations,
    the Bayes tree of the last linearization and the cost the linearization predicts.

    Why not GTSAM's Levenberg-Marquardt or Cholesky: without position (and, with yaw-only
    aiding, velocity) measurements the position and velocity marginals grow to km and tens
    of m/s while the bias random-walk links between 0.2 s keyframes carry an information
    of ~1e14; the normal equations then have condition numbers beyond 1e16 (Cholesky
    reports an "indeterminate system") and LM's ``lambda I`` damping dominates the weakly
    observed directions, so LM creeps for a hundred iterations. QR on the Jacobian meets
    only the square root of that condition number, and the problem is nearly linear (the
    nonlinearity is the attitude), so undamped Gauss-Newton converges in 2-5 iterations.
    The first step from dead reckoning may raise the cost: convergence is judged on the
    decrease the linearization predicts for its step (``|r|^2 - |r - A delta|^2``), which
    for a nearly linear problem is the next step's change of the cost. So the last
    elimination both ends the iterations and gives the marginals (its step, far below a
    sigma, is applied; the marginals at the point before it differ by a second-order
    amount). (The loop is written out: it is ~10x faster than
    ``gtsam.GaussNewtonOptimizer.iterate`` from Python on these graphs.) ``linearize``
    replaces ``graph.linearize`` (the vectorized factors,
    :func:`polins.fusion.graph.batched.linearize`). Raises :class:`DivergedError` on a non-finite cost.
    """
    ordering = graph.orderingCOLAMD()
    for iteration in range(1, max_iterations + 1):
        linear = graph.linearize(values) if linearize is None else linearize(values)
        bayes_tree = linear.eliminateMultifrontal(ordering, gtsam.EliminateQR)
        delta = bayes_tree.optimize()
        zero = gtsam.VectorValues(delta)
        zero.setZero()
        error, predicted = linear.error(zero), linear.error(delta)
        del linear
        if not (np.isfinite(error) and np.isfinite(predicted)):
            raise DivergedError("Gauss-Newton diverged (non-finite cost)")
        values = values.retract(delta)
        if error - predicted <= rel_tol * max(error, 1.0):
            return values, iteration, bayes_tree, predicted
    return values, max_iterations, bayes_tree, predicted


def levenberg_marquardt_qr(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    *,
    max_iterations: int = 100,
    rel_tol: float = 1e-6,
) -> tuple[gtsam.Values, int, gtsam.GaussianBayesTree, float]:
    """GTSAM's Levenberg-Marquardt with multifrontal QR (``optimizer="levenberg-marquardt"``,
    and the fallback if Gauss-Newton fails). Robust far from the solution, but its
    ``lambda I`` damping slows it down in the weakly observed directions (see
    :func:`gauss_newton_qr`): expect tens of iterations. Returns the values, the
    iterations, the QR Bayes tree linearized at the values and the cost."""
    params = gtsam.LevenbergMarquardtParams()
    params.setLinearSolverType("MULTIFRONTAL_QR")
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(rel_tol)
    params.setAbsoluteErrorTol(0.0)
    params.setlambdaInitial(1e-9)
    params.setlambdaLowerBound(1e-15)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    linear = graph.linearize(result)
    bayes_tree = linear.eliminateMultifrontal(graph.orderingCOLAMD(), gtsam.EliminateQR)
    return result, int(optimizer.iterations()), bayes_tree, float(graph.error(result))


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
        n_r = r.shape[0]
        keys = list(cond.keys())
        at, offset, n_front = {}, 0, 0
        for key in keys:
            at[key] = offset
            offset += dims[key]
            n_front += offset <= n_r
        r_inv, fail = dtrtri(r, lower=0)  # (upper triangular, small)
        if fail:
            raise np.linalg.LinAlgError(f"singular conditional in the Bayes tree ({fail})")
        cov = np.empty((offset, offset))
        cov[:n_r, :n_r] = r_inv @ r_inv.T
        if offset > n_r:
            assert parent_cov is not None and parent_at is not None
            sep = [i for k in keys[n_front:] for i in range(parent_at[k], parent_at[k] + dims[k])]
            p_ss = parent_cov.take(sep, 0).take(sep, 1)
            a = r_inv @ cond.S()
            p_fs = -a @ p_ss
            cov[:n_r, :n_r] -= p_fs @ a.T
            cov[:n_r, n_r:] = p_fs
            cov[n_r:, :n_r] = p_fs.T
            cov[n_r:, n_r:] = p_ss
        for key in keys[:n_front]:
            lo = at[key]
            out[key] = cov[lo : lo + dims[key], lo : lo + dims[key]].copy()
        stack.extend((clique[j], cov, at) for j in range(clique.nrChildren()))
    return out


def optimize(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    prob: Problem,
    linearize: Callable[[gtsam.Values], gtsam.GaussianFactorGraph] | None = None,
) -> tuple[gtsam.Values, int, gtsam.GaussianBayesTree, float]:
    """The batch optimizer of ``prob.config``; Levenberg-Marquardt if Gauss-Newton fails.
    Returns the values, the iterations, the QR Bayes tree of the last linearization and
    the cost (:func:`gauss_newton_qr`)."""
    c = prob.config
    if c.graph.optimizer == "gauss-newton":
        try:
            return gauss_newton_qr(
                graph, values, max_iterations=MAX_ITERATIONS, linearize=linearize
            )
        except RuntimeError as exc:
            # DivergedError, or GTSAM's IndeterminantLinearSystemException (a RuntimeError
            # in Python, "Indeterminant linear system detected ..."): fall back to damping.
            if not isinstance(exc, DivergedError) and "Indeterminant" not in str(exc):
                raise
    return levenberg_marquardt_qr(graph, values, max_iterations=5 * MAX_ITERATIONS)


@dataclass(eq=False)
class BatchGraph:
    """The whole-log graph of the batch solver (:func:`batch_graph`): the graph, its
    initial values, the batches of its Python factors (:mod:`polins.fusion.graph.batched`)
    and the index in the graph of each measurement factor (index into ``Problem.meas``)."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    batches: list[FactorBatch]
    where: dict[int, int]

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """The graph linearized at ``values``, its Python factors evaluated by type."""
        return batched_linearize(self.graph, values, self.batches)

    def remove(self, gated: Iterable[int]) -> None:
        """Take the measurement factors ``gated`` (indices into ``Problem.meas``) out."""
        for i in gated:
            self.graph.remove(self.where.pop(i))


def batch_graph(
    prob: Problem, rejected: set[int], linearization: gtsam.Values | None
) -> BatchGraph:
    """Whole-log graph without the ``rejected`` measurement factors, with initial values
    (dead reckoning, or ``linearization``, whose velocity, position and bias also set the
    transport rate and the bias of the preintegration)."""
    imu_batch = ScaleImuBatch()
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
    where: dict[int, int] = {}
    for k in range(len(prob.t_key)):
        for f in prob.aux[k] + prob.scale_factors_at(k):
            graph.add(f)
        for i in prob.meas_at[k]:
            if i not in rejected:
                where[i] = graph.size()
                graph.add(prob.meas[i].factor)
        if k == len(prob.t_key) - 1:
            break
        if linearization is not None:
            state = gtsam.NavState(linearization.atPose3(X(k)), linearization.atVector(V(k)))
            bias = linearization.atConstantBias(B(k))
        pim = prob.preintegrate(k, bias, prob.imu_correction(state))
        graph.add(prob.imu_factor(k, pim, batch=imu_batch))
        if linearization is None:
            state = pim.predict(state, bias)
            values.insert(X(k + 1), state.pose())
            values.insert(V(k + 1), state.velocity())
            values.insert(B(k + 1), bias)
            values.insert(prob.states.initial(k + 1, prob.states.guess))
            values.insert(prob.scale_values(k + 1))
    values = values if linearization is None else linearization
    return BatchGraph(graph, values, [*prob.batches(), imu_batch], where)


def keyframe_estimates(
    prob: Problem, result: gtsam.Values, bayes_tree: gtsam.GaussianBayesTree
) -> Estimates:
    """The keyframes' values and marginals (:func:`marginal_covariances`) of a solve."""
    est = Estimates.empty(len(prob.t_key), prob.states.n)
    marginal = marginal_covariances(bayes_tree, result.dims()).__getitem__
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
    return est


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
    ``start``: initial values of every key, also the linearization point of the
    preintegration (:func:`polins.fusion.graph.start.filter_values`); without them, dead
    reckoning, and with the Earth rate a first solve from there gives the linearization
    point of the preintegration. Each gate round re-solves the same graph without the
    gated factors, from the last result.
    """
    rejected: dict[int, tuple[float, str]] = {}
    if prob.detected and causal is None:
        causal = {}
        # (without scale-factor variables: this pass only gates)
        solve_incremental(prob, [], {}, solver="isam2", rejected=causal, scale=False)
    if prob.detected and causal:
        rejected = {i: (nis, f"causal {why}") for i, (nis, why) in causal.items()
                    if i in prob.detected}  # fmt: skip
    iterations: list[int] = []
    built = batch_graph(prob, set(rejected), start)
    if prob.earth_rate and start is None:
        if progress is not None:
            progress("solve 1 from dead reckoning")
        first, it, _tree, _error = optimize(built.graph, built.values, prob, built.linearize)
        iterations.append(it)
        built = batch_graph(prob, set(rejected), first)
    result = built.values
    for gate_round in range(1 + MAX_GATE_ROUNDS):
        if progress is not None:
            progress(f"gate round {gate_round + 1}, solve {len(iterations) + 1}")
        result, it, bayes_tree, error = optimize(built.graph, result, prob, built.linearize)
        iterations.append(it)
        if progress is not None:
            progress(f"gate round {gate_round + 1}, marginals")
        est = keyframe_estimates(prob, result, bayes_tree)
        del bayes_tree  # (memory)
        new = post_fit_gate(prob, est, rejected, records, final=gate_round == MAX_GATE_ROUNDS)
        if not new:
            break
        rejected.update(new)
        built.remove(new)
    info.update(iterations=iterations, error=error, n_factors=built.graph.nrFactors(),
                rejected=sorted(rejected))  # fmt: skip
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
