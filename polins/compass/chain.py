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
4. the heading, its 180 deg choice and the filter sigma, inflated by
   ``kappa^2 sigma^2 + sigma_floor^2 + cot^2(Z) tilt_std^2`` (docs/model.md §10).

A :data:`Compensation` replaces the least-squares Stokes rows of step 1 by another
per-pixel estimate (the paper's Algorithm 1, :mod:`polins.compass.paper`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.compass.eigen import (
    eigen_gap,
    eigen_level_rows,
    sandwich_covariance,
    sandwich_middle,
)
from polins.compass.heading import (
    check_sun_and_attitude,
    filter_sigmas,
    level_frames,
    resolve_sun_sign,
    yaw_from_sun_level,
    yaw_variance_from_sun_covariance,
)
from polins.compass.jointml import gauss_newton, ml_evaluate
from polins.compass.kernels import dot, dot_rows
from polins.compass.lens import CameraConstants, camera_constants, subsample
from polins.compass.measurement import METHODS, Measurement, MeasurementMaps, MeasureOptions
from polins.compass.pixels import check_raw, gather_channels
from polins.compass.polarimetry import (
    stokes_calibration,
    stokes_noise_variance,
    stokes_rows,
    validity_rows,
)
from polins.compass.prediction import PixelData, pixel_data
from polins.compass.selection import Selection, selection_mask
from polins.frames import heading_deg_from_yaw, wrap_angle
from polins.models.loader import CameraModel

__all__ = ["Compensation", "measure_image"]

Compensation = Callable[[NDArray, CameraModel, NDArray], tuple[NDArray, NDArray]]
"""A per-pixel replacement of the Stokes estimate: ``(channels (4, n), cam, sun_c_prior (3,))
-> (rows (3, n) = (S0, S1, S2) [DN], epsilon (n,))``, with ``epsilon`` the per-pixel
direct-sunlight coefficient it estimated (its median over the used pixels is reported)."""


def _excluded_sun(sun_c: NDArray, rays: NDArray, cos_excl: float) -> NDArray:
    return dot_rows(sun_c.astype(rays.dtype), rays) > cos_excl


def measure_image(
    raw: ArrayLike,
    cam: CameraModel,
    sun_n: ArrayLike,
    rot_nb_prior: Rotation,
    opt: MeasureOptions,
    *,
    method: str,
    maps: bool = False,
    compensation: Compensation | None = None,
) -> tuple[Measurement, MeasurementMaps | None]:
    """One image through the chain (the body of ``polins.measure``).

    Parameters
    ----------
    raw : array_like, (H, W)
        Raw mosaic (checked with :func:`polins.compass.pixels.check_raw`).
    cam : CameraModel
    sun_n : array_like, (3,)
        ENU sun vector.
    rot_nb_prior : Rotation
        Prior body -> ENU attitude.
    opt : MeasureOptions
    method : {"compensated", "traditional", "paper"}
        ``"compensated"`` runs the joint ML, the others the eigen solution; the name is
        reported in the :class:`~polins.compass.measurement.Measurement`.
    maps : bool
        Also return the per-pixel :class:`~polins.compass.measurement.MeasurementMaps`.
    compensation : Compensation, optional
        Replaces the least-squares Stokes rows (not with ``"compensated"``).

    Returns
    -------
    Measurement, and MeasurementMaps or None
    """
    arr = check_raw(raw, cam)
    if method not in METHODS:
        raise ValueError(f"method={method!r}: expected one of {METHODS}")
    s_n = check_sun_and_attitude(sun_n, rot_nb_prior)
    if compensation is not None and method == "compensated":
        raise ValueError("a per-pixel compensation replaces the joint ML: not with 'compensated'")

    # Frames: l is level with x_l the horizontal projection of body x (docs/conventions.md).
    yaw_prior, mat_lb, mat_cl, mat_cn = level_frames(rot_nb_prior, cam)
    mat_lc = mat_cl.T
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
    channels = gather_channels(arr, cache.pixels, dtype)
    cal = stokes_calibration(cam, opt.gain_correction)
    rows = stokes_rows(channels, cal, dtype)
    sigma2 = stokes_noise_variance(cam, rows[0])
    valid = validity_rows(
        channels,
        rows,
        cache.pixels,
        cam,
        sigma2,
        dop_min=0.0,  # applied per selection, see below
        s0_min=opt.s0_min_dn,
        redundancy_max_sigma=opt.redundancy_max_sigma,
        gradient_max=opt.gradient_max,
        finite_check=dtype == np.float64,
    )
    sigma_l2 = sigma2 * cal.sigma_l_factor**2
    inv_sigma_l2: NDArray | float
    if isinstance(sigma_l2, np.ndarray):
        inv_sigma_l2 = (1.0 / sigma_l2).astype(dtype)
    else:
        inv_sigma_l2 = 1.0 / float(sigma_l2)

    sun_c_prior = mat_cn @ s_n
    cos_excl = float(np.cos(opt.sun_exclusion))
    epsilon_px = None
    if compensation is not None:
        est_rows, epsilon_px = compensation(channels, cam, sun_c_prior)
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

    def inv_sigma_at(idx: NDArray | None) -> NDArray | float:
        if not isinstance(inv_sigma_l2, np.ndarray):
            return float(np.sqrt(inv_sigma_l2))
        return np.sqrt(inv_sigma_l2 if idx is None else inv_sigma_l2.take(idx))

    def inv_sigma2_at(idx: NDArray) -> NDArray | float:
        return inv_sigma_l2.take(idx) if isinstance(inv_sigma_l2, np.ndarray) else inv_sigma_l2

    # 1. Starting sun: eigen solution on the fixed pixel subsample, sun mask from the prior.
    n_fov = cache.pixels.size
    stride = max(1, n_fov // opt.gn_pixels) if opt.gn_pixels > 0 else 1
    sub = subsample(cam, dtype, stride)
    rows_sub = est_rows.take(sub.index, axis=1)
    valid_sub = valid[sub.index]
    s0d, s1d, s2d = rows_sub
    keep = valid_sub & ~_excluded_sun(sun_c_prior, sub.rays, cos_excl)
    p2 = s1d * s1d + s2d * s2d
    keep &= p2 >= opt.dop_min**2 * (s0d * s0d)
    keep &= p2 >= opt.snr_min**2 / inv_sigma2_at(sub.index)
    if np.count_nonzero(keep) * stride < opt.min_pixels:
        n_est = int(np.count_nonzero(keep)) * stride
        reason = f"too few valid pixels ({n_est} < {opt.min_pixels})"
        return Measurement.refused(method, reason, n_est), None
    eig0, _, _ = eigen_level_rows(
        s1d,
        s2d,
        inv_sigma2_at(sub.index),
        sub.basis,
        cache.projection,
        mat_lc,
        opt.weighted,
        mask=keep,
    )
    sun_l0 = resolve_sun_sign(eig0.sun, s_n, yaw_prior, opt.horizon_fallback)

    # 2. Subsample selection with this sun; the DoP cut along the predicted direction.
    sel_sub = Selection(
        valid_sub, sub.rays, cos_excl, opt.dop_min, opt.snr_min / inv_sigma_at(sub.index)
    )
    fixed = opt.fixed_zenith and method == "compensated"
    zen_arg = zenith if fixed else None
    a0 = float(np.arctan2(sun_l0[1], sun_l0[0]))
    z0 = float(np.arccos(np.clip(sun_l0[2], -1.0, 1.0)))
    theta = np.array([a0, opt.epsilon0] if fixed else [a0, z0, opt.epsilon0])
    data_sub = pixel_data(
        rows_sub[0],
        rows_sub[1],
        rows_sub[2],
        sub.forward,
        inv_sigma_at(sub.index),
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
        inv_sigma_at(None),
        packed=True,
        rays=cache.lens_rays,
    )

    if method == "compensated":
        gap = eigen_gap(eig0)
        if stride > 1:
            ml, _ = gauss_newton(
                data_sub,
                theta,
                zen_arg,
                mat_cl,
                loss=opt.loss,
                max_iterations=opt.max_iterations,
                tol_sigma=0.1,  # the full-set step that follows removes the rest
                select=sel_sub,
            )
            if not ml.converged:
                return Measurement.refused(method, "joint ML did not converge", ml.n * stride), None
            theta = ml.theta
        # 3. One Gauss-Newton step on all valid pixels (iterate if there is no subsample).
        ml, mask = gauss_newton(
            data_full,
            theta,
            zen_arg,
            mat_cl,
            loss=opt.loss,
            max_iterations=1 if stride > 1 else opt.max_iterations,
            select=full_select,
        )
        if stride == 1 and not ml.converged:
            return Measurement.refused(method, "joint ML did not converge", ml.n), None
        assert mask is not None
        theta = ml.theta
        sun_l = ml.sun_l
        var_yaw = float(ml.covariance[0, 0])
        epsilon, epsilon_std = float(theta[-1]), float(np.sqrt(ml.covariance[-1, -1]))
        residual_rms = ml.residual_rms
    else:
        # 3. Eigen solution on all valid pixels, selected with the starting sun.
        mask = selection_mask(data_full, full_select, mat_cl @ sun_l0)
        eig, e, omega = eigen_level_rows(
            est_rows[1],
            est_rows[2],
            inv_sigma_l2,
            cache.basis,
            cache.projection,
            mat_lc,
            opt.weighted,
            mask=mask,
        )
        sun_l = resolve_sun_sign(eig.sun, s_n, yaw_prior, opt.horizon_fallback)
        gap = eigen_gap(eig)
        middle = sandwich_middle(e, omega, mat_cl @ sun_l)
        var_yaw = yaw_variance_from_sun_covariance(
            sun_l, sandwich_covariance(eig, mat_lc @ middle @ mat_lc.T)
        )
        theta = np.array([np.arctan2(sun_l[1], sun_l[0]), np.arccos(np.clip(sun_l[2], -1, 1)), 0.0])
        zen_arg = None
        epsilon, epsilon_std = float("nan"), float("nan")
        if epsilon_px is not None:
            epsilon = float(np.nanmedian(epsilon_px[mask]))
        r_sub, _, _, _ = ml_evaluate(
            dataclasses.replace(data_sub, mask=valid_sub), theta, None, mat_cl, False
        )
        r_sub = data_sub.sigma_scaled(r_sub)
        n_sub = max(int(np.count_nonzero(valid_sub)), 1)
        residual_rms = float(np.sqrt(dot(r_sub, r_sub) / n_sub))

    n_pixels = int(np.count_nonzero(mask))
    if n_pixels < opt.min_pixels:
        reason = f"too few valid pixels ({n_pixels} < {opt.min_pixels})"
        return Measurement.refused(method, reason, n_pixels), None
    nu = rows[3] * mask
    noise_std_est = float(np.sqrt(dot(nu, nu) / n_pixels))
    yaw = yaw_from_sun_level(sun_l, s_n)
    mapped = _maps(cache, est_rows, mask, data_full, theta, zen_arg, mat_cl) if maps else None

    if not gap >= opt.eigen_gap_min:
        reason = f"eigen-gap {gap:.3f} below {opt.eigen_gap_min}"
        return Measurement.refused(method, reason, n_pixels), mapped
    if opt.yaw_gate is not None and abs(float(wrap_angle(yaw - yaw_prior))) > opt.yaw_gate:
        reason = "heading outside the gate around the prior yaw"
        return Measurement.refused(method, reason, n_pixels), mapped
    if opt.residual_rms_max is not None and not residual_rms <= opt.residual_rms_max:
        reason = f"residual RMS {residual_rms:.3g} above {opt.residual_rms_max:g}"
        return Measurement.refused(method, reason, n_pixels), mapped
    if not np.isfinite(var_yaw) or var_yaw < 0:
        return Measurement.refused(method, "singular covariance", n_pixels), mapped

    std_meas = float(np.sqrt(var_yaw))
    yaw_std, sun_std = filter_sigmas(std_meas, zenith, opt.kappa, opt.sigma_floor, opt.tilt_std)
    sun_l = sun_l / np.linalg.norm(sun_l)
    result = Measurement(
        ok=True,
        reason="",
        method=method,
        yaw=yaw,
        yaw_std=yaw_std,
        yaw_std_meas=std_meas,
        heading_deg=float(heading_deg_from_yaw(yaw)),
        sun_b=mat_lb.T @ sun_l,
        sun_l=sun_l,
        sun_c=mat_cl @ sun_l,
        sun_std=sun_std,
        epsilon=epsilon,
        epsilon_std=epsilon_std,
        n_pixels=n_pixels,
        eigen_gap=float(gap),
        residual_rms=float(residual_rms),
        noise_std_est=noise_std_est,
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
