"""The measurement chain of one image as named stages: Stokes -> pixels -> solve -> heading.

:func:`measure_image` (the body of ``polins.measure``, docs/measurement.md) composes

1. :func:`polins.compass.heading.image_geometry`: the sun and the level frames of the prior;
2. :func:`polins.compass.image.image_stokes`: Stokes rows, noise and the sun-independent
   quality masks of the field-of-view pixels (docs/model.md §7);
3. :func:`polins.compass.skypixels.sky_pixels`: the region of interest, the starting sun,
   the thin-cloud cells, the weights and the selection rules (docs/measurement.md §4);
4. :func:`polins.compass.solution.solve_image`: ``"compensated"`` (the joint ML, with its
   fallback) or ``"traditional"`` (the eigen solution) (docs/measurement.md §5, §6, §11);
5. :func:`instrumental_std`, :func:`sun_branch` and :func:`heading_measurement`: the
   camera-fixed part of the sigma, the 180 deg branch, the heading and its filter sigma
   (docs/measurement.md §11, §12).

Without an ephemeris (``sun_n=None``) the zenith is estimated, the yaw is NaN and the sun is
reported in the body frame, its 180 deg branch chosen by :mod:`polins.compass.branch`.
:func:`measure_stokes` runs stages 3-5 on a given Stokes stage (another per-pixel estimate
of the rows, e.g. :mod:`polins.sim.algorithm1`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.compass.branch import brightness_contrast, choose_branch, sun_angle_variances
from polins.compass.heading import (
    Geometry,
    filter_sigmas,
    image_geometry,
    yaw_from_sun_level,
)
from polins.compass.image import ImageStokes, image_stokes
from polins.compass.instrumental import fitted_sensitivity, instrumental_sensitivity
from polins.compass.kernels import compiled
from polins.compass.measurement import (
    Measurement,
    MeasurementMaps,
    MeasureOptions,
    Refusal,
    check_method,
)
from polins.compass.pixels import check_raw
from polins.compass.residual import ml_evaluate
from polins.compass.skymodel import sky_model
from polins.compass.skypixels import SkyPixels, sky_pixels
from polins.compass.solution import Solution, solve_image
from polins.compass.zenith import zenith_solution
from polins.frames import heading_deg_from_yaw, wrap_angle
from polins.models import CameraModel

__all__ = [
    "BRANCH_CONTRAST_MIN",
    "BRANCH_Z_MIN",
    "EIGEN_GAP_MIN",
    "ELEVATION_STD_MAX",
    "INSTRUMENTAL_DOP_STD",
    "MODEL_SCALE",
    "ZENITH_MIN",
    "Branch",
    "check_sun",
    "heading_measurement",
    "instrumental_std",
    "instrumental_stds",
    "measure_image",
    "measure_stokes",
    "sun_branch",
]


ZENITH_MIN = float(np.radians(5.0))
"""A sun closer than this to the zenith is refused [rad]: the azimuth is unobservable."""

EIGEN_GAP_MIN = 0.5
"""A normalised eigen-gap below this is refused (docs/model.md §10.1)."""

MODEL_SCALE = 2.0
"""Calibration of the sky-model part of the sigma: the jackknife's variance beyond the pixel
noise times ``MODEL_SCALE^2`` (calibrated on realistic skies, with and without ``sun_n``;
docs/measurement.md §12)."""

INSTRUMENTAL_DOP_STD = 0.002
"""``instrumental_dop_std="auto"`` without a camera-file figure: gains good to +-0.5 %."""

ELEVATION_STD_MAX = float(np.radians(5.0))
"""Sun-free measurement: ``sun_elevation_b`` is reported when its sigma is below this [rad]."""

BRANCH_Z_MIN = 5.0
"""Sun-free measurement: significance [sigmas] an elevation or a brightness difference needs
to choose the 180 deg branch (docs/measurement.md §11)."""

BRANCH_CONTRAST_MIN = 0.02
"""Sun-free measurement: smallest relative brightness difference between the sun side and
the antisun side for the brightness to choose the branch [-]."""


@dataclass(frozen=True)
class Branch:
    """The 180 deg branch of the solved sun.

    Attributes
    ----------
    sun_l : (3,)
        Unit level-frame sun on the chosen branch.
    branch : str
        What chose it (docs/measurement.md §11).
    zenith : float
        Its zenith [rad] (the ephemeris' with ``sun_n``).
    """

    sun_l: NDArray
    branch: str
    zenith: float


def check_sun(geo: Geometry) -> None:
    """Refuse a sun below the horizon or within :data:`ZENITH_MIN` of the zenith (with an
    ephemeris; no check without one).

    Raises
    ------
    Refusal
        With the reason, for :meth:`Measurement.refused`.
    """
    if geo.sun_n is None:
        return
    if geo.sun_n[2] <= 0.0:
        raise Refusal("sun below the horizon")
    if geo.zenith < ZENITH_MIN:
        zenith_min_deg = float(np.degrees(ZENITH_MIN))
        raise Refusal(f"sun within {zenith_min_deg:.3g} deg of the zenith: heading unobservable")


def measure_image(
    raw: ArrayLike,
    cam: CameraModel,
    sun_n: ArrayLike | None,
    rot_nb_prior: Rotation | None,
    opt: MeasureOptions,
    *,
    method: str,
    maps: bool = False,
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
    method : {"compensated", "traditional"}
        ``"compensated"`` runs the joint ML, ``"traditional"`` the eigen solution; the
        :class:`~polins.compass.measurement.Measurement` reports the one used
        (``"traditional"`` when the joint ML fell back to it).
    maps : bool
        Also return the per-pixel :class:`~polins.compass.measurement.MeasurementMaps`.
    sun_azimuth_b_prior : float, optional
        Without ``sun_n``: prior body-frame sun azimuth [rad] for the 180 deg branch.

    Returns
    -------
    Measurement, and MeasurementMaps or None
    """
    arr = check_raw(raw, cam)
    check_method(method)
    geo = image_geometry(cam, sun_n, rot_nb_prior, sun_azimuth_b_prior)
    try:
        check_sun(geo)
    except Refusal as r:
        return Measurement.refused(method, r.reason, r.n_pixels), None
    img = image_stokes(arr, cam, opt)
    return measure_stokes(img, cam, geo, opt, method=method, maps=maps)


def measure_stokes(
    img: ImageStokes,
    cam: CameraModel,
    geo: Geometry,
    opt: MeasureOptions,
    *,
    method: str,
    maps: bool = False,
    weighted: bool = True,
) -> tuple[Measurement, MeasurementMaps | None]:
    """Stages 3-5 of the chain on a Stokes stage ``img`` (module notes); ``weighted=False``
    gives the eigen solution equal weights (the paper's Eq. 31)."""
    try:
        px = sky_pixels(img, cam, geo, opt, weighted=weighted)
    except Refusal as r:
        return Measurement.refused(method, r.reason, r.n_pixels), None
    sol = solve_image(img, cam, px, geo, opt, method, weighted=weighted)
    std_instrumental = instrumental_std(img, cam, px, sol, geo, opt)
    if sol.method == "traditional":  # the zenith cone when its sigma is smaller (§13)
        stds = instrumental_stds(cam, opt)
        zen = zenith_solution(img, px, sol, geo, opt, std_instrumental, stds, MODEL_SCALE)
        sol, std_instrumental = zen if zen is not None else (sol, std_instrumental)
    n_pixels = int(np.count_nonzero(sol.mask))
    if n_pixels < opt.min_pixels:
        reason = f"too few valid pixels ({n_pixels} < {opt.min_pixels})"
        return Measurement.refused(sol.method, reason, n_pixels), None
    nu2 = compiled("square_sum_pass")(img.rows[3], sol.mask)
    noise_std_est = float(np.sqrt(nu2 / n_pixels))
    mapped = _maps(img, px, sol, geo) if maps else None
    fixed = opt.fixed_zenith and method == "compensated" and geo.sun_n is not None
    try:
        branch = sun_branch(img, px, sol, geo, opt, n_pixels)
        result = heading_measurement(sol, branch, geo, opt, n_pixels, fixed, std_instrumental)
    except Refusal as r:
        return Measurement.refused(sol.method, r.reason, r.n_pixels), mapped
    return dataclasses.replace(
        result, noise_std_est=noise_std_est, noise_ratio=img.noise_ratio
    ), mapped


def instrumental_stds(cam: CameraModel, opt: MeasureOptions) -> tuple[float, float]:
    """``instrumental_dop_std`` and ``instrumental_mixing_std`` [-], ``"auto"`` resolved:
    the camera file's figures, else :data:`INSTRUMENTAL_DOP_STD` and 0."""
    dop_std, mixing_std = opt.instrumental_dop_std, opt.instrumental_mixing_std
    if dop_std == "auto":
        dop_std = (
            INSTRUMENTAL_DOP_STD if cam.instrumental_dop_std is None else cam.instrumental_dop_std
        )
    if mixing_std == "auto":
        mixing_std = 0.0 if cam.instrumental_mixing_std is None else cam.instrumental_mixing_std
    return float(dop_std), float(mixing_std)


def instrumental_std(
    img: ImageStokes,
    cam: CameraModel,
    px: SkyPixels,
    sol: Solution,
    geo: Geometry,
    opt: MeasureOptions,
) -> float:
    """The camera-fixed polarization's yaw sigma [rad] on the subsample (a ratio of sums,
    docs/measurement.md §12); 0 where the sensitivity is not finite."""
    data_used = dataclasses.replace(px.data_sub, mask=sol.mask_sub)
    if sol.method == "compensated" and opt.fit_delta:
        sky_r = sky_model(img.sub.rays, False, 0.0, False, True)
        assert sky_r is not None
        sensitivity = fitted_sensitivity(data_used, sol.theta, sol.zenith, geo.mat_cl, sky_r)
    else:
        sensitivity = instrumental_sensitivity(data_used, sol.theta, sol.zenith, geo.mat_cl,
                                               with_epsilon=sol.method == "compensated")  # fmt: skip
    dop_std, mixing_std = instrumental_stds(cam, opt)
    std = float(np.hypot(dop_std * sensitivity[0], mixing_std * sensitivity[1]))
    return std if np.isfinite(std) else 0.0


def sun_branch(
    img: ImageStokes,
    px: SkyPixels,
    sol: Solution,
    geo: Geometry,
    opt: MeasureOptions,
    n_pixels: int,
) -> Branch:
    """The 180 deg branch: the ephemeris, or without one the elevation, the sky
    brightness, the prior azimuth (docs/measurement.md §11).

    Raises
    ------
    Refusal
        Without an ephemeris, the chosen sun within :data:`ZENITH_MIN` of the zenith.
    """
    sun_l = sol.sun_l / np.linalg.norm(sol.sun_l)
    if geo.sun_n is not None:
        branch = "elevation" if sun_l[2] >= np.sin(opt.horizon_fallback) else "prior yaw"
        return Branch(sun_l, branch, geo.zenith)
    if sun_l[2] < 0:
        sun_l = -sun_l
    _, var_el_l = sun_angle_variances(sun_l, sol.cov_sun_l)
    var_s0 = img.sigma2 * float(np.sum(img.cal.estimator[0] ** 2))
    if isinstance(var_s0, np.ndarray):
        var_s0 = var_s0.take(img.sub.index)
    brightness = brightness_contrast(px.rows_sub[0], px.valid_sub, img.sub.rays,
                                     geo.mat_cl @ sun_l, var_s0)  # fmt: skip
    sun_b0 = geo.mat_lb.T @ sun_l
    sign, branch = choose_branch(
        float(np.arcsin(np.clip(sun_l[2], -1.0, 1.0))),
        float(np.sqrt(var_el_l)),
        float(np.arctan2(sun_b0[1], sun_b0[0])),
        brightness,
        geo.sun_azimuth_b_prior,
        elevation_min=opt.horizon_fallback,
        z_min=BRANCH_Z_MIN,
        contrast_min=BRANCH_CONTRAST_MIN,
    )
    sun_l = sign * sun_l
    zenith = float(np.arccos(np.clip(sun_l[2], -1.0, 1.0)))
    if zenith < ZENITH_MIN:
        zenith_min_deg = float(np.degrees(ZENITH_MIN))
        reason = f"sun within {zenith_min_deg:.3g} deg of the zenith: azimuth unobservable"
        raise Refusal(reason, n_pixels)
    return Branch(sun_l, branch, zenith)


def _check_solution(
    sol: Solution, yaw: float, geo: Geometry, opt: MeasureOptions, n_pixels: int
) -> None:
    """Refuse a small eigen-gap, a heading outside the gate, a large residual or a
    singular covariance."""
    if not sol.eigen_gap >= EIGEN_GAP_MIN:
        raise Refusal(f"eigen-gap {sol.eigen_gap:.3f} below {EIGEN_GAP_MIN}", n_pixels)
    if opt.gate is not None and abs(float(wrap_angle(yaw - geo.yaw_prior))) > opt.gate:
        raise Refusal("heading outside the gate around the prior yaw", n_pixels)
    limit = opt.residual_limit
    if limit is not None and not sol.residual_rms <= limit:
        reason = f"residual RMS {sol.residual_rms:.3g} above {limit:g}"
        raise Refusal(reason, n_pixels)
    if not np.isfinite(sol.var_yaw) or sol.var_yaw < 0:
        raise Refusal("singular covariance", n_pixels)


def heading_measurement(
    sol: Solution,
    br: Branch,
    geo: Geometry,
    opt: MeasureOptions,
    n_pixels: int,
    fixed: bool,
    std_instrumental: float,
) -> Measurement:
    """The heading, its filter sigma and the body-frame sun of a solution on its branch
    (``fixed``: the zenith came from the ephemeris; ``std_instrumental`` [rad] the
    camera-fixed part, :func:`instrumental_std`; docs/measurement.md §12). The noise
    figures of the image are filled in by the caller."""
    s_n, sun_l = geo.sun_n, br.sun_l
    yaw = yaw_from_sun_level(sun_l, s_n) if s_n is not None else float("nan")
    _check_solution(sol, yaw, geo, opt, n_pixels)
    std_meas = float(np.sqrt(sol.var_yaw))
    # Model error: the jackknife's variance beyond the pixel noise, calibrated (§12).
    var_model = max(sol.var_jack - sol.var_yaw, 0.0) if np.isfinite(sol.var_jack) else 0.0
    std_sky = MODEL_SCALE * np.sqrt(var_model)
    std_model = float(np.sqrt(std_sky**2 + std_instrumental**2))
    yaw_std, sun_std = filter_sigmas(std_meas, std_model, br.zenith, opt.tilt_std)
    sun_b = geo.mat_lb.T @ sun_l
    var_az_b, var_el_b = sun_angle_variances(sun_b, geo.mat_lb.T @ sol.cov_sun_l @ geo.mat_lb)
    azimuth_b = float(np.arctan2(sun_b[1], sun_b[0]))
    elevation_b = float(np.arcsin(np.clip(sun_b[2], -1.0, 1.0)))
    elevation_b_std = float("nan") if fixed else float(np.sqrt(var_el_b))
    if not fixed and not elevation_b_std <= ELEVATION_STD_MAX:
        elevation_b = float("nan")
    reasons = [sol.fallback]
    azimuth_b_alt = float("nan")
    if br.branch == "ambiguous":
        azimuth_b_alt = float(wrap_angle(azimuth_b + np.pi))
        reasons.append("ambiguous: 180 deg (the other candidate is sun_azimuth_b_alt)")
    no_yaw = s_n is None
    return Measurement(
        ok=True,
        reason="; ".join(r for r in reasons if r),
        method=sol.method,
        yaw=yaw,
        yaw_std=float("nan") if no_yaw else yaw_std,
        yaw_std_meas=float("nan") if no_yaw else std_meas,
        heading_deg=float("nan") if no_yaw else float(heading_deg_from_yaw(yaw)),
        sun_b=sun_b,
        sun_l=sun_l,
        sun_c=geo.mat_cl @ sun_l,
        sun_std=sun_std,
        epsilon=sol.epsilon,
        epsilon_std=sol.epsilon_std,
        n_pixels=n_pixels,
        eigen_gap=sol.eigen_gap,
        residual_rms=float(sol.residual_rms),
        sun_azimuth_b=azimuth_b,
        sun_azimuth_b_std=float(np.hypot(np.sqrt(var_az_b), std_model)),
        sun_elevation_b=elevation_b,
        sun_elevation_b_std=elevation_b_std,
        sun_azimuth_b_alt=azimuth_b_alt,
        sun_branch=br.branch,
        yaw_std_noise=std_meas,
        yaw_std_model=std_model,
        yaw_std_correlated=float(std_instrumental),
        yaw_std_jackknife=float(np.sqrt(sol.var_jack)),
    )


def _maps(img: ImageStokes, px: SkyPixels, sol: Solution, geo: Geometry) -> MeasurementMaps:
    """Per-pixel AoP, DoP, used pixels and normalised residual at the solution."""
    s0, s1, s2 = (r.astype(np.float64) for r in img.estimate)
    with np.errstate(invalid="ignore", divide="ignore"):
        dop_v = np.hypot(s1, s2) / s0
    data = dataclasses.replace(px.data_full, mask=sol.mask)
    r, _, _, _ = ml_evaluate(data, sol.theta, sol.zenith, geo.mat_cl, False)
    r = px.data_full.sigma_scaled(r)
    residual = np.where(sol.mask, r, np.nan)
    pixels = img.cache.pixels
    return MeasurementMaps(
        aop=pixels.to_image(0.5 * np.arctan2(s2, s1)),
        dop=pixels.to_image(dop_v),
        valid=pixels.to_image(sol.mask, fill=0.0).astype(bool),
        residual=pixels.to_image(residual),
    )
