"""Joint maximum likelihood of the sun direction and the direct-sunlight coefficient epsilon.

Gauss-Newton (IRLS for the robust losses) minimises ``sum rho(r_i)`` of the AoP-orthogonal
residuals of :mod:`polins.compass.residual` over ``theta = (A_l[, Z_l], eps)``
(docs/model.md §9.2, docs/measurement.md §3, §5, §11): the step control, the covariance, the
sector jackknife and the separability of epsilon. :func:`gauss_newton` is the
component-first kernel of the per-image chain; :func:`sun_joint_ml` takes the library's
trailing-component layout.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.compass.kernels import dot
from polins.compass.losses import (
    LOSSES,
    loss_objective,
    loss_weights,
    robust_variance_factor,
)
from polins.compass.normal import (
    normal_equations,
    pass_ready,
    sector_normal_equations,
    sums_normal_equations,
    sums_sector_normal_equations,
)
from polins.compass.prediction import PixelData
from polins.compass.residual import ml_evaluate, ml_pass_sums, stokes_pixel_data, sun_derivatives
from polins.compass.sectors import SectorRuns, ml_jackknife
from polins.compass.selection import Selection
from polins.compass.skymodel import SkyModel
from polins.frames import wrap_angle

FloatArray = NDArray[np.float64]

__all__ = [
    "LOSSES",
    "MLSolution",
    "epsilon_correlation",
    "gauss_newton",
    "sun_covariance",
    "sun_joint_ml",
]

_SUN_STEP_MAX = 0.3  # largest Gauss-Newton step of a sun angle [rad] (docs/measurement.md §11)
_HALVINGS_MAX = 6  # step halvings of the line search before giving up


def _bounded_step(step: NDArray, k_sun: int) -> NDArray:
    """The Gauss-Newton step with its sun angles scaled down to at most
    :data:`_SUN_STEP_MAX` (the direction is kept)."""
    largest = max(abs(float(a)) for a in step[:k_sun])
    return step * (_SUN_STEP_MAX / largest) if largest > _SUN_STEP_MAX else step


def epsilon_correlation(covariance: ArrayLike) -> float:
    """How far epsilon (the last parameter) is from separable from the sun parameters: the
    multiple correlation ``R = sqrt(1 - 1/(C_ee F_ee))`` of epsilon with the others, with
    ``F = C^-1`` the Fisher information (docs/measurement.md §11). With one sun parameter it
    is ``|corr(A, eps)|``; with the zenith free it is dominated by ``corr(Z, eps)``. 1 (not
    separable) for a singular or non-finite covariance."""
    cov = np.asarray(covariance, dtype=float)
    if not np.all(np.isfinite(cov)) or cov[-1, -1] <= 0:
        return 1.0
    if cov.shape == (2, 2):  # |corr(A, eps)| without a matrix inverse
        product = float(cov[0, 0] * cov[1, 1])
        return min(abs(float(cov[0, 1])) / np.sqrt(product), 1.0) if product > 0 else 1.0
    try:
        info = np.linalg.inv(cov)
    except np.linalg.LinAlgError:
        return 1.0
    vif = float(cov[-1, -1] * info[-1, -1])  # variance inflation factor, >= 1
    if not vif > 0:
        return 1.0
    return float(np.sqrt(max(0.0, 1.0 - 1.0 / vif)))


@dataclass(frozen=True)
class MLSolution:
    """Joint ML estimate of docs/model.md §9.2.

    Attributes
    ----------
    theta : (k,)
        (A_l[, Z_l], eps); A_l counter-clockwise from x_l [rad].
    covariance : (k, k)
        ``sigma_hat^2 (J^T J)^-1`` (robust sandwich for Huber/Cauchy).
    sun_l : (3,)
        Level-frame unit sun vector.
    residual_rms : float
        RMS of the normalised residuals (about 1 when the noise model holds).
    iterations : int
    converged : bool
    n : int
        Pixels used.
    jackknife : (G, k) or None
        Leave-one-sector-out deviations of theta (:func:`polins.compass.sectors.ml_jackknife`)
        when sectors were given.
    sector_share : (G,) or None
        Each group's share of the azimuth information ``H_g[0, 0] / H[0, 0]``.
    sector_h : (G, k, k) or None
        The groups' parts ``H_g`` of the normal matrix (unscaled).
    sun_parameters : int
        1 (the azimuth) or 2 (azimuth and zenith): the leading entries of ``theta``.
    """

    theta: FloatArray
    covariance: FloatArray
    sun_l: FloatArray
    residual_rms: float
    iterations: int
    converged: bool
    n: int = 0
    jackknife: FloatArray | None = None
    sector_share: FloatArray | None = None
    sector_h: FloatArray | None = None
    sun_parameters: int = 1


def gauss_newton(
    data: PixelData,
    theta0: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    *,
    loss: str,
    max_iterations: int,
    tol: float = 1e-9,
    tol_sigma: float = 1e-2,
    select: Selection | None = None,
    epsilon_bound: float = np.inf,
    sectors: SectorRuns | None = None,
    sector_h: FloatArray | None = None,
    sky: SkyModel | None = None,
    stop_correlation: float = 1.0,
) -> tuple[MLSolution, NDArray | None]:
    """Gauss-Newton (IRLS for robust losses) on ``data``; with ``max_iterations=1`` it is the
    single full-set step of the subsample-then-full scheme (docs/measurement.md). ``select``
    makes the pixel selection at the first evaluation (then fixed); returns it as the mask.

    Safeguards for any start (docs/measurement.md §11): sun-angle steps are at most
    :data:`_SUN_STEP_MAX`, epsilon is kept in ``[-epsilon_bound, epsilon_bound]`` (a
    solution on the bound is not a free estimate: the caller refuses it), and a step that
    increases the loss is halved (from the second iteration on: one evaluation per
    iteration as long as the loss decreases).

    With ``sectors`` (the runs of ``data``'s pixel set) the solution carries the
    leave-one-group-out deviations of the last accepted linearization
    (docs/measurement.md §12). ``sector_h`` (e.g. a subsample solution's) replaces the
    groups' normal matrices, scaled to this solution's ``J^T J``: only ``b_g`` is summed.

    A linearization whose :func:`epsilon_correlation` exceeds ``stop_correlation`` ends the
    iteration there (not converged, no jackknife): the solution is not separable, and the
    iterations of an ill-conditioned problem would not change that (docs/measurement.md §11).
    """
    theta = np.asarray(theta0, dtype=float).copy()
    theta[-1] = min(max(theta[-1], -epsilon_bound), epsilon_bound)
    converged, it = False, 0
    k_sun = 1 if zenith is not None else 2
    r = np.zeros(0)
    jtj = np.eye(theta.size)
    jtr = np.zeros(theta.size)
    scale, rss, n = 1.0, 0.0, data.n
    data, r_scale, post_scale = _common_scale(data, loss)
    mask = data.mask
    theta_prev, step, loss_prev, halvings = theta, np.zeros_like(theta), np.inf, 0
    # The linear loss in one compiled pass (sums per jackknife group; no rows are stored).
    fused = loss == "linear" and not (sky is not None and sky.fit_delta)
    fused = fused and pass_ready(data, select, theta.size)
    accepted: tuple[NDArray, NDArray | None, NDArray | None, NDArray] | None = None
    for it in range(1, max_iterations + 1):  # noqa: B007
        if fused:
            group_sums, mask = ml_pass_sums(data, theta, zenith, mat_cl, select, sky, sectors)
            jtj, jtr, rss = sums_normal_equations(group_sums, theta.size)
            objective = rss
        else:
            r, jac, mask = _scaled_rows(data, theta, zenith, mat_cl, select, sky, r_scale)
            objective = loss_objective(r, loss, scale) if np.isfinite(loss_prev) else np.inf
        if select is not None:
            data = dataclasses.replace(data, mask=mask)
            select = None
            n = data.n
        if (
            np.isfinite(loss_prev)
            and halvings < _HALVINGS_MAX
            and objective * post_scale**2 > loss_prev * (1.0 + 1e-6)
        ):
            theta, step = _halved(theta_prev, step, epsilon_bound)
            halvings += 1
            continue
        if fused:
            accepted = (group_sums, None, None, theta)  # the linearization of jtj, jtr
            loss_prev = rss * post_scale**2
        else:
            jtj, jtr, rss, weights, scale = _irls_normal_equations(r, jac, loss, n)
            accepted = (r, jac, weights, theta)
            loss_prev = loss_objective(r, loss, scale) * post_scale**2
        jtj, jtr, rss = jtj * post_scale**2, jtr * post_scale**2, rss * post_scale**2
        try:
            step = _bounded_step(-np.linalg.solve(jtj, jtr), k_sun)
            jtj_inv = np.linalg.inv(jtj)
        except np.linalg.LinAlgError:
            break
        if stop_correlation < 1.0 and epsilon_correlation(jtj_inv) > stop_correlation:
            sectors = None  # not separable: no jackknife
            break
        theta_prev, halvings = theta, 0
        theta = theta + step
        if not -epsilon_bound <= theta[-1] <= epsilon_bound:
            theta[-1] = min(max(theta[-1], -epsilon_bound), epsilon_bound)
            step = theta - theta_prev
        if _step_converged(step, rss, n, jtj_inv, k_sun, tol, tol_sigma):
            converged = True
            break
    cov, rms = _covariance(loss, r, scale, n, theta.size, rss, jtj, jtr)
    sun_l, _ = sun_derivatives(theta, zenith)
    theta[0] = float(wrap_angle(theta[0]))
    jackknife = share = sector_h_out = None
    if sectors is not None and accepted is not None:
        jackknife, share, sector_h_out = _sector_jackknife(
            accepted, sectors, sector_h, zenith, mat_cl, jtj, jtr, post_scale
        )
    return MLSolution(theta, np.asarray(cov, dtype=np.float64), sun_l, rms, it, converged, n,
                      jackknife, share, sector_h_out, k_sun), mask  # fmt: skip


def _halved(theta_prev: NDArray, step: NDArray, epsilon_bound: float) -> tuple[NDArray, NDArray]:
    """The line search's half step back towards the previous point: ``theta`` (epsilon
    kept in its bound) and the halved step."""
    step *= 0.5
    theta = theta_prev + step
    theta[-1] = min(max(theta[-1], -epsilon_bound), epsilon_bound)
    return theta, step


def _scaled_rows(
    data: PixelData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    select: Selection | None,
    sky: SkyModel | None,
    r_scale: float,
) -> tuple[NDArray, NDArray, NDArray | None]:
    """:func:`ml_evaluate`'s residuals and Jacobian times a common ``1/sigma_L``
    ``r_scale`` (for the robust weights), and the mask in force."""
    r, jac_opt, _, mask = ml_evaluate(data, theta, zenith, mat_cl, True, select, sky)
    assert jac_opt is not None
    jac = jac_opt
    if r_scale != 1.0:
        r = r * r.dtype.type(r_scale)
        jac = jac * jac.dtype.type(r_scale)
    return r, jac, mask


def _irls_normal_equations(
    r: NDArray, jac: NDArray, loss: str, n: int
) -> tuple[NDArray, NDArray, float, NDArray | None, float]:
    """``J^T W J``, ``J^T W r``, ``r^T W r`` with the loss's IRLS weights, the weights and
    the loss's scale."""
    weights, scale = loss_weights(r, loss, n)
    jtj, jtr, rss = normal_equations(r, jac, weights)
    return jtj, jtr, rss, weights, scale


def _common_scale(data: PixelData, loss: str) -> tuple[PixelData, float, float]:
    """``data``, the residuals' common ``1/sigma_L`` and the normal equations' scale: with the
    linear loss a common ``1/sigma_L`` scales the normal equations instead of every residual."""
    r_scale = 1.0 if isinstance(data.inv_sigma, np.ndarray) else float(data.inv_sigma)
    if loss == "linear" and r_scale != 1.0:
        return dataclasses.replace(data, inv_sigma=1.0), 1.0, r_scale
    return data, r_scale, 1.0


def _step_converged(
    step: NDArray,
    rss: float,
    n: int,
    jtj_inv: NDArray,
    k_sun: int,
    tol: float,
    tol_sigma: float,
) -> bool:
    """Converged when the sun step is below ``tol`` [rad], or negligible (``tol_sigma``
    sigma) against the statistical uncertainty (e.g. the float32 floor of noise-free data);
    the nuisance parameters (neutral_sep^2, delta_perp) to one sigma."""
    sigma = np.sqrt(rss / max(n - step.size, 1) * np.abs(np.diag(jtj_inv)[:-1]))
    sigma[:k_sun] *= tol_sigma
    return bool(np.all(np.abs(step[:-1]) <= np.maximum(tol, sigma)))


def _covariance(
    loss: str,
    r: NDArray,
    scale: float,
    n: int,
    dof: int,
    rss: float,
    jtj: NDArray,
    jtr: NDArray,
) -> tuple[NDArray, float]:
    """The covariance ``(dof, dof)`` of the estimate and the RMS normalised residual: for the
    linear loss from the residual sum of squares after the last step (to second order), else
    Huber's sandwich factor (NaN covariance when ``J^T J`` is singular)."""
    if loss == "linear":
        try:
            rss_after = max(rss - float(jtr @ np.linalg.solve(jtj, jtr)), 0.0)
        except np.linalg.LinAlgError:
            rss_after = rss
        var = rss_after / max(n - dof, 1)
        rms = float(np.sqrt(rss_after / max(n, 1)))
    else:
        var = robust_variance_factor(r, loss, scale, n, dof)
        rms = float(np.sqrt(dot(r, r) / max(n, 1)))
    try:
        cov = var * np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        cov = np.full((dof, dof), np.nan)
    return cov, rms


def _sector_jackknife(
    accepted: tuple[NDArray, NDArray | None, NDArray | None, NDArray],
    sectors: SectorRuns,
    sector_h: FloatArray | None,
    zenith: float | None,
    mat_cl: NDArray,
    jtj: NDArray,
    jtr: NDArray,
    post_scale: float,
) -> tuple[FloatArray | None, FloatArray | None, FloatArray | None]:
    """The leave-one-group-out deviations of the last accepted linearization ``accepted``
    (residuals or the compiled pass's group sums, Jacobian, weights, theta), the groups'
    shares of the azimuth information and their normal matrices (docs/measurement.md §12)."""
    r_a, jac_a, weights_a, theta_a = accepted  # r_a: the pass's group sums when fused
    dof = theta_a.size
    sun_c = mat_cl @ sun_derivatives(theta_a, zenith)[0]
    if jac_a is None:
        sector_parts = sums_sector_normal_equations(r_a, dof, sector_h)
    else:
        sector_parts = sector_normal_equations(r_a, jac_a, weights_a, sectors, sun_c, sector_h)
    if sector_parts is None:
        return None, None, None
    group_h, sector_b = sector_parts
    share = group_h[:, 0, 0] / max(float(np.sum(group_h[:, 0, 0])), 1e-300)
    if sector_h is not None:  # another pixel set's: scale to this J^T J
        group_h = group_h * (np.trace(jtj) / max(float(np.trace(group_h.sum(0))), 1e-300))
    else:
        group_h = group_h * post_scale**2
    try:
        jackknife = ml_jackknife(jtj, jtr, group_h, sector_b * post_scale**2)
    except np.linalg.LinAlgError:
        jackknife = None
    return jackknife, share, sector_parts[0]


def sun_covariance(solution: MLSolution) -> FloatArray:
    """Level-frame covariance ``(3, 3)`` of the unit sun of a joint ML solution:
    ``J C_sun J^T`` with ``J`` the derivatives of the sun by ``A_l`` (and ``Z_l`` when the
    zenith was estimated, ``sun_parameters`` 2)."""
    s = solution.sun_l
    cols = [np.array([-s[1], s[0], 0.0])]  # d sun / d A_l
    if solution.sun_parameters == 2:
        a, z = solution.theta[0], solution.theta[1]
        cols.append(np.array([np.cos(z) * np.cos(a), np.cos(z) * np.sin(a), -np.sin(z)]))
    jac = np.column_stack(cols)
    k = jac.shape[1]
    return jac @ solution.covariance[:k, :k] @ jac.T


def sun_joint_ml(
    stokes: ArrayLike,
    forward: ArrayLike,
    mat_cl: ArrayLike,
    sun_l0: ArrayLike,
    *,
    epsilon0: float = 0.0,
    sigma_l: ArrayLike | float = 1.0,
    zenith: float | None = None,
    loss: str = "linear",
    max_iterations: int = 10,
    epsilon_bound: float = 0.1,
) -> MLSolution:
    """Joint maximum-likelihood sun vector and direct-sunlight coefficient (docs/model.md §9.2).

    Minimises ``sum_i rho(r_i)`` over theta = (A_l, Z_l, eps), or (A_l, eps) with the zenith
    fixed to ``zenith`` (the ephemeris' apparent zenith: the fixed-zenith variant), by
    Gauss-Newton from ``sun_l0`` (e.g. the eigen solution) or from the best point of a 15 deg
    grid of suns (epsilon 0), whichever fits better: it converges from any start.

    Parameters
    ----------
    stokes : (n, 3) measured Stokes [DN]. forward : (n, 2, 3) :func:`lens_forward` rows.
    mat_cl : (3, 3) level -> camera rotation matrix.
    sun_l0 : (3,) starting level-frame sun. epsilon0 : starting epsilon.
    sigma_l : per-pixel or common sigma_L [DN] (only relative values matter for the estimate;
        the covariance is rescaled by the residual variance).
    zenith : fixed sun zenith [rad] or None (estimated).
    loss : {"linear", "huber", "cauchy"}
    epsilon_bound : largest ``|epsilon|`` (the physical range is about 0 to 0.05); a
        solution on it is not a free estimate.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss={loss!r}: expected one of {LOSSES}")
    s = np.asarray(stokes, dtype=float)
    if s.ndim != 2 or s.shape[1] != 3:
        raise ValueError(f"stokes must have shape (n, 3), got {s.shape}")
    sl = np.asarray(sun_l0, dtype=float)
    sl = sl / np.linalg.norm(sl)
    a0 = np.arctan2(sl[1], sl[0])
    theta0 = [a0, epsilon0] if zenith is not None else [a0, np.arccos(sl[2]), epsilon0]
    data = stokes_pixel_data(s, forward, sigma_l)
    mat = np.asarray(mat_cl, dtype=float)
    sub = stokes_pixel_data(s[:: max(1, len(s) // 4000)],
                         np.asarray(forward)[:: max(1, len(s) // 4000)],
                         sigma_l if np.ndim(sigma_l) == 0
                         else np.asarray(sigma_l)[:: max(1, len(s) // 4000)])  # fmt: skip
    theta_start = _grid_start(sub, np.asarray(theta0, dtype=float), zenith, mat)
    solution, _ = gauss_newton(
        data,
        theta_start,
        zenith,
        mat,
        loss=loss,
        max_iterations=max_iterations,
        epsilon_bound=epsilon_bound,
    )
    return solution


_GRID_AZIMUTHS = 24  # 15 deg steps
_GRID_ZENITHS = np.radians([10.0, 25.0, 40.0, 55.0, 70.0, 85.0])


def _grid_start(data: PixelData, theta0: NDArray, zenith: float | None, mat_cl: NDArray) -> NDArray:
    """The start of the joint ML from anywhere (docs/measurement.md §11): ``theta0`` or the
    best point of a 15 deg azimuth x 15 deg zenith grid (epsilon 0) by the sum of squared
    residuals on ``data``, whichever fits better."""

    def rss(theta: NDArray) -> float:
        r, _, _, _ = ml_evaluate(data, theta, zenith, mat_cl, False)
        return float(np.dot(r, r))

    best, best_rss = theta0, rss(theta0)
    azimuths = np.arange(_GRID_AZIMUTHS) * (2 * np.pi / _GRID_AZIMUTHS) - np.pi
    zeniths = [None] if zenith is not None else _GRID_ZENITHS
    for a in azimuths:
        for z in zeniths:
            theta = np.array([a, 0.0]) if z is None else np.array([a, z, 0.0])
            value = rss(theta)
            if value < best_rss:
                best, best_rss = theta, value
    return best
