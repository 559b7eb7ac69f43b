"""The compensated solve of one image: joint ML on a subsample, rotated-cloud cells, full-set step.

Step 3 of :mod:`polins.compass.chain` (docs/measurement.md §5, §12):

1. Gauss-Newton of the joint ML with the sky model of the options (Rayleigh or Berry with
   its neutral-point separation, the camera-fixed ``delta_perp``;
   :mod:`polins.compass.skymodel`) on the pixel subsample;
2. with ``cloud_aop_z``: sky cells whose mean AoP residual is significant (a thin cloud
   turns the E-vector, :func:`polins.compass.modelerror.rotated_cells`), and with
   ``cloud_fit_ratio`` those whose DoP falls short of the fitted sky's (the chain's
   ``depolarized``, :func:`polins.compass.modelerror.depolarized_cells`), are dropped and
   the subsample is solved again, up to :data:`CLOUD_ROUNDS` times;
3. one Gauss-Newton step on all valid pixels, the neutral-point separation kept at the
   subsample's value (the Berry prediction is one compiled pass over the pixels).
   Without a subsample (``stride == 1``) the full set is solved directly, to a tenth of a
   sigma (the epsilon column of the Jacobian is approximate to ~2 %, so the iteration can
   circle the optimum by a few hundredths of a sigma).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from polins.compass.jointml import MLSolution, gauss_newton
from polins.compass.measurement import MeasureOptions
from polins.compass.modelerror import CLOUD_CELLS, rotated_cells
from polins.compass.prediction import PixelData
from polins.compass.sectors import SectorRuns
from polins.compass.selection import Selection
from polins.compass.skymodel import SkyModel, sky_model

__all__ = ["CLOUD_ROUNDS", "SEP_MIN", "Depolarized", "compensated_solution"]

CLOUD_ROUNDS = 3
"""Largest number of rotated-cloud passes (each drops cells and solves again)."""


SEP_MIN = float(np.radians(5.0))
"""Smallest neutral-point separation that counts [rad]: the points are then within 2.5 deg
of the sun, inside its exclusion radius (10 deg by default)."""


SCORE_MARGIN = 0.2
"""The Berry sky is solved when the one-step separation square of the score test reaches
this fraction of the identification threshold (on realistic skies every identified
separation reached 0.52 of it, docs/measurement.md §5)."""


def _sky(rays: NDArray, opt: MeasureOptions, berry: bool = True) -> SkyModel | None:
    return sky_model(rays, berry and opt.sky_model == "berry", opt.neutral_sep,
                     opt.fit_sep, opt.fit_delta)  # fmt: skip


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


def _separation_identified(ml: MLSolution, k: int, opt: MeasureOptions) -> bool:
    """The fitted square of the neutral-point separation ``theta[k]`` is significant (above
    ``sep_z_min`` of its sigma, the sigma at least the pixel noise's) and the separation in
    range (:data:`SEP_MIN` to 90 deg)."""
    tau = float(ml.theta[k])
    var = _separation_variance(ml, k)
    ok = SEP_MIN**2 < tau < (np.pi / 2) ** 2 and np.isfinite(var)
    return ok and tau > opt.sep_z_min * np.sqrt(var)


def _separation_possible(
    data: PixelData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    select: Selection,
    sky: SkyModel,
    k: int,
    opt: MeasureOptions,
) -> bool:
    """The score test of the neutral-point separation at zero: one Gauss-Newton step of
    the Berry sky from the start ``theta`` with ``sep^2 = 0`` (the gradient of the
    log-likelihood in ``sep^2`` against its Fisher information, jointly with the other
    parameters) may reach an identified separation (:func:`_separation_identified`, with
    the margin :data:`SCORE_MARGIN`); else only the Rayleigh sky is solved
    (docs/measurement.md §5)."""
    start = np.array(theta, dtype=float)
    start[k] = 0.0
    step, _ = gauss_newton(data, start, zenith, mat_cl, loss=opt.loss, max_iterations=1,
                           epsilon_bound=opt.epsilon_max, select=select, sky=sky)  # fmt: skip
    tau = float(step.theta[k])
    var = _separation_variance(step, k)
    if not np.isfinite(tau) or not np.isfinite(var):
        return True
    return tau > SCORE_MARGIN * max(SEP_MIN**2, opt.sep_z_min * np.sqrt(var))


Depolarized = Callable[[float, float, float], NDArray]
"""``depolarized(azimuth, zenith, neutral_sep)`` [rad] of the fitted level-frame sun and
separation: the sky cells ``(CLOUD_CELLS**2,)`` bool whose DoP falls short of that sky's."""


def _drop_clouds(
    ml: MLSolution,
    mask: NDArray | None,
    data: PixelData,
    select: Selection,
    cells: NDArray,
    solve: Callable[[NDArray, Selection], tuple[MLSolution, NDArray | None]],
    problem: Callable[[MLSolution], str],
    zenith: float | None,
    mat_cl: NDArray,
    sky: SkyModel | None,
    opt: MeasureOptions,
    depolarized: Depolarized | None,
) -> tuple[MLSolution, NDArray | None, NDArray]:
    """Cloud passes on one pixel set (rotated and, with ``depolarized``, depolarized
    cells): the solution, its mask and the dropped cells ``(CLOUD_CELLS**2,)`` bool."""
    dropped = np.zeros(CLOUD_CELLS * CLOUD_CELLS, dtype=bool)
    if opt.cloud_aop_z is None and depolarized is None:
        return ml, mask, dropped
    k_sep = 1 if zenith is not None else 2
    for _ in range(CLOUD_ROUNDS):
        if problem(ml):
            break
        flagged = np.zeros_like(dropped)
        if opt.cloud_aop_z is not None:
            flagged = rotated_cells(dataclasses.replace(data, mask=mask), ml.theta, zenith,
                                    mat_cl, sky, cells, opt.cloud_aop_z, opt.cloud_aop_min)  # fmt: skip
        if depolarized is not None and sky is not None and sky.berry:  # its DoP shape fits
            sep = np.sqrt(max(float(ml.theta[k_sep]), 0.0)) if sky.fit_sep else sky.neutral_sep
            zenith_sun = float(ml.theta[1]) if zenith is None else zenith
            flagged = flagged | depolarized(float(ml.theta[0]), zenith_sun, float(sep))
        flagged &= ~dropped
        if not flagged.any():
            break
        dropped |= flagged
        select = dataclasses.replace(select, valid=select.valid & ~flagged.take(cells))
        ml, mask = solve(ml.theta, select)
    return ml, mask, dropped


def compensated_solution(
    data_sub: PixelData,
    data_full: PixelData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    select_sub: Selection,
    select_full: Selection,
    cells: NDArray,
    sub_index: NDArray,
    sectors: tuple[SectorRuns, SectorRuns],
    rays: tuple[NDArray, NDArray],
    problem: Callable[[MLSolution, bool], str],
    opt: MeasureOptions,
    depolarized: Depolarized | None = None,
) -> tuple[MLSolution, NDArray | None, NDArray | None, str]:
    """The joint ML of one image (module notes).

    Parameters
    ----------
    data_sub, data_full : PixelData
        The subsample (None-strided: ``data_sub is data_full``) and all field-of-view pixels.
    theta : (k,)
        Start ``(A_l[, Z_l][, neutral_sep][, delta_perp], eps)``.
    zenith : float or None
        Fixed zenith [rad] or None.
    mat_cl : (3, 3)
        Level -> camera rotation.
    select_sub, select_full : Selection
        The pixel selections (``select_full.valid`` is updated in place with the dropped
        cloud cells).
    cells : (n,) int
        The field-of-view pixels' sky cells; ``sub_index`` the subsample's pixels.
    sectors : (SectorRuns, SectorRuns)
        Jackknife runs of the subsample and of the full set.
    rays : ((3, n_sub), (3, n))
        Camera-frame unit rays of the subsample and of the full set.
    problem : callable
        ``problem(ml, converged)``: why a solution cannot be used ("" if it can).
    depolarized : callable, optional
        The DoP test of the cloud passes (:data:`Depolarized`); None: none.

    Returns
    -------
    MLSolution (of the full set, ``theta`` without ``neutral_sep`` when the subsample had
    it), the full-set mask, the subsample mask (None without a subsample), and the
    fallback reason ("" if none).
    """
    strided = data_sub is not data_full

    Solve = Callable[[NDArray, Selection], tuple[MLSolution, NDArray | None]]

    def solve(data: PixelData, sectors_x: SectorRuns, sky: SkyModel | None, iterations: int,
              tol_sigma: float = 1e-2, sector_h: NDArray | None = None) -> Solve:  # fmt: skip
        def run(theta0: NDArray, select: Selection) -> tuple[MLSolution, NDArray | None]:
            return gauss_newton(data, theta0, zenith, mat_cl, loss=opt.loss,
                                max_iterations=iterations, tol_sigma=tol_sigma, select=select,
                                epsilon_bound=opt.epsilon_max, sectors=sectors_x, sky=sky,
                                sector_h=sector_h)  # fmt: skip

        return run

    def fails(converged: bool) -> Callable[[MLSolution], str]:
        return lambda ml: problem(ml, converged)

    k_sep = 1 if zenith is not None else 2

    def fit(
        data: PixelData, sectors_x: SectorRuns, rays_x: NDArray, select: Selection
    ) -> tuple[MLSolution, NDArray | None, SkyModel | None, Solve]:
        """The iterated solve in the sky model, in the Rayleigh sky when the fitted
        neutral-point separation is not identified (sep 0: no neutral points seen), and
        only in the Rayleigh sky when the score test at sep 0 finds nothing to fit."""

        def rayleigh(start: NDArray) -> tuple[MLSolution, NDArray | None, SkyModel | None, Solve]:
            sky_r = _sky(rays_x, opt, berry=False)
            run_r = solve(data, sectors_x, sky_r, opt.max_iterations, tol_sigma=0.1)
            ml_r, mask_r = run_r(np.delete(start, k_sep), select)
            return ml_r, mask_r, sky_r, run_r

        sky = _sky(rays_x, opt)
        berry = sky is not None and sky.fit_sep
        if sky is not None and berry and not _separation_possible(
                data, theta, zenith, mat_cl, select, sky, k_sep, opt):  # fmt: skip
            return rayleigh(theta)
        run = solve(data, sectors_x, sky, opt.max_iterations, tol_sigma=0.1)
        ml, mask = run(theta, select)
        if berry and not _separation_identified(ml, k_sep, opt):
            return rayleigh(ml.theta)
        return ml, mask, sky, run

    if not strided:
        ml, mask, sky, run = fit(data_full, sectors[1], rays[1], select_full)
        ml, mask, dropped = _drop_clouds(ml, mask, data_full, select_full, cells, run,
                                         fails(True), zenith, mat_cl, sky, opt, depolarized)  # fmt: skip
        if dropped.any():
            np.logical_and(select_full.valid, ~dropped.take(cells), out=select_full.valid)
        if sky is not None and sky.fit_sep:
            ml = _without(ml, k_sep)
        return ml, mask, None, problem(ml, True)

    ml, mask_sub, sky_sub, run = fit(data_sub, sectors[0], rays[0], select_sub)
    cells_sub = cells.take(sub_index)
    ml, mask_sub, dropped = _drop_clouds(ml, mask_sub, data_sub, select_sub, cells_sub, run,
                                         fails(True), zenith, mat_cl, sky_sub, opt, depolarized)  # fmt: skip
    fallback = problem(ml, True)
    if fallback:
        return ml, None, mask_sub, fallback
    if dropped.any():  # a gather over all pixels (0.4 ms at full resolution)
        np.logical_and(select_full.valid, ~dropped.take(cells), out=select_full.valid)
    theta, sector_h = ml.theta, ml.sector_h
    sky_full = _sky(rays[1], opt, berry=False)
    if sky_sub is not None and sky_sub.berry:  # the full step keeps the fitted separation
        sep = opt.neutral_sep
        if sky_sub.fit_sep:
            sep = float(np.sqrt(ml.theta[k_sep]))
            without = _without(ml, k_sep)
            theta, sector_h = without.theta, without.sector_h
        sky_full = sky_model(rays[1], True, sep, False, opt.fit_delta)
    step = solve(data_full, sectors[1], sky_full, 1, sector_h=sector_h)
    full, mask_full = step(theta, select_full)
    return full, mask_full, mask_sub, problem(full, False)
