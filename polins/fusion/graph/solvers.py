"""The batch graph solver: Gauss-Newton / LM with QR over the whole log, QR marginals, post-fit gating.

:func:`solve_batch` takes a :class:`~polins.fusion.graph.problem.Problem`, appends one
:class:`~polins.fusion.items.UpdateRecord` per yaw/sun/zero-velocity factor to ``records`` and its
diagnostics to ``info``, and returns the keyframe
:class:`~polins.fusion.graph.estimates.Estimates`.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X
from numpy.typing import NDArray
from scipy.linalg.lapack import dtrtri

from polins.fusion.config import MAX_GATE_ROUNDS, MAX_ITERATIONS
from polins.fusion.graph import windows as windows_module
from polins.fusion.graph.estimates import Estimates
from polins.fusion.graph.incremental import solve_incremental
from polins.fusion.graph.problem import Problem
from polins.fusion.graph.windows import (
    OVERLAP_S,
    BatchGraph,
    batch_graph,
    past_prior,
    window_values,
    windows,
)
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


def keyframe_estimates(
    prob: Problem,
    result: gtsam.Values,
    bayes_tree: gtsam.GaussianBayesTree,
    frames: range,
    est: Estimates,
) -> None:
    """The values and marginals (:func:`marginal_covariances`) of keyframes ``frames`` of a
    solve into ``est``."""
    marginal = marginal_covariances(bayes_tree, result.dims()).__getitem__
    # the scale factors are constants: one marginal (the last keyframe's) for all
    last = prob.scale_values(frames[-1]).keys() if result.exists(X(frames[-1])) else []
    scale_cov = [marginal(key) for key in last]
    for k in frames:
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


def solve_batch(
    prob: Problem,
    records: list[UpdateRecord],
    info: dict[str, Any],
    causal: dict[int, tuple[float, str]] | None = None,
    progress: Callable[[str], None] | None = None,
    start: gtsam.Values | None = None,
    window_s: float | None = None,
) -> Estimates:
    """Gauss-Newton (QR) over the log, post-fit gating, QR marginals; a log longer than
    ``window_s`` [s] (default ``windows.WINDOW_S``) in overlapping windows
    (:mod:`polins.fusion.graph.windows`).

    The zero-velocity factors of the standstill detector (``Problem.detected``) are gated
    first by a causal pass, as the ESKF gates them: the detector also fires at constant
    speed, and so many wrong factors bend the whole solution, which a post-fit gate cannot
    undo. ``causal`` gives that pass's verdicts (index into ``prob.meas`` -> NIS, reason;
    :func:`polins.fusion.graph.fuse_graph` takes them from the ESKF's run); without it an
    ISAM2 pass (:func:`solve_incremental`) gates them. ``progress`` is told each stage.
    ``start``: initial values of every key, also the linearization point of the
    preintegration (:func:`polins.fusion.graph.start.filter_values`); without them, dead
    reckoning (one window), and with the Earth rate a first solve from there gives the
    linearization point of the preintegration. Each gate round re-solves the same graph
    without the gated factors, from the last result.
    """
    rejected: dict[int, tuple[float, str]] = {}
    if prob.detected and causal is None:
        causal = {}
        # (without scale-factor variables: this pass only gates)
        solve_incremental(prob, [], {}, solver="isam2", rejected=causal, scale=False)
    if prob.detected and causal:
        rejected = {i: (nis, f"causal {why}") for i, (nis, why) in causal.items()
                    if i in prob.detected}  # fmt: skip
    span_s = windows_module.WINDOW_S if window_s is None else window_s
    spans = windows(prob.t_key, span_s if start is not None else np.inf, OVERLAP_S)
    est = Estimates.empty(len(prob.t_key), prob.states.n)
    info.update(iterations=[], error=0.0, n_factors=0, rejected=[], windows=len(spans))
    priors: list[gtsam.NonlinearFactor] | None = None
    result = None
    for w, (frames, join) in enumerate(spans):
        if progress is not None and len(spans) > 1:
            progress(f"window {w + 1} of {len(spans)}")
        init = start
        if start is not None and result is not None:  # the overlap from the last window
            init = window_values(prob, start, frames, result)
        built, result = solve_window(prob, frames, join, priors, init, dict(rejected), records,
                                     info, est, progress)  # fmt: skip
        if join < len(prob.t_key):
            priors = past_prior(prob, built, result, join)
        del built
    return est


def solve_window(
    prob: Problem,
    frames: range,
    join: int,
    priors: list[gtsam.NonlinearFactor] | None,
    start: gtsam.Values | None,
    rejected: dict[int, tuple[float, str]],
    records: list[UpdateRecord],
    info: dict[str, Any],
    est: Estimates,
    progress: Callable[[str], None] | None,
) -> tuple[BatchGraph, gtsam.Values]:
    """One window's solve and gate rounds (:func:`solve_batch`): its keyframes before
    ``join`` into ``est``, their measurements' verdicts into ``records``; returns the
    window's graph and result."""
    built = batch_graph(prob, set(rejected), start, frames, priors)
    iterations = info["iterations"]
    if prob.earth_rate and start is None:
        if progress is not None:
            progress("solve 1 from dead reckoning")
        first, it, _tree, _error = optimize(built.graph, built.values, prob, built.linearize)
        iterations.append(it)
        built = batch_graph(prob, set(rejected), first, frames, priors)
    result = built.values
    inside = [i for k in frames for i in prob.meas_at[k]]
    owned = {i for k in frames if k < join for i in prob.meas_at[k]}
    for gate_round in range(1 + MAX_GATE_ROUNDS):
        if progress is not None:
            progress(f"gate round {gate_round + 1}, solve {len(iterations) + 1}")
        result, it, bayes_tree, error = optimize(built.graph, result, prob, built.linearize)
        iterations.append(it)
        if progress is not None:
            progress(f"gate round {gate_round + 1}, marginals")
        keyframe_estimates(prob, result, bayes_tree, range(frames[0], join), est)
        del bayes_tree  # (memory)
        final = gate_round == MAX_GATE_ROUNDS
        new = post_fit_gate(prob, est, rejected, records, final=final, indices=inside,
                            owned=owned)  # fmt: skip
        if not new:
            break
        rejected.update(new)
        built.remove(new)
    info["error"] += error
    info["n_factors"] += built.graph.nrFactors()
    info["rejected"] = sorted({*info["rejected"], *(i for i in rejected if i in owned)})
    return built, result


def post_fit_gate(
    prob: Problem,
    est: Estimates,
    rejected: dict[int, tuple[float, str]],
    records: list[UpdateRecord],
    *,
    final: bool,
    indices: Sequence[int] | None = None,
    owned: Collection[int] | None = None,
) -> dict[int, tuple[float, str]]:
    """Post-fit chi-square gate of the yaw, sun and zero-velocity factors.

    The post-fit residual of a correct measurement has covariance ``R - H P H^T``
    (``P`` the smoothed covariance), so ``r^T (R - H P H^T)^-1 r`` is chi-square with
    ``dim`` degrees of freedom. An outlier also inflates its neighbours' residuals, so each
    round gates only the grossest exceedances (NIS at least half the largest within
    ``GATE_SPAN_S`` of it, :func:`local_worst`); the graph is re-solved and the gate
    repeated. Outliers further apart are gated in the same round: the rounds do not grow
    with the log's length. Returns the newly gated factors (empty: ``records``, one per
    factor, has been written). ``indices``: the factors to gate (default all; a window's),
    ``owned``: those to write to ``records`` (default all).
    """
    rows: list[UpdateRecord] = []
    exceed: dict[int, tuple[float, str]] = {}
    for i in range(len(prob.meas)) if indices is None else indices:
        mf = prob.meas[i]
        lin = prob.states.model(mf.item, est.mat_nb[mf.k], est.vel_n[mf.k], prob.tilt_coupling,
                                est.extra[mf.k], est.bias[mf.k, :3])  # fmt: skip
        report = owned is None or i in owned
        if i in rejected:
            nis, reason = rejected[i]
            if report:
                rows.append(UpdateRecord(mf.item.t, mf.item.kind, lin.dim, nis, False, reason))
            continue
        s = lin.R - lin.H @ est.cov[mf.k] @ lin.H.T
        s = 0.5 * (s + s.T) + 1e-6 * lin.R  # kept regular when the measurement dominates
        nis = float(lin.residual @ np.linalg.solve(s, lin.residual))
        limit = gate_limit(prob.config.gate_probability, lin.dim)
        if nis > limit and not final:
            reason = f"post-fit NIS {nis:.3g} > gate {limit:.3g} (chi2, {lin.dim} dof)"
            exceed[i] = (nis, reason)
        if report:
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
