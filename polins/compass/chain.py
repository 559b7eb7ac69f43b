"""The measurement chain of one image: raw mosaic -> Stokes -> masks -> sun vector -> heading.

One function, :func:`measure_image`, runs every method of ``polins.measure``
(docs/measurement.md):

1. Stokes rows and the sun-independent quality masks of the field-of-view pixels
   (docs/model.md §7), in float32 for integer mosaics (whose rounding is 4 orders below
   the 1 DN quantisation) and float64 for float mosaics;
2. a starting sun from the eigen solution on a fixed pixel subsample, the sun mask taken
   from the prior (docs/model.md §9.1);
3. ``"compensated"``: Gauss-Newton of the joint ML on the subsample, then one step on all
   valid pixels (docs/model.md §9.2, docs/measurement.md §5); otherwise the eigen solution
   on all valid pixels with its eigen-gap sandwich covariance (docs/model.md §10.2);
4. the heading, its 180 deg choice and the filter sigma: the pixel noise, the model error
   from a jackknife over sky sectors and the camera-fixed polarization, and the tilt term
   (docs/measurement.md §12).

Without an ephemeris (``sun_n=None``) the zenith is estimated, the yaw is NaN and the sun is
reported in the body frame, its 180 deg branch chosen by :mod:`polins.compass.branch`. A
joint ML that cannot be trusted (epsilon not separable from the sun, on its bound, or not
converged) falls back to the weighted eigen solution with the reason
(docs/measurement.md §11).

A :data:`Compensation` replaces the least-squares Stokes rows of step 1 by another
per-pixel estimate (the paper's Algorithm 1, :mod:`polins.compass.paper`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.special import ndtri

from polins.compass.branch import brightness_contrast, choose_branch, sun_angle_variances
from polins.compass.eigen import (
    EigenSolution,
    eigen_gap,
    eigen_level_rows,
    sandwich_covariance,
    weighted_residuals,
)
from polins.compass.heading import (
    check_sun_and_attitude,
    filter_sigmas,
    level_frames,
    resolve_sun_sign,
    yaw_from_sun_level,
    yaw_variance_from_sun_covariance,
)
from polins.compass.jointml import (
    MLSolution,
    epsilon_correlation,
    ml_evaluate,
    sun_covariance,
)
from polins.compass.kernels import dot, dot_rows, moment
from polins.compass.lens import CameraConstants, camera_constants, subsample
from polins.compass.measurement import METHODS, Measurement, MeasurementMaps, MeasureOptions
from polins.compass.modelerror import (
    cloudy_cells,
    depolarized_cells,
    fitted_sensitivity,
    instrumental_sensitivity,
    model_weights,
    sky_cells,
)
from polins.compass.pixels import check_raw
from polins.compass.polarimetry import stokes_calibration, stokes_image
from polins.compass.prediction import PixelData, pixel_data
from polins.compass.sectors import eigen_jackknife, jackknife_variance, sector_runs
from polins.compass.selection import Selection, selection_mask
from polins.compass.skymodel import sky_model
from polins.compass.solve import compensated_solution
from polins.errors import UserInputError
from polins.frames import heading_deg_from_yaw, wrap_angle
from polins.models import CameraModel
from polins.sky.neutral_points import berry_neutral_points_level

__all__ = ["Compensation", "measure_image"]

Compensation = Callable[[NDArray, CameraModel, NDArray], tuple[NDArray, NDArray]]
"""A per-pixel replacement of the Stokes estimate: ``(channels (4, n), cam, sun_c_prior (3,))
-> (rows (3, n) = (S0, S1, S2) [DN], epsilon (n,))``, with ``epsilon`` the per-pixel
direct-sunlight coefficient it estimated (its median over the used pixels is reported)."""


_SECTOR_MIN_SHARE = 1e-3
"""Smallest share of the azimuth information for a jackknife group to count."""

_DOP_TEST_PIXELS = 60_000
"""Pixels of the fitted sky's DoP test (every k-th field-of-view pixel): its cells' sums
need many more than the joint ML's subsample (docs/measurement.md §4)."""


def _excluded_sun(sun_c: NDArray, rays: NDArray, cos_excl: float) -> NDArray:
    return dot_rows(sun_c.astype(rays.dtype), rays) > cos_excl


def _noise_ratio(
    nu: NDArray, sigma2: NDArray | float, unsaturated: NDArray, index: NDArray
) -> float:
    """Robust measured / declared channel noise on the unsaturated pixels among ``index``,
    before the redundancy test (which would truncate ``nu``): from the fraction ``f`` of
    ``|nu| < sigma``, ``1 / Phi^-1((1 + f)/2)`` for Gaussian noise (a quantile, like the
    MAD, but without a sort)."""
    used = unsaturated.take(index)  # False for NaN
    n = int(np.count_nonzero(used))
    if n == 0:
        return float("nan")
    sigma = np.sqrt(sigma2.take(index) if isinstance(sigma2, np.ndarray) else sigma2)
    used &= np.abs(nu.take(index)) < sigma
    q = float(ndtri(0.5 + 0.5 * np.count_nonzero(used) / n))
    return 1.0 / q if q > 0 else float("inf")


def _ml_problem(ml: MLSolution, opt: MeasureOptions, converged: bool) -> str:
    """Why a joint ML solution cannot be used ("" if it can; docs/measurement.md §11)."""
    corr = epsilon_correlation(ml.covariance)
    if corr > opt.separability_max:
        what = "zenith" if ml.sun_parameters == 2 else "sun azimuth"
        return f"epsilon and {what} not separable (corr {corr:.4f})"
    if converged and not ml.converged:
        return "joint ML did not converge"
    eps = float(ml.theta[-1])
    if not abs(eps) < opt.epsilon_max:
        return f"epsilon {eps:.3g} at its bound {opt.epsilon_max:g} (physical: about 0 to 0.05)"
    return ""


def _check_inputs(
    sun_n: ArrayLike | None, rot_nb_prior: Rotation | None, sun_azimuth_b_prior: float | None
) -> tuple[NDArray | None, Rotation]:
    """The unit ENU sun (None without an ephemeris) and the prior attitude (identity, a
    level body, when there is none and no ``sun_n``)."""
    if sun_azimuth_b_prior is not None and not np.isfinite(sun_azimuth_b_prior):
        raise UserInputError(f"sun_azimuth_b_prior={sun_azimuth_b_prior} must be finite [rad]")
    if sun_n is None:
        if rot_nb_prior is None:
            return None, Rotation.identity()
        if not isinstance(rot_nb_prior, Rotation) or not rot_nb_prior.single:
            raise UserInputError("rot_nb_prior must be a single scipy Rotation (body -> ENU)")
        return None, rot_nb_prior
    if rot_nb_prior is None:
        raise UserInputError("sun_n needs rot_nb_prior: its roll and pitch level the sun")
    return check_sun_and_attitude(sun_n, rot_nb_prior), rot_nb_prior


def measure_image(
    raw: ArrayLike,
    cam: CameraModel,
    sun_n: ArrayLike | None,
    rot_nb_prior: Rotation | None,
    opt: MeasureOptions,
    *,
    method: str,
    maps: bool = False,
    compensation: Compensation | None = None,
    sun_azimuth_b_prior: float | None = None,
) -> tuple[Measurement, MeasurementMaps | None]:
    """One image through the chain (the body of ``polins.measure``).

    Parameters
    ----------
    raw : array_like, (H, W)
        Raw mosaic (checked with :func:`polins.compass.pixels.check_raw`).
    cam : CameraModel
    sun_n : array_like, (3,), or None
        ENU sun vector; None: measure the sun in the body frame only (no yaw,
        docs/measurement.md §11).
    rot_nb_prior : Rotation or None
        Prior body -> ENU attitude (required with ``sun_n``; without it only its roll and
        pitch are used, and None means a level body).
    opt : MeasureOptions
    method : {"compensated", "traditional", "paper"}
        ``"compensated"`` runs the joint ML, the others the eigen solution; the name is
        reported in the :class:`~polins.compass.measurement.Measurement` (``"traditional"``
        when the joint ML fell back to it).
    maps : bool
        Also return the per-pixel :class:`~polins.compass.measurement.MeasurementMaps`.
    compensation : Compensation, optional
        Replaces the least-squares Stokes rows (not with ``"compensated"``).
    sun_azimuth_b_prior : float, optional
        Without ``sun_n``: prior body-frame sun azimuth [rad] for the 180 deg branch.

    Returns
    -------
    Measurement, and MeasurementMaps or None
    """
    arr = check_raw(raw, cam)
    if method not in METHODS:
        raise ValueError(f"method={method!r}: expected one of {METHODS}")
    s_n, rot_prior = _check_inputs(sun_n, rot_nb_prior, sun_azimuth_b_prior)
    if compensation is not None and method == "compensated":
        raise ValueError("a per-pixel compensation replaces the joint ML: not with 'compensated'")

    # Frames: l is level with x_l the horizontal projection of body x (docs/conventions.md).
    yaw_prior, mat_lb, mat_cl, mat_cn = level_frames(rot_prior, cam)
    mat_lc = mat_cl.T
    zenith = float("nan")
    if s_n is not None:
        zenith = float(np.arccos(np.clip(s_n[2], -1.0, 1.0)))
        if s_n[2] <= 0.0:
            return Measurement.refused(method, "sun below the horizon"), None
        if zenith < opt.zenith_min:
            zenith_min_deg = float(np.degrees(opt.zenith_min))
            reason = f"sun within {zenith_min_deg:.3g} deg of the zenith: heading unobservable"
            return Measurement.refused(method, reason), None

    # Stokes of the field-of-view pixels and the sun-independent quality masks.
    # Precision follows the input: integer mosaics (quantised to 1 DN) in float32, whose
    # rounding is 4 orders below the quantisation noise; float mosaics in float64.
    dtype = np.float64 if np.issubdtype(arr.dtype, np.floating) else np.float32
    cache = camera_constants(cam, dtype)
    cal = stokes_calibration(cam, opt.gain_correction, cache.pixels)  # per-pixel with maps
    image = stokes_image(
        arr,
        cache.pixels,
        cam,
        cal,
        s0_min=opt.s0_min_dn,
        redundancy_max_sigma=opt.redundancy_max_sigma,
        gradient_max=opt.gradient_max,  # the DoP is cut per selection, see below
        channels=compensation is not None,
    )
    rows, sigma2, valid = image.rows, image.sigma2, image.valid
    if opt.max_field_angle is not None:
        valid &= cache.rays[2] >= dtype(np.cos(opt.max_field_angle))
    sigma_l2 = sigma2 * cal.sigma_l_factors() ** 2
    inv_sigma_l2: NDArray | float
    if isinstance(sigma_l2, np.ndarray):
        inv_sigma_l2 = (1.0 / sigma_l2).astype(dtype)
    else:
        inv_sigma_l2 = 1.0 / float(sigma_l2)
    n_fov = cache.pixels.size
    stride = max(1, n_fov // opt.gn_pixels) if opt.gn_pixels > 0 else 1
    sub = subsample(cam, dtype, stride)
    # Every 4th subsample pixel: ~4,000 pixels give the ratio to ~2 %.
    noise_ratio = _noise_ratio(rows[3], sigma2, image.unsaturated, sub.index[::4])

    cos_excl = float(np.cos(opt.sun_exclusion))
    epsilon_px = None
    if compensation is not None:
        if s_n is None:
            raise UserInputError(f"method={method!r} needs sun_n")
        assert image.channels is not None
        est_rows, epsilon_px = compensation(image.channels, cam, mat_cn @ s_n)
        est_rows = est_rows.astype(dtype)
        valid &= np.isfinite(est_rows).all(axis=0)
    else:
        est_rows = rows[:3]
    # Invalid pixels get harmless finite data (S = (1, 0, 0)): the full-set arithmetic then
    # runs over all pixels and masks by multiplication, with no compression or NaN handling.
    invalid = ~valid
    np.copyto(est_rows, np.array([[1.0], [0.0], [0.0]], dtype=dtype), where=invalid)
    np.copyto(rows[3], dtype(0.0), where=invalid)
    if isinstance(inv_sigma_l2, np.ndarray):
        np.copyto(inv_sigma_l2, dtype(1.0), where=invalid)

    def inv_weight_at(idx: NDArray | None) -> NDArray | float:
        w = inv_weight_l2
        if not isinstance(w, np.ndarray):
            return float(np.sqrt(w))
        return np.sqrt(w if idx is None else w.take(idx))

    def inv_sigma_at(idx: NDArray | None) -> NDArray | float:
        if not isinstance(inv_sigma_l2, np.ndarray):
            return float(np.sqrt(inv_sigma_l2))
        return np.sqrt(inv_sigma_l2 if idx is None else inv_sigma_l2.take(idx))

    def inv_sigma2_at(idx: NDArray) -> NDArray | float:
        return inv_sigma_l2.take(idx) if isinstance(inv_sigma_l2, np.ndarray) else inv_sigma_l2

    # 1. Starting sun: eigen solution on the fixed pixel subsample, sun mask from the prior
    # (without an ephemeris: from a first eigen solution, around the sun and the antisun).
    rows_sub = est_rows.take(sub.index, axis=1)
    valid_sub = valid[sub.index]
    s0d, s1d, s2d = rows_sub
    keep = valid_sub.copy()
    p2 = s1d * s1d + s2d * s2d
    keep &= p2 >= opt.dop_min**2 * (s0d * s0d)
    keep &= p2 >= opt.snr_min**2 / inv_sigma2_at(sub.index)

    def starting_eigen(mask: NDArray) -> EigenSolution:
        eig, _, _ = eigen_level_rows(
            s1d, s2d, inv_sigma2_at(sub.index), sub.basis, cache.projection, mat_lc,
            opt.weighted, mask=mask,
        )  # fmt: skip
        return eig

    if s_n is not None:
        keep &= ~_excluded_sun(mat_cn @ s_n, sub.rays, cos_excl)
    elif np.count_nonzero(keep) >= 3:
        sun_c00 = mat_cl @ starting_eigen(keep).sun
        keep &= ~_excluded_sun(sun_c00, sub.rays, cos_excl)
        keep &= ~_excluded_sun(-sun_c00, sub.rays, cos_excl)
    if np.count_nonzero(keep) * stride < opt.min_pixels:
        n_est = int(np.count_nonzero(keep)) * stride
        reason = f"too few valid pixels ({n_est} < {opt.min_pixels})"
        return Measurement.refused(method, reason, n_est), None
    eig0 = starting_eigen(keep)
    sun_l0 = eig0.sun
    if s_n is not None:
        sun_l0 = resolve_sun_sign(eig0.sun, s_n, yaw_prior, opt.horizon_fallback)

    cells = sky_cells(cam)
    if opt.cloud_dop_ratio is not None:  # thin clouds: cells with a DoP deficit (§4)
        cloudy = cloudy_cells(rows_sub, sub.rays, mat_cl @ sun_l0, opt.cloud_dop_ratio,
                              valid_sub, cells.take(sub.index))  # fmt: skip
        if cloudy.any():
            valid &= ~cloudy.take(cells)
            valid_sub = valid[sub.index]

    # Weights: the pixel noise, and with model_aop_std > 0 a model error of the AoP that
    # grows with the field angle and towards the sun and the antisun (§4).
    inv_weight_l2 = inv_sigma_l2
    if opt.model_aop_std > 0:
        inv_weight_l2 = model_weights(inv_sigma_l2, est_rows, cache.rays, mat_cl @ sun_l0, opt)

    # 2. Subsample selection with this sun; the DoP cut along the predicted direction.
    sel_sub = Selection(
        valid_sub, sub.rays, cos_excl, opt.dop_min, opt.snr_min / inv_sigma_at(sub.index)
    )
    fixed = opt.fixed_zenith and method == "compensated" and s_n is not None
    zen_arg = zenith if fixed else None
    a0 = float(np.arctan2(sun_l0[1], sun_l0[0]))
    z0 = float(np.arccos(np.clip(sun_l0[2], -1.0, 1.0)))
    extra = [opt.neutral_sep**2] * (opt.fit_sep and opt.sky_model == "berry") + [
        0.0
    ] * opt.fit_delta
    theta = np.array([a0, *([] if fixed else [z0]), *extra, opt.epsilon0])
    data_sub = pixel_data(
        rows_sub[0],
        rows_sub[1],
        rows_sub[2],
        sub.forward,
        inv_weight_at(sub.index),
        packed=True,
        rays=sub.lens_rays,
    )
    full_select = Selection(
        valid, cache.rays, cos_excl, opt.dop_min, opt.snr_min / inv_sigma_at(None)
    )
    data_full = pixel_data(
        est_rows[0],
        est_rows[1],
        est_rows[2],
        cache.forward,
        inv_weight_at(None),
        packed=True,
        rays=cache.lens_rays,
    )

    depolarized = None
    if opt.cloud_fit_ratio is not None:  # thin clouds by the fitted sky's DoP (§4)
        dense = subsample(cam, dtype, max(1, n_fov // _DOP_TEST_PIXELS))
        rows_d, valid_d = est_rows.take(dense.index, axis=1), valid[dense.index]
        cells_d, up_c, fit_ratio = cells.take(dense.index), mat_cl[:, 2], opt.cloud_fit_ratio

        def depolarized(azimuth: float, zenith_sun: float, sep: float) -> NDArray:
            points = berry_neutral_points_level(azimuth, zenith_sun, sep)
            points_c = (mat_cl @ points[0][:, 0], mat_cl @ points[1][:, 0])
            return depolarized_cells(rows_d, valid_d, dense.rays, cells_d, points_c, up_c,
                                     fit_ratio)  # fmt: skip

    used_method, fallback = method, ""
    gap = eigen_gap(eig0)
    mask: NDArray
    mask_sub: NDArray | None = None
    if method == "compensated":
        ml, mask_ml, mask_sub, fallback = compensated_solution(
            data_sub if stride > 1 else data_full, data_full, theta, zen_arg, mat_cl, sel_sub,
            full_select, cells, sub.index, (sector_runs(cam, stride), sector_runs(cam)),
            (sub.rays, cache.rays), lambda ml, conv: _ml_problem(ml, opt, conv), opt,
            depolarized,
        )  # fmt: skip
        if fallback:
            used_method = "traditional"  # weighted, with the reason (docs/measurement.md §11)
            fallback = f"compensated -> traditional: {fallback}"
        else:
            assert ml is not None and mask_ml is not None
            mask = mask_ml
            theta = ml.theta
            sun_l = ml.sun_l
            cov_sun_l = sun_covariance(ml)
            var_yaw = float(ml.covariance[0, 0])
            var_jack = float("nan")
            if ml.jackknife is not None and ml.sector_share is not None:
                var_jack = jackknife_variance(
                    ml.jackknife[:, 0], ml.sector_share, _SECTOR_MIN_SHARE
                )
            epsilon, epsilon_std = float(theta[-1]), float(np.sqrt(ml.covariance[-1, -1]))
            residual_rms = ml.residual_rms
    if used_method != "compensated":
        # 3. Eigen solution on all valid pixels, selected with the starting sun.
        mask = selection_mask(data_full, full_select, mat_cl @ sun_l0)
        eig, e, omega = eigen_level_rows(
            est_rows[1],
            est_rows[2],
            inv_weight_l2,
            cache.basis,
            cache.projection,
            mat_lc,
            opt.weighted or bool(fallback),
            mask=mask,
        )
        sun_l = eig.sun
        if s_n is not None:
            sun_l = resolve_sun_sign(eig.sun, s_n, yaw_prior, opt.horizon_fallback)
        gap = eigen_gap(eig)
        wr = weighted_residuals(e, omega, mat_cl @ sun_l)
        middle = moment(e, wr * wr)  # the sandwich's middle (docs/measurement.md §6)
        cov_sun_l = sandwich_covariance(eig, mat_lc @ middle @ mat_lc.T)
        var_yaw = yaw_variance_from_sun_covariance(sun_l, cov_sun_l)
        deltas, share = eigen_jackknife(e, wr, omega, sector_runs(cam), mat_lc, eig, sun_l)
        var_jack = jackknife_variance(deltas, share, _SECTOR_MIN_SHARE)
        theta = np.array([np.arctan2(sun_l[1], sun_l[0]), np.arccos(np.clip(sun_l[2], -1, 1)), 0.0])
        zen_arg = None
        epsilon, epsilon_std = float("nan"), float("nan")
        if epsilon_px is not None:
            epsilon = float(np.nanmedian(epsilon_px[mask])) if mask.any() else float("nan")
        r_sub, _, _, _ = ml_evaluate(
            dataclasses.replace(data_sub, mask=valid_sub), theta, None, mat_cl, False
        )
        r_sub = data_sub.sigma_scaled(r_sub)
        n_sub = max(int(np.count_nonzero(valid_sub)), 1)
        residual_rms = float(np.sqrt(dot(r_sub, r_sub) / n_sub))

    # The camera-fixed polarization's effect, on the subsample (a ratio of sums, §12).
    if mask_sub is None or used_method != "compensated":
        mask_sub = selection_mask(data_sub, sel_sub, mat_cl @ sun_l)
    data_used = dataclasses.replace(data_sub, mask=mask_sub)
    if used_method == "compensated" and opt.fit_delta:
        sky_r = sky_model(sub.rays, False, 0.0, False, True)
        assert sky_r is not None
        sensitivity = fitted_sensitivity(data_used, theta, zen_arg, mat_cl, sky_r)
    else:
        sensitivity = instrumental_sensitivity(data_used, theta, zen_arg, mat_cl,
                                               with_epsilon=used_method == "compensated")  # fmt: skip
    std_instrumental = float(np.hypot(opt.instrumental_dop_std * sensitivity[0],
                                      opt.instrumental_mixing_std * sensitivity[1]))  # fmt: skip
    n_pixels = int(np.count_nonzero(mask))
    if n_pixels < opt.min_pixels:
        reason = f"too few valid pixels ({n_pixels} < {opt.min_pixels})"
        return Measurement.refused(used_method, reason, n_pixels), None
    nu = rows[3] * mask
    noise_std_est = float(np.sqrt(dot(nu, nu) / n_pixels))
    mapped = _maps(cache, est_rows, mask, data_full, theta, zen_arg, mat_cl) if maps else None
    sun_l = sun_l / np.linalg.norm(sun_l)

    # The 180 deg branch: the ephemeris, or without one the elevation, the sky brightness,
    # the prior azimuth (docs/measurement.md §11).
    if s_n is not None:
        branch = "elevation" if sun_l[2] >= np.sin(opt.horizon_fallback) else "prior yaw"
    else:
        if sun_l[2] < 0:
            sun_l = -sun_l
        _, var_el_l = sun_angle_variances(sun_l, cov_sun_l)
        var_s0 = sigma2 * float(np.sum(cal.estimator[0] ** 2))
        brightness = brightness_contrast(
            rows_sub[0],
            valid_sub,
            sub.rays,
            mat_cl @ sun_l,
            var_s0.take(sub.index) if isinstance(var_s0, np.ndarray) else var_s0,
        )
        sun_b0 = mat_lb.T @ sun_l
        sign, branch = choose_branch(
            float(np.arcsin(np.clip(sun_l[2], -1.0, 1.0))),
            float(np.sqrt(var_el_l)),
            float(np.arctan2(sun_b0[1], sun_b0[0])),
            brightness,
            sun_azimuth_b_prior,
            elevation_min=opt.horizon_fallback,
            z_min=opt.branch_z_min,
            contrast_min=opt.branch_contrast_min,
        )
        sun_l = sign * sun_l
        zenith = float(np.arccos(np.clip(sun_l[2], -1.0, 1.0)))
        if zenith < opt.zenith_min:
            zenith_min_deg = float(np.degrees(opt.zenith_min))
            reason = f"sun within {zenith_min_deg:.3g} deg of the zenith: azimuth unobservable"
            return Measurement.refused(used_method, reason, n_pixels), mapped

    if not gap >= opt.eigen_gap_min:
        reason = f"eigen-gap {gap:.3f} below {opt.eigen_gap_min}"
        return Measurement.refused(used_method, reason, n_pixels), mapped
    yaw = yaw_from_sun_level(sun_l, s_n) if s_n is not None else float("nan")
    if opt.yaw_gate is not None and abs(float(wrap_angle(yaw - yaw_prior))) > opt.yaw_gate:
        reason = "heading outside the gate around the prior yaw"
        return Measurement.refused(used_method, reason, n_pixels), mapped
    if opt.residual_rms_max is not None and not residual_rms <= opt.residual_rms_max:
        reason = f"residual RMS {residual_rms:.3g} above {opt.residual_rms_max:g}"
        return Measurement.refused(used_method, reason, n_pixels), mapped
    if not np.isfinite(var_yaw) or var_yaw < 0:
        return Measurement.refused(used_method, "singular covariance", n_pixels), mapped

    std_meas = float(np.sqrt(var_yaw))
    # Model error: the jackknife's variance beyond the pixel noise, calibrated (§12).
    var_model = max(var_jack - var_yaw, 0.0) if np.isfinite(var_jack) else 0.0
    std_sky = opt.model_scale * np.sqrt(var_model)
    if not np.isfinite(std_instrumental):
        std_instrumental = 0.0
    std_model = float(np.sqrt(std_sky**2 + std_instrumental**2 + opt.sigma_floor**2))
    std_noise = opt.kappa * std_meas
    yaw_std, sun_std = filter_sigmas(std_noise, std_model, zenith, opt.tilt_std)
    sun_b = mat_lb.T @ sun_l
    var_az_b, var_el_b = sun_angle_variances(sun_b, mat_lb.T @ cov_sun_l @ mat_lb)
    azimuth_b = float(np.arctan2(sun_b[1], sun_b[0]))
    elevation_b = float(np.arcsin(np.clip(sun_b[2], -1.0, 1.0)))
    elevation_b_std = float("nan") if fixed else float(np.sqrt(var_el_b))
    if not fixed and not elevation_b_std <= opt.elevation_std_max:
        elevation_b = float("nan")
    reasons = [fallback]
    azimuth_b_alt = float("nan")
    if branch == "ambiguous":
        azimuth_b_alt = float(wrap_angle(azimuth_b + np.pi))
        reasons.append("ambiguous: 180 deg (the other candidate is sun_azimuth_b_alt)")
    result = Measurement(
        ok=True,
        reason="; ".join(r for r in reasons if r),
        method=used_method,
        yaw=yaw,
        yaw_std=yaw_std if s_n is not None else float("nan"),
        yaw_std_meas=std_meas if s_n is not None else float("nan"),
        heading_deg=float(heading_deg_from_yaw(yaw)) if s_n is not None else float("nan"),
        sun_b=sun_b,
        sun_l=sun_l,
        sun_c=mat_cl @ sun_l,
        sun_std=sun_std,
        epsilon=epsilon,
        epsilon_std=epsilon_std,
        n_pixels=n_pixels,
        eigen_gap=float(gap),
        residual_rms=float(residual_rms),
        noise_std_est=noise_std_est,
        sun_azimuth_b=azimuth_b,
        sun_azimuth_b_std=float(np.hypot(opt.kappa * np.sqrt(var_az_b), std_model)),
        sun_elevation_b=elevation_b,
        sun_elevation_b_std=elevation_b_std,
        sun_azimuth_b_alt=azimuth_b_alt,
        sun_branch=branch,
        noise_ratio=noise_ratio,
        yaw_std_noise=std_noise,
        yaw_std_model=std_model,
        yaw_std_correlated=float(std_instrumental),
        yaw_std_jackknife=float(np.sqrt(var_jack)),
    )
    return result, mapped


def _maps(
    cache: CameraConstants,
    est_rows: NDArray,
    mask: NDArray,
    data: PixelData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
) -> MeasurementMaps:
    s0, s1, s2 = (r.astype(np.float64) for r in est_rows)
    with np.errstate(invalid="ignore", divide="ignore"):
        dop_v = np.hypot(s1, s2) / s0
    r, _, _, _ = ml_evaluate(dataclasses.replace(data, mask=mask), theta, zenith, mat_cl, False)
    r = data.sigma_scaled(r)
    residual = np.where(mask, r, np.nan)
    px = cache.pixels
    return MeasurementMaps(
        aop=px.to_image(0.5 * np.arctan2(s2, s1)),
        dop=px.to_image(dop_v),
        valid=px.to_image(mask, fill=0.0).astype(bool),
        residual=px.to_image(residual),
    )
