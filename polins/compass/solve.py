"""The compensated solve of one image: joint ML on a subsample, cloud cells, full-set step.

The solve stage of :mod:`polins.compass.chain` (docs/measurement.md §5, §12):

1. Gauss-Newton of the joint ML with the sky model of the options (Rayleigh or Berry with
   its neutral-point separation, the camera-fixed ``delta_perp``;
   :mod:`polins.compass.skymodel`) on the pixel subsample;
2. with ``clouds="auto"``: sky cells whose mean AoP residual is significant (a thin
   cloud turns the E-vector, :func:`polins.compass.clouds.rotated_cells`) and those whose
   DoP falls short of the fitted sky's (:func:`polins.compass.clouds.fitted_sky_depolarized`)
   are dropped and the subsample is solved again, up to :data:`CLOUD_ROUNDS` times;
3. one Gauss-Newton step on all valid pixels, the neutral-point separation kept at the
   subsample's value (the Berry prediction is one compiled pass over the pixels).
   Without a subsample (``stride == 1``) the full set is solved directly, to a tenth of a
   sigma (the epsilon column of the Jacobian is approximate to ~2 %, so the iteration can
   circle the optimum by a few hundredths of a sigma).

A solution that cannot be trusted (:func:`ml_problem`) is returned with the reason, and the
chain falls back to the eigen solution (docs/measurement.md §11).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from polins.compass.clouds import (
    CLOUD_AOP_MIN,
    CLOUD_AOP_Z,
    CLOUD_CELLS,
    DopTest,
    fitted_sky_depolarized,
    rotated_cells,
)
from polins.compass.jointml import MLSolution, epsilon_correlation, gauss_newton
from polins.compass.measurement import MeasureOptions
from polins.compass.prediction import PixelData
from polins.compass.sectors import SectorRuns
from polins.compass.selection import Selection
from polins.compass.skymodel import SkyModel, sky_model

__all__ = [
    "CLOUD_ROUNDS",
    "EPSILON_MAX",
    "MAX_ITERATIONS",
    "NEUTRAL_SEP",
    "SEPARABILITY_MAX",
    "SEPARABILITY_STOP",
    "SEP_MIN",
    "SEP_Z_MIN",
    "CompensatedSolution",
    "SolveSetup",
    "compensated_solution",
    "ml_problem",
]

CLOUD_ROUNDS = 3
"""Largest number of cloud passes (each drops cells and solves again)."""


SEP_MIN = float(np.radians(5.0))
"""Smallest neutral-point separation that counts [rad]: the points are then within 2.5 deg
of the sun, inside its exclusion radius (10 deg by default)."""


NEUTRAL_SEP = float(np.radians(32.0))
"""Start of the fitted separation of the Babinet and Brewster points [rad]."""

SEP_Z_MIN = 10.0
"""A fitted separation square below this many of its sigmas is not identified (its effect
grows as its square: near zero the linearised sigma is optimistic); the image is then
solved with the Rayleigh sky."""

MAX_ITERATIONS = 10
"""Gauss-Newton iterations on the subsample."""

EPSILON_MAX = 0.1
"""Largest accepted ``|epsilon|`` (physical: about 0 to 0.05); the iteration is bounded to
it and a solution on the bound falls back to the eigen solution."""

SEPARABILITY_MAX = 0.98
"""Largest accepted correlation of epsilon with the sun parameters
(:func:`polins.compass.jointml.epsilon_correlation`); above it the chain falls back to the
eigen solution (docs/measurement.md §11)."""

SEPARABILITY_STOP = 0.99
"""A fit whose linearization gives a correlation of epsilon with the sun parameters above
this stops there (its iterations would not bring it below :data:`SEPARABILITY_MAX`: over
the narrow-field and fisheye images of docs/measurement.md §11 the correlation moved by
less than 0.008 from the first linearization to the last). A stopped Rayleigh-sky fit is
a fallback; a stopped Berry-sky fit hands over to the Rayleigh fit from the same start,
and runs to its end when that one is separable (:func:`_fit_sky`)."""

SCORE_MARGIN = 0.2
"""The Berry sky is solved when the one-step separation square of the score test reaches
this fraction of the identification threshold (on realistic skies every identified
separation reached 0.52 of it, docs/measurement.md §5)."""


@dataclass(frozen=True)
class SolveSetup:
    """What every solve of one image shares.

    Attributes
    ----------
    zenith : float or None
        Fixed sun zenith [rad], or None when it is estimated.
    mat_cl : (3, 3)
        Level -> camera rotation.
    opt : MeasureOptions
    """

    zenith: float | None
    mat_cl: NDArray
    opt: MeasureOptions

    @property
    def k_sep(self) -> int:
        """Index of the neutral-point separation in ``theta`` (after the sun angles)."""
        return 1 if self.zenith is not None else 2


@dataclass(frozen=True)
class Fit:
    """One Gauss-Newton problem: the pixels, their jackknife runs, the sky and the stop."""

    data: PixelData
    sectors: SectorRuns
    sky: SkyModel | None
    iterations: int
    tol_sigma: float = 1e-2
    sector_h: NDArray | None = None
    stop_correlation: float = 1.0


@dataclass(frozen=True)
class CompensatedSolution:
    """The joint ML of one image.

    Attributes
    ----------
    ml : MLSolution
        Of the full set (``theta`` without ``neutral_sep`` when the subsample had it).
    mask, mask_sub : (n,) bool or None
        The full-set mask (None when the subsample's solution fell back) and the
        subsample's (None without a subsample).
    fallback : str
        Why the solution cannot be used ("" if it can).
    """

    ml: MLSolution
    mask: NDArray | None
    mask_sub: NDArray | None
    fallback: str


def ml_problem(ml: MLSolution, converged: bool) -> str:
    """Why a joint ML solution cannot be used ("" if it can; docs/measurement.md §11):
    epsilon not separable from the sun, not converged (when ``converged`` is asked), or
    epsilon on its bound."""
    corr = epsilon_correlation(ml.covariance)
    if corr > SEPARABILITY_MAX:
        what = "zenith" if ml.sun_parameters == 2 else "sun azimuth"
        return f"epsilon and {what} not separable (corr {corr:.4f})"
    if converged and not ml.converged:
        return "joint ML did not converge"
    eps = float(ml.theta[-1])
    if not abs(eps) < EPSILON_MAX:
        return f"epsilon {eps:.3g} at its bound {EPSILON_MAX:g} (physical: about 0 to 0.05)"
    return ""


def run_fit(
    setup: SolveSetup, fit: Fit, theta0: NDArray, select: Selection
) -> tuple[MLSolution, NDArray | None]:
    """Gauss-Newton of ``fit`` from ``theta0``, the selection made at the first evaluation."""
    opt = setup.opt
    return gauss_newton(fit.data, theta0, setup.zenith, setup.mat_cl, loss=opt.loss,
                        max_iterations=fit.iterations, tol_sigma=fit.tol_sigma, select=select,
                        epsilon_bound=EPSILON_MAX, sectors=fit.sectors, sky=fit.sky,
                        sector_h=fit.sector_h, stop_correlation=fit.stop_correlation)  # fmt: skip


def _sky(rays: NDArray, opt: MeasureOptions, berry: bool = True) -> SkyModel | None:
    return sky_model(rays, berry and opt.sky_model == "berry", NEUTRAL_SEP, True, opt.fit_delta)


def _without(ml: MLSolution, k: int) -> MLSolution:
    """The solution without its parameter ``k`` (the neutral-point separation): the
    marginal covariance and jackknife of the others."""
    cov = np.delete(np.delete(ml.covariance, k, axis=0), k, axis=1)
    jack = None if ml.jackknife is None else np.delete(ml.jackknife, k, axis=1)
    h = None if ml.sector_h is None else np.delete(np.delete(ml.sector_h, k, axis=1), k, axis=2)
    theta = np.delete(ml.theta, k)
    return dataclasses.replace(ml, theta=theta, covariance=cov, jackknife=jack, sector_h=h)


def _separation_variance(ml: MLSolution, k: int) -> float:
    """The variance of the fitted ``theta[k]`` at least the pixel noise's (the covariance
    over ``min(residual_rms^2, 1)``); NaN when the solution selected no pixels (a zero or
    non-finite residual RMS)."""
    rms = float(ml.residual_rms)
    if not (np.isfinite(rms) and rms > 0.0):
        return math.nan
    return float(ml.covariance[k, k]) / min(rms**2, 1.0)


def _separation_identified(ml: MLSolution, k: int) -> bool:
    """The fitted square of the neutral-point separation ``theta[k]`` is significant (above
    :data:`SEP_Z_MIN` of its sigma, the sigma at least the pixel noise's) and the separation in
    range (:data:`SEP_MIN` to 90 deg)."""
    tau = float(ml.theta[k])
    var = _separation_variance(ml, k)
    ok = SEP_MIN**2 < tau < (np.pi / 2) ** 2 and np.isfinite(var)
    return ok and tau > SEP_Z_MIN * np.sqrt(var)


def _separation_possible(
    setup: SolveSetup, data: PixelData, theta: NDArray, select: Selection, sky: SkyModel
) -> bool:
    """The score test of the neutral-point separation at zero: one Gauss-Newton step of
    the Berry sky from the start ``theta`` with ``sep^2 = 0`` (the gradient of the
    log-likelihood in ``sep^2`` against its Fisher information, jointly with the other
    parameters) may reach an identified separation (:func:`_separation_identified`, with
    the margin :data:`SCORE_MARGIN`); else only the Rayleigh sky is solved
    (docs/measurement.md §5)."""
    k, opt = setup.k_sep, setup.opt
    start = np.array(theta, dtype=float)
    start[k] = 0.0
    step, _ = gauss_newton(data, start, setup.zenith, setup.mat_cl, loss=opt.loss,
                           max_iterations=1, epsilon_bound=EPSILON_MAX, select=select,
                           sky=sky)  # fmt: skip
    tau = float(step.theta[k])
    var = _separation_variance(step, k)
    if not np.isfinite(tau) or not np.isfinite(var):
        return True
    return tau > SCORE_MARGIN * max(SEP_MIN**2, SEP_Z_MIN * np.sqrt(var))


def _drop_clouds(
    setup: SolveSetup,
    fit: Fit,
    ml: MLSolution,
    mask: NDArray | None,
    select: Selection,
    cells: NDArray,
    dop_test: Callable[[], DopTest] | None,
) -> tuple[MLSolution, NDArray | None, NDArray]:
    """Cloud passes on one pixel set (rotated and, with ``dop_test``, depolarized cells):
    the solution, its mask and the dropped cells ``(CLOUD_CELLS**2,)`` bool."""
    opt, zenith, sky = setup.opt, setup.zenith, fit.sky
    dropped = np.zeros(CLOUD_CELLS * CLOUD_CELLS, dtype=bool)
    if opt.clouds == "off":
        return ml, mask, dropped
    for _ in range(CLOUD_ROUNDS):
        if ml_problem(ml, True):
            break
        flagged = rotated_cells(dataclasses.replace(fit.data, mask=mask), ml.theta, zenith,
                                setup.mat_cl, sky, cells, CLOUD_AOP_Z, CLOUD_AOP_MIN)  # fmt: skip
        if dop_test is not None and sky is not None and sky.berry:  # its DoP shape fits
            sep = (
                np.sqrt(max(float(ml.theta[setup.k_sep]), 0.0)) if sky.fit_sep else sky.neutral_sep
            )
            zenith_sun = float(ml.theta[1]) if zenith is None else zenith
            flagged = flagged | fitted_sky_depolarized(dop_test(), float(ml.theta[0]), zenith_sun,
                                                       float(sep))  # fmt: skip
        flagged &= ~dropped
        if not flagged.any():
            break
        dropped |= flagged
        select = dataclasses.replace(select, valid=select.valid & ~flagged.take(cells))
        ml, mask = run_fit(setup, fit, ml.theta, select)
    return ml, mask, dropped


def _stopped(ml: MLSolution) -> bool:
    """The Gauss-Newton stopped at :data:`SEPARABILITY_STOP` (not separable)."""
    return not ml.converged and epsilon_correlation(ml.covariance) > SEPARABILITY_STOP


def _fit_sky(
    setup: SolveSetup,
    data: PixelData,
    sectors: SectorRuns,
    rays: NDArray,
    select: Selection,
    theta: NDArray,
) -> tuple[MLSolution, NDArray | None, Fit]:
    """The iterated solve in the sky model, in the Rayleigh sky when the fitted
    neutral-point separation is not identified (sep 0: no neutral points seen), and only in
    the Rayleigh sky when the score test at sep 0 finds nothing to fit. A Berry-sky fit not
    separable at its start (:data:`SEPARABILITY_STOP`) is followed by the Rayleigh fit from
    the same start: when that is not separable either, it is the answer (a fallback);
    otherwise the Berry fit runs to its end as usual."""
    opt, k_sep = setup.opt, setup.k_sep
    sky = _sky(rays, opt)
    berry = sky is not None and sky.fit_sep
    rayleigh = Fit(data, sectors, _sky(rays, opt, berry=False), MAX_ITERATIONS, tol_sigma=0.1,
                   stop_correlation=SEPARABILITY_STOP)  # fmt: skip
    if sky is None or not berry or _separation_possible(setup, data, theta, select, sky):
        fit = Fit(data, sectors, sky, MAX_ITERATIONS, tol_sigma=0.1,
                  stop_correlation=SEPARABILITY_STOP)  # fmt: skip
        ml, mask = run_fit(setup, fit, theta, select)
        if berry and _stopped(ml):  # the Berry sky not separable at the start: the Rayleigh?
            quick, quick_mask = run_fit(setup, rayleigh, np.delete(theta, k_sep), select)
            if _stopped(quick):
                return quick, quick_mask, rayleigh
            ml, mask = run_fit(setup, dataclasses.replace(fit, stop_correlation=1.0), theta,
                               select)  # fmt: skip
        if not berry or _separation_identified(ml, k_sep):
            return ml, mask, fit
        theta = ml.theta
    fit = rayleigh
    ml, mask = run_fit(setup, fit, np.delete(theta, setup.k_sep), select)
    return ml, mask, fit


def _full_step(
    setup: SolveSetup,
    ml: MLSolution,
    sky_sub: SkyModel | None,
    data_full: PixelData,
    sectors_full: SectorRuns,
    rays_full: NDArray,
) -> tuple[Fit, NDArray]:
    """The one Gauss-Newton step on all pixels after the subsample's solution ``ml``: the
    problem and its start (the fitted separation kept, not estimated)."""
    opt, k_sep = setup.opt, setup.k_sep
    theta, sector_h = ml.theta, ml.sector_h
    sky_full = _sky(rays_full, opt, berry=False)
    if sky_sub is not None and sky_sub.berry:  # the full step keeps the fitted separation
        sep = NEUTRAL_SEP
        if sky_sub.fit_sep:
            sep = float(np.sqrt(ml.theta[k_sep]))
            without = _without(ml, k_sep)
            theta, sector_h = without.theta, without.sector_h
        sky_full = sky_model(rays_full, True, sep, False, opt.fit_delta)
    return Fit(data_full, sectors_full, sky_full, 1, sector_h=sector_h), theta


def compensated_solution(
    setup: SolveSetup,
    data: tuple[PixelData, PixelData],
    theta: NDArray,
    select: tuple[Selection, Selection],
    cells: tuple[NDArray, NDArray],
    sectors: tuple[SectorRuns, SectorRuns],
    rays: tuple[NDArray, NDArray],
    dop_test: Callable[[], DopTest] | None = None,
) -> CompensatedSolution:
    """The joint ML of one image (module notes).

    Parameters
    ----------
    setup : SolveSetup
    data : (PixelData, PixelData)
        The subsample (``data[0] is data[1]`` without one) and all field-of-view pixels.
    theta : (k,)
        Start ``(A_l[, Z_l][, neutral_sep][, delta_perp], eps)``.
    select : (Selection, Selection)
        The pixel selections of the subsample and of the full set (the full set's fit
        leaves out the cloud cells the subsample's fit dropped).
    cells : ((n_sub,) int, (n,) int)
        The sky cells of the subsample's and of the field-of-view pixels.
    sectors : (SectorRuns, SectorRuns)
        Jackknife runs of the subsample and of the full set.
    rays : ((3, n_sub), (3, n))
        Camera-frame unit rays of the subsample and of the full set.
    dop_test : callable, optional
        Returns the fitted sky's DoP test of the cloud passes (called when a pass needs
        it: a solution that falls back never builds it; it should return one cached
        object); None: no DoP test.
    """
    k_sep = setup.k_sep
    if data[0] is data[1]:  # no subsample: the full set solved directly
        ml, mask, fit = _fit_sky(setup, data[1], sectors[1], rays[1], select[1], theta)
        ml, mask, _ = _drop_clouds(setup, fit, ml, mask, select[1], cells[1], dop_test)
        if fit.sky is not None and fit.sky.fit_sep:
            ml = _without(ml, k_sep)
        return CompensatedSolution(ml, mask, None, ml_problem(ml, True))

    ml, mask_sub, fit = _fit_sky(setup, data[0], sectors[0], rays[0], select[0], theta)
    ml, mask_sub, dropped = _drop_clouds(setup, fit, ml, mask_sub, select[0], cells[0], dop_test)
    fallback = ml_problem(ml, True)
    if fallback:
        return CompensatedSolution(ml, None, mask_sub, fallback)
    select_full = select[1]
    if dropped.any():  # a gather over all pixels (0.4 ms at full resolution)
        valid = select_full.valid & ~dropped.take(cells[1])
        select_full = dataclasses.replace(select_full, valid=valid)
    step, theta = _full_step(setup, ml, fit.sky, data[1], sectors[1], rays[1])
    full, mask_full = run_fit(setup, step, theta, select_full)
    return CompensatedSolution(full, mask_full, mask_sub, ml_problem(full, False))
