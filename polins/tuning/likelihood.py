"""Maximum-likelihood tuning of named noise parameters from the filter's innovation likelihood, with identifiability.

The innovations of a Kalman filter are independent Gaussians ``nu_k ~ N(0, S_k)`` when its
noise model is right, so the negative log-likelihood of a log under noise parameters
``theta`` is (docs/tuning.md)::

    L(theta) = 1/2 sum_k [ log det(2 pi S_k) + nu_k' S_k^-1 nu_k ]

summed over the accepted updates of :func:`polins.fusion.run_fusion` run without a gate
(a gate would make ``L`` jump where an update crosses it). :func:`tune` minimizes ``L`` over
the logarithms of the parameters (bounded L-BFGS-B), and judges each parameter by its sigma
in log space. The Cramér-Rao sigma, from the observed Fisher information (the numerical
Hessian ``H`` of ``L`` at the optimum, :func:`central_hessian`), is the precision under the
filter's model; when that model is wrong (a pseudo-measurement sigma far from the vehicle's
truth) or the innovations are not white, the estimate's spread is the sandwich
``H^-1 J H^-1`` with ``J`` the variance of the score summed over time blocks
(:func:`score_information`, :func:`sandwich_sigma`). A parameter whose larger sigma exceeds
``max_log_sigma`` (default log 2: the log cannot tell it from half or double) is
unidentifiable. Unidentifiable parameters keep their starting values; one whose estimate
lies on the search bound (start ``/ search_factor`` or ``* search_factor``) is not
identified either, but takes the bound: the likelihood keeps rising beyond it (a
simulator's exact standstill asks for a zero-velocity sigma of 0). The identifiable ones
are refitted with the others held there.

The standstill detector's test follows the IMU noise (:mod:`polins.fusion.vehicle`), so a
candidate's ARW would change which epochs carry zero-velocity and zero-rate updates and the
likelihood would jump. Each search holds the detector's model
(``FuseConfig.standstill_model``), first at the start values, then at the search's
estimate, until the estimate's rest epochs are those it was fitted with (at most
:data:`DETECTOR_ROUNDS` searches): the tuned file then detects the epochs it was tuned on.

Parameters (:data:`polins.tuning.parameters.PARAMETERS`): the white-noise and random-walk densities of the IMU model
(SI, :class:`polins.models.ImuModel` fields) and the measurement-noise filter options:
``yaw_floor_deg`` / ``sun_floor_deg``, a floor [deg] added in quadrature to every
``yaw_std`` / ``sun_std`` of the measurements, ``yaw_std_scale`` / ``sun_std_scale``, a
factor on them (applied before the floor), and the sigmas of the vehicle's
pseudo-measurements and odometer, ``nhc_std``, ``standstill_std``, ``odometer_std``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.optimize import minimize

from polins.fusion import FuseConfig, FusionResult, ImplausibleRunError, run_fusion
from polins.fusion.vehicle import vehicle_items
from polins.tuning.innovations import innovation_arrays, innovation_stats
from polins.tuning.parameters import check_params, start_values, with_values
from polins.tuning.result import TuneResult

FloatArray = NDArray[np.float64]

N_SCORE_BLOCKS = 20  # time blocks of the robust (sandwich) information's score sums
DETECTOR_ROUNDS = 4  # most searches, each with the standstill detector held at the last estimate
REST_KINDS = ("zupt", "zaru")  # the updates at the standstill detector's rest epochs


def update_terms(updates: pd.DataFrame) -> pd.DataFrame:
    """Each accepted update's term ``1/2 [log det(2 pi S) + nu' S^-1 nu]`` of the negative
    log-likelihood: columns ``name``, ``t`` [s], ``k`` (the update's number among its kind's
    at that time) and ``nll``, in time order within each kind."""
    parts = []
    for kind in pd.unique(updates["name"]):
        t, nu, S = innovation_arrays(updates, str(kind))
        if nu.shape[0] == 0:
            continue
        _, logdet = np.linalg.slogdet(2.0 * np.pi * S)
        nis = np.einsum("ni,ni->n", nu, np.linalg.solve(S, nu[..., None])[..., 0])
        part = pd.DataFrame({"name": str(kind), "t": t, "nll": 0.5 * (logdet + nis)})
        part.insert(2, "k", part.groupby("t").cumcount())
        parts.append(part)
    if not parts:
        return pd.DataFrame({"name": [], "t": [], "k": [], "nll": []})
    return pd.concat(parts, ignore_index=True)


def negative_log_likelihood(updates: pd.DataFrame) -> float:
    """``1/2 sum [log det(2 pi S) + nu' S^-1 nu]`` over the accepted updates with an
    innovation (the ``updates`` table of :class:`polins.fusion.FusionResult`)."""
    return float(update_terms(updates)["nll"].sum())


def score_information(
    plus: Sequence[pd.DataFrame],
    minus: Sequence[pd.DataFrame],
    step: float,
    n_blocks: int = N_SCORE_BLOCKS,
) -> FloatArray:
    """The variance ``J`` of the log-likelihood's score from its time-block sums.

    ``plus[i]`` / ``minus[i]`` are the :func:`update_terms` of runs at ``theta +- step e_i``
    (log space); each update's score is their central difference. Scores of updates close
    in time are correlated (the NHC and zero-velocity innovations follow the slowly varying
    velocity error), so ``J`` is the covariance of the scores summed over ``n_blocks``
    equal time blocks, times the number of blocks (batch means). Under the filter's model
    ``J`` equals the Fisher information; the sandwich ``H^-1 J H^-1`` stays honest when the
    model is wrong (docs/tuning.md, "Identifiable").
    """
    keys = ["name", "t", "k"]
    base = plus[0][keys]
    cols = []
    for p, m in zip(plus, minus, strict=True):
        both = base.merge(p, on=keys, how="left").merge(m, on=keys, how="left",
                                                        suffixes=("_p", "_m"))  # fmt: skip
        cols.append(((both["nll_p"] - both["nll_m"]) / (2.0 * step)).to_numpy(dtype=float))
    scores = np.nan_to_num(np.stack(cols, axis=-1))  # an update missing in one run: no score
    t = base["t"].to_numpy(dtype=float)
    edges = np.linspace(t.min(), t.max(), n_blocks + 1)[1:-1]
    block = np.searchsorted(edges, t)
    sums = np.zeros((n_blocks, scores.shape[1]))
    np.add.at(sums, block, scores)
    return n_blocks * np.atleast_2d(np.cov(sums, rowvar=False))


def sandwich_sigma(H: FloatArray, J: FloatArray) -> FloatArray:
    """``sqrt(diag(H^-1 J H^-1))``: the robust sigma of a maximum-likelihood estimate
    under a possibly wrong model (Huber); inf along a direction without information."""
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    tiny = 1e-9 * max(float(np.max(np.abs(w))), 1e-300)
    if np.any(w <= tiny):
        return _fisher_sigma(H)
    Hinv = (V / w) @ V.T
    return np.sqrt(np.clip(np.diag(Hinv @ J @ Hinv), 0.0, None))


def _fisher_sigma(H: FloatArray) -> FloatArray:
    """Cramér-Rao sigmas ``sqrt(diag(H^-1))`` of a symmetric information matrix; a
    direction without information (eigenvalue <= 0) gives inf to the parameters in it."""
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    tiny = 1e-9 * max(float(np.max(np.abs(w))), 1e-300)
    var = np.where(w > tiny, 1.0 / np.where(w > tiny, w, 1.0), np.inf)
    weights = V**2
    with np.errstate(invalid="ignore"):
        out = np.where(weights > 1e-6, weights * var, 0.0).sum(axis=1)
    return np.sqrt(out)


def central_hessian(f: Callable[[FloatArray], float], x: FloatArray, step: float) -> FloatArray:
    """Hessian of ``f`` at ``x`` by second-order central differences with ``step``.

    ``1 + 2n + n(n-1)`` evaluations of ``f`` for ``n`` parameters, among them ``f(x +- step
    e_i)`` that :func:`score_information` reuses; each evaluation is a filter run, and
    ``scipy.differentiate.hessian`` nests two derivatives (``9 n^2`` evaluations: 81
    instead of 13 runs for 3 parameters).
    """
    eye = np.eye(x.size) * step
    f0 = f(x)
    fp = [f(x + e) for e in eye]
    fm = [f(x - e) for e in eye]
    H = np.empty((x.size, x.size))
    for i in range(x.size):
        H[i, i] = (fp[i] - 2.0 * f0 + fm[i]) / step**2
        for j in range(i):
            fpp, fmm = f(x + eye[i] + eye[j]), f(x - eye[i] - eye[j])
            mixed = fpp - fp[i] - fp[j] + 2.0 * f0 - fm[i] - fm[j] + fmm
            H[i, j] = H[j, i] = mixed / (2.0 * step**2)
    return H


def _robust_sigma(
    terms: Callable[[FloatArray], pd.DataFrame],
    theta: FloatArray,
    H: FloatArray,
    cr_sigma: FloatArray,
    step: float = 0.05,
) -> FloatArray:
    """The larger of the Cramér-Rao and the sandwich sigma at ``theta`` (log space), the
    scores from central differences of each update's term (:func:`score_information`)."""
    if not np.all(np.isfinite(cr_sigma)):
        return cr_sigma
    eye = np.eye(theta.size) * step
    plus = [terms(theta + e) for e in eye]
    minus = [terms(theta - e) for e in eye]
    J = score_information(plus, minus, step)
    return np.maximum(cr_sigma, sandwich_sigma(H, J))


def tune(
    imu: pd.DataFrame,
    measurements: pd.DataFrame,
    config: FuseConfig | None = None,
    params: Sequence[str] = ("gyro_arw", "yaw_floor_deg"),
    *,
    initial: Mapping[str, float] | None = None,
    rot_nb0: Any = None,
    odometry: pd.DataFrame | None = None,
    max_log_sigma: float = math.log(2.0),
    search_factor: float = 100.0,
    hessian_step: float = 0.2,
    prob: float = 0.95,
) -> TuneResult:
    """Tune noise parameters by maximum likelihood of the filter's innovations.

    Parameters
    ----------
    imu, measurements : DataFrame
        The IMU log and measurements table of :func:`polins.fusion.run_fusion`.
    config : FuseConfig, optional
        The filter configuration (its IMU model gives the IMU parameters' start values).
    params : sequence of str
        Names of :data:`PARAMETERS` to tune.
    initial : mapping, optional
        Start values by name (units of :data:`PARAMETERS`); default the model's, and
        0.05 deg for a floor.
    rot_nb0 : Rotation, optional
        Initial attitude (None: self-alignment), as in ``run_fusion``.
    odometry : DataFrame, optional
        The log's odometer (``t, speed``), as in ``run_fusion``: the tuned filter must be
        the one that fuses, with every aiding the log has; without it the IMU noise absorbs
        the velocity errors the odometer would have removed.
    max_log_sigma : float
        Largest robust sigma of ``log(parameter)`` of an identifiable parameter (the larger
        of the Cramér-Rao and the sandwich sigma, :func:`sandwich_sigma`).
    search_factor : float
        The search stays within start ``/ search_factor .. * search_factor``.
    hessian_step : float
        Step of the numerical Hessian in log space.
    prob : float
        Probability of the NIS and whiteness bands (:func:`innovation_stats`).

    Returns
    -------
    TuneResult
    """
    params = check_params(params)
    cfg = config or FuseConfig()
    start = start_values(cfg.resolve(odometry=odometry is not None), params, initial or {})
    lik = _Likelihood(imu, measurements, cfg, rot_nb0, odometry, start)

    def nll(theta: FloatArray, names: tuple[str, ...], fixed: Mapping[str, float]) -> float:
        return lik.nll({**fixed, **dict(zip(names, np.exp(theta).tolist(), strict=True))})

    def search(names: tuple[str, ...], fixed: Mapping[str, float], x0: FloatArray) -> FloatArray:
        half = math.log(search_factor)
        bounds = [(t - half, t + half) for t in np.log([start[p] for p in names])]
        # converged when a step gains less than about 0.01 nats: far below the 0.5 nats of
        # a Cramér-Rao sigma, so the estimate is as good as the log allows
        ftol = 0.01 / max(abs(nll(x0, names, fixed)), 1.0)
        res = minimize(nll, x0, args=(names, fixed), method="L-BFGS-B", bounds=bounds,
                       options={"eps": 1e-3, "ftol": ftol, "gtol": 0.05})  # fmt: skip
        return np.asarray(res.x, dtype=float)

    def fit(names: tuple[str, ...], fixed: Mapping[str, float], x0: FloatArray) -> FloatArray:
        # the search with the detector held, then held again at the estimate until the
        # estimate's rest epochs are those it was fitted with (docs/tuning.md)
        theta = x0
        for k in range(DETECTOR_ROUNDS):
            theta = search(names, fixed, theta)
            values = {**fixed, **dict(zip(names, np.exp(theta).tolist(), strict=True))}
            if k == DETECTOR_ROUNDS - 1 or not lik.hold(values):
                break
        return theta

    theta_start = np.log([start[p] for p in params])
    theta = fit(params, {}, theta_start)
    half = math.log(search_factor)
    side = np.where(theta <= theta_start - half + 1e-6, -1, 0)
    side = np.where(theta >= theta_start + half - 1e-6, 1, side)
    bound = dict(zip(params, side.tolist(), strict=True))
    estimate = dict(zip(params, np.exp(theta).tolist(), strict=True))
    # the information of the parameters inside the search, those on a bound held there
    inner = tuple(p for p in params if not bound[p])
    held = {p: estimate[p] for p in params if bound[p]}
    if held and inner:  # the search that ran into a bound refitted without it
        theta_in = fit(inner, held, np.log([estimate[p] for p in inner]))
        estimate.update(zip(inner, np.exp(theta_in).tolist(), strict=True))
    cr = dict.fromkeys(params, math.inf)
    robust = dict.fromkeys(params, math.inf)
    if inner:
        th_in = np.log([estimate[p] for p in inner])
        H = central_hessian(lambda th: nll(th, inner, held), th_in, hessian_step)
        sig = _fisher_sigma(H)
        at = lambda th: lik.terms({**held, **dict(zip(inner, np.exp(th).tolist(), strict=True))})  # noqa: E731
        cr.update(zip(inner, sig.tolist(), strict=True))
        robust.update(zip(inner, _robust_sigma(at, th_in, H, sig, hessian_step).tolist(),
                          strict=True))  # fmt: skip
    ident = {p: bool(robust[p] <= max_log_sigma) and not bound[p] for p in params}
    values = {p: estimate[p] if ident[p] or bound[p] else start[p] for p in params}
    free = tuple(p for p in params if ident[p])
    if free and any(not ident[p] and not bound[p] for p in params):  # refit, the others held
        fixed = {p: values[p] for p in params if not ident[p]}
        theta_free = fit(free, fixed, np.log([estimate[p] for p in free]))
        values.update(zip(free, np.exp(theta_free).tolist(), strict=True))
    before, after = lik.run(start, gated=True), lik.run(values, gated=True)
    return TuneResult(
        params=params,
        initial=start,
        estimate=estimate,
        values=values,
        cr_sigma_log=cr,
        robust_sigma_log=robust,
        identifiable=ident,
        at_bound=bound,
        nll_before=lik.nll(start),
        nll_after=lik.nll(values),
        stats_before=innovation_stats(before.updates, prob=prob, gate_prob=cfg.gate_probability),
        stats_after=innovation_stats(after.updates, prob=prob, gate_prob=cfg.gate_probability),
        config=with_values(cfg, measurements, values)[0],
        measurements=measurements,
        before=before,
        after=after,
        n_evaluations=lik.count,
    )


class _Likelihood:
    """The filter runs of one tuning: the log, the configuration, the standstill
    detector's held model, and a memory of the ungated runs' likelihood terms by parameter
    values (the search revisits points).

    The ungated runs hold the standstill detector's model (``FuseConfig.standstill_model``,
    :meth:`hold`): the detector's test follows the IMU noise, and with it free the rest
    epochs, and the zero-velocity and zero-rate updates at them, would change from one
    candidate to the next, making the likelihood jump (docs/tuning.md). The zero-rate sigma
    still follows each candidate's ARW (a smooth function)."""

    def __init__(self, imu: pd.DataFrame, measurements: pd.DataFrame, config: FuseConfig,
                 rot_nb0: Any, odometry: pd.DataFrame | None,
                 start: Mapping[str, float]) -> None:  # fmt: skip
        self.imu, self.measurements, self.config = imu, measurements, config
        self.rot_nb0, self.odometry = rot_nb0, odometry
        self.count = 0
        self._terms: dict[tuple[tuple[str, float], ...], pd.DataFrame] = {}
        self.epochs: FloatArray | None = None
        self.ungated: FuseConfig  # the runs' configuration, set by hold()
        self.hold(start)

    def rest_epochs(self, run: FuseConfig) -> FloatArray:
        """The times [s] of the zero-velocity and zero-rate updates that the standstill
        detector gives with the configuration ``run``."""
        run = run.resolve(odometry=self.odometry is not None)
        t = self.imu["t"].to_numpy(dtype=float)
        w = self.imu[["gx", "gy", "gz"]].to_numpy(dtype=float)
        f = self.imu[["ax", "ay", "az"]].to_numpy(dtype=float)
        return np.array([it.t for it in vehicle_items(run, t, w, f) if it.kind in REST_KINDS])

    def hold(self, values: Mapping[str, float]) -> bool:
        """Hold the detector at the IMU model of ``values``; whether its rest epochs changed
        (the memory of runs is then cleared)."""
        run = with_values(self.config, self.measurements, values)[0]
        epochs = self.rest_epochs(run)
        changed = self.epochs is None or not np.array_equal(epochs, self.epochs)
        if changed:
            self.ungated = self.config.replace(gate_prob="off", smooth=False,
                                               standstill_model=run.imu)  # fmt: skip
            self.epochs = epochs
            self._terms.clear()
        return changed

    def run(self, values: Mapping[str, float], *, gated: bool = False) -> FusionResult:
        """The filter with ``values`` (gated as the configuration, or without a gate)."""
        config, meas = with_values(self.config if gated else self.ungated, self.measurements,
                                   values)  # fmt: skip
        self.count += 1
        try:
            return run_fusion(self.imu, meas, rot_nb0=self.rot_nb0, config=config,
                              odometry=self.odometry)  # fmt: skip
        except ImplausibleRunError as exc:  # a candidate far off: its likelihood says so
            return exc.result

    def terms(self, values: Mapping[str, float]) -> pd.DataFrame:
        """The ungated run's :func:`update_terms` at ``values``."""
        key = tuple(sorted((k, float(v)) for k, v in values.items()))
        if key not in self._terms:
            self._terms[key] = update_terms(self.run(values).updates)
        return self._terms[key]

    def nll(self, values: Mapping[str, float]) -> float:
        """The negative log-likelihood at ``values``."""
        return float(self.terms(values)["nll"].sum())


__all__ = [
    "DETECTOR_ROUNDS",
    "N_SCORE_BLOCKS",
    "REST_KINDS",
    "central_hessian",
    "negative_log_likelihood",
    "sandwich_sigma",
    "score_information",
    "tune",
    "update_terms",
]
