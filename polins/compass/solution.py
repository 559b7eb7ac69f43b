"""The solve stage of one image: the sun, its covariance and jackknife, compensated or traditional.

The fourth stage of :mod:`polins.compass.chain`. ``"compensated"``: the joint ML of the sun
and epsilon (:mod:`polins.compass.solve`; docs/model.md §9.2, docs/measurement.md §5); a
solution that cannot be trusted falls back to the weighted eigen solution with the reason
(docs/measurement.md §11). ``"traditional"``: the eigen solution on all valid pixels,
selected with the starting sun, with its eigen-gap sandwich covariance and the jackknife of
the eigenvector over sky sectors (docs/model.md §10.2, docs/measurement.md §6, §12).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from polins.compass.clouds import CLOUD_FIT_RATIO, DOP_TEST_PIXELS, DopTest
from polins.compass.eigen import (
    eigen_gap,
    eigen_level_rows,
    sandwich_covariance,
)
from polins.compass.heading import Geometry, resolve_sun_sign, yaw_variance_from_sun_covariance
from polins.compass.image import ImageStokes
from polins.compass.jointml import sun_covariance
from polins.compass.kernels import dot
from polins.compass.lens import subsample
from polins.compass.measurement import MeasureOptions
from polins.compass.residual import ml_evaluate
from polins.compass.sectors import (
    eigen_jackknife_sums,
    eigen_sandwich_sums,
    jackknife_variance,
    sector_runs,
)
from polins.compass.selection import selection_mask
from polins.compass.skypixels import SkyPixels
from polins.compass.solve import NEUTRAL_SEP, SolveSetup, compensated_solution
from polins.models import CameraModel

__all__ = ["Solution", "solve_compensated", "solve_image", "solve_traditional"]

_SECTOR_MIN_SHARE = 1e-3
"""Smallest share of the azimuth information for a jackknife group to count."""


@dataclass(frozen=True, eq=False)
class Solution:
    """The solve stage's result (level frame).

    Attributes
    ----------
    method : str
        ``"compensated"`` or ``"traditional"`` (also after a fallback).
    fallback : str
        Why the compensated solution fell back ("" if it did not).
    sun_l : (3,)
        The sun.
    cov_sun_l : (3, 3)
        Its pixel-noise covariance.
    var_yaw : float
        Pixel-noise variance of the yaw [rad^2].
    var_jack : float
        Jackknife variance of the azimuth over sky sectors [rad^2] (NaN without one).
    theta : (k,)
        Parameters ``(A_l[, Z_l], ..., eps)`` for the residuals.
    zenith : float or None
        The fixed zenith of ``theta`` [rad], None when it holds one.
    epsilon, epsilon_std : float
        Direct-sunlight coefficient and its sigma (NaN where not estimated).
    residual_rms : float
        RMS normalised residual.
    mask, mask_sub : (n,), (n_sub,) bool
        Pixels used, of the full set and of the subsample.
    eigen_gap : float
        Normalised eigen-gap of the eigen solution (the starting one for the joint ML).
    """

    method: str
    fallback: str
    sun_l: NDArray
    cov_sun_l: NDArray
    var_yaw: float
    var_jack: float
    theta: NDArray
    zenith: float | None
    epsilon: float
    epsilon_std: float
    residual_rms: float
    mask: NDArray
    mask_sub: NDArray
    eigen_gap: float


def solve_image(
    img: ImageStokes,
    cam: CameraModel,
    px: SkyPixels,
    geo: Geometry,
    opt: MeasureOptions,
    method: str,
    *,
    weighted: bool = True,
) -> Solution:
    """The solve stage: ``method="compensated"`` with its fallback, else the eigen solution
    (``weighted=False``: equal weights, the paper's Eq. 31)."""
    fallback = ""
    if method == "compensated":
        solved = solve_compensated(img, cam, px, geo, opt)
        if isinstance(solved, Solution):
            return solved
        fallback = f"compensated -> traditional: {solved}"  # weighted (docs/measurement.md §11)
    return solve_traditional(img, cam, px, geo, opt, weighted or bool(fallback), fallback)


def _dop_test(
    img: ImageStokes, cam: CameraModel, px: SkyPixels, geo: Geometry, ratio: float
) -> DopTest:
    """The pixels of the fitted sky's DoP test (every k-th field-of-view pixel)."""
    dense = subsample(cam, img.dtype, max(1, img.cache.pixels.size // DOP_TEST_PIXELS))
    return DopTest(img.estimate.take(dense.index, axis=1), px.valid[dense.index], dense.rays,
                   px.cells.take(dense.index), geo.mat_cl, ratio)  # fmt: skip


def solve_compensated(
    img: ImageStokes, cam: CameraModel, px: SkyPixels, geo: Geometry, opt: MeasureOptions
) -> Solution | str:
    """The joint ML from the starting sun, or why it cannot be used."""
    fixed = opt.fixed_zenith and geo.sun_n is not None
    zenith = geo.zenith if fixed else None
    sun_l0 = px.sun_l0
    a0 = float(np.arctan2(sun_l0[1], sun_l0[0]))
    z0 = float(np.arccos(np.clip(sun_l0[2], -1.0, 1.0)))
    extra = [NEUTRAL_SEP**2] * (opt.sky_model == "berry")
    extra += [0.0] * opt.fit_delta
    theta = np.array([a0, *([] if fixed else [z0]), *extra, opt.epsilon0])
    dop_test = None
    if opt.clouds == "auto":  # thin clouds by the fitted sky's DoP (§4), built when needed
        dop_test = functools.cache(lambda: _dop_test(img, cam, px, geo, CLOUD_FIT_RATIO))
    sub, cache = img.sub, img.cache
    data = (px.data_sub if img.stride > 1 else px.data_full, px.data_full)
    solved = compensated_solution(
        SolveSetup(zenith, geo.mat_cl, opt), data, theta, (px.select_sub, px.select_full),
        (px.cells_sub, px.cells), (sector_runs(cam, img.stride), sector_runs(cam)),
        (sub.rays, cache.rays), dop_test,
    )  # fmt: skip
    if solved.fallback:
        return solved.fallback
    ml = solved.ml
    assert solved.mask is not None
    var_jack = float("nan")
    if ml.jackknife is not None and ml.sector_share is not None:
        var_jack = jackknife_variance(ml.jackknife[:, 0], ml.sector_share, _SECTOR_MIN_SHARE)
    mask_sub = solved.mask_sub
    if mask_sub is None:
        mask_sub = selection_mask(px.data_sub, px.select_sub, geo.mat_cl @ ml.sun_l)
    return Solution(
        method="compensated",
        fallback="",
        sun_l=ml.sun_l,
        cov_sun_l=sun_covariance(ml),
        var_yaw=float(ml.covariance[0, 0]),
        var_jack=var_jack,
        theta=ml.theta,
        zenith=zenith,
        epsilon=float(ml.theta[-1]),
        epsilon_std=float(np.sqrt(ml.covariance[-1, -1])),
        residual_rms=ml.residual_rms,
        mask=solved.mask,
        mask_sub=mask_sub,
        eigen_gap=float(eigen_gap(px.eig0)),
    )


def solve_traditional(
    img: ImageStokes,
    cam: CameraModel,
    px: SkyPixels,
    geo: Geometry,
    opt: MeasureOptions,
    weighted: bool,
    fallback: str = "",
) -> Solution:
    """The eigen solution on all valid pixels selected with the starting sun, its sandwich
    covariance, its jackknife and the residual RMS on the subsample."""
    cache, est, mat_cl, mat_lc = img.cache, img.estimate, geo.mat_cl, geo.mat_lc
    mask = selection_mask(px.data_full, px.select_full, mat_cl @ px.sun_l0)
    eig, e, omega = eigen_level_rows(est[1], est[2], img.inv_sigma_l2, cache.basis,
                                     cache.projection, mat_lc, weighted, mask=mask)  # fmt: skip
    sun_l = eig.sun
    if geo.sun_n is not None:
        sun_l = resolve_sun_sign(eig.sun, geo.sun_n, geo.yaw_prior, opt.horizon_fallback)
    # The sandwich's middle sum_i (w_i r_i)^2 u_i u_i^T (docs/model.md §10.2,
    # docs/measurement.md §6) and the jackknife's sums, in one pass.
    middle, run_sums = eigen_sandwich_sums(e, omega, mat_cl @ sun_l, sector_runs(cam))
    cov_sun_l = sandwich_covariance(eig, mat_lc @ middle @ mat_lc.T)
    deltas, share = eigen_jackknife_sums(run_sums, sector_runs(cam), mat_lc, eig, sun_l)
    theta = np.array([np.arctan2(sun_l[1], sun_l[0]), np.arccos(np.clip(sun_l[2], -1, 1)), 0.0])
    epsilon = float("nan")
    if img.epsilon_px is not None:
        epsilon = float(np.nanmedian(img.epsilon_px[mask])) if mask.any() else float("nan")
    data_sub = px.data_sub
    r_sub, _, _, _ = ml_evaluate(
        dataclasses.replace(data_sub, mask=px.valid_sub), theta, None, mat_cl, False
    )
    r_sub = data_sub.sigma_scaled(r_sub)
    n_sub = max(int(np.count_nonzero(px.valid_sub)), 1)
    return Solution(
        method="traditional",
        fallback=fallback,
        sun_l=sun_l,
        cov_sun_l=cov_sun_l,
        var_yaw=yaw_variance_from_sun_covariance(sun_l, cov_sun_l),
        var_jack=jackknife_variance(deltas, share, _SECTOR_MIN_SHARE),
        theta=theta,
        zenith=None,
        epsilon=epsilon,
        epsilon_std=float("nan"),
        residual_rms=float(np.sqrt(dot(r_sub, r_sub) / n_sub)),
        mask=mask,
        mask_sub=selection_mask(data_sub, px.select_sub, mat_cl @ sun_l),
        eigen_gap=float(eigen_gap(eig)),
    )
