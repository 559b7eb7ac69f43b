"""Polarization compass: raw DoFP image -> sun vector -> heading with its covariance
(SPEC.md sections 7-10); the public entry point is :func:`measure` (``polins.measure``).

Three methods return the same :class:`Measurement`:

``"traditional"``
    Gain-corrected least-squares Stokes, E-vectors built in the camera frame and rotated with
    the prior roll/pitch (SPEC 6.1), weighted eigen sun vector (SPEC 9.1), eigen-gap sandwich
    covariance (SPEC 10.2).
``"paper"``
    The paper's Algorithm 1 (SPEC 8.2) followed by the same eigen solution. A *reproduction
    mode* with switches for the printed or scale-consistent Eq. 22 and k_c; its per-pixel k_m
    is degenerate (AUDIT section 1, Eq. 22). Not for operational use.
``"compensated"`` (default)
    Joint maximum likelihood of the sun azimuth (and zenith, unless fixed from the ephemeris)
    and the direct-sunlight coefficient epsilon over the whole image (SPEC 9.2), with the
    compensation angle taken from the estimated sun, not the INS prior. Gauss-Newton runs on
    a pixel subsample and finishes with one Gauss-Newton step on all valid pixels.

Heading (SPEC 10.1): ``yaw = wrap(atan2(s_n_y, s_n_x) - atan2(s_l_y, s_l_x))``; the eigenvector
sign is fixed by the sun being above the horizon, and only within ``horizon_fallback_deg`` of
the horizon by the prior yaw. The filter covariance is the measurement variance inflated by
``kappa^2 sigma^2 + sigma_floor^2 + cot^2(Z) sigma_tilt^2`` (SPEC 10.2).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.compass.camera import pixel_rays_c
from polins.compass.polarimetry import (
    PixelSet,
    _gather,
    _paper_rows,
    _stokes_rows,
    _valid_rows,
    check_raw,
    pixel_set,
    stokes_calibration,
    stokes_noise_variance,
    sunlight_direction,
    sunlight_stokes,
)
from polins.compass.sunvector import (
    LOSSES,
    EigenSolution,
    _dot,
    _dot_rows,
    _eigen_from_moment,
    _evector_rows,
    _gauss_newton,
    _lens_basis_rows,
    _lens_forward_rows,
    _ml_data,
    _ml_evaluate,
    _MLData,
    _moment,
    _pack_forward,
    _sandwich,
    _sandwich_middle,
    _Selection,
    _selection_mask,
    eigen_gap,
    yaw_from_sun_level,
    yaw_variance_from_sun_covariance,
)
from polins.frames import (
    heading_deg_from_yaw,
    rot_lb_from_rot_nb,
    wrap_angle,
    yaw_from_rot_nb,
)
from polins.models.loader import CameraModel

FloatArray = NDArray[np.float64]

METHODS = ("compensated", "traditional", "paper")

__all__ = [
    "METHODS",
    "MeasureOptions",
    "Measurement",
    "MeasurementMaps",
    "measure",
    "measure_with_maps",
    "yaw_crlb",
]


@dataclass(frozen=True)
class MeasureOptions:
    """Options of :func:`measure` (pass them as keyword arguments).

    Attributes
    ----------
    gain_correction : bool
        Apply the calibrated channel gains in the Stokes estimate (False: the paper's
        uncorrected "traditional" baseline).
    weighted : bool
        Eigen weights ``p^2/sigma_L^2`` (SPEC 9.1); False = the paper's equal weights
        (``method="paper", weighted=False`` is Algorithm 1 followed by the paper's Eq. 31).
    paper_eq22 : {"scale-consistent", "printed"}
        ``method="paper"``: m = 2 or the printed m = 4 in Eq. 22 (SPEC 8.2).
    paper_kc : float
        ``method="paper"``: the empirical k_c.
    paper_gain_final : bool
        ``method="paper"``: divide the compensated intensities by beta_k.
    paper_eq14 : {"fixed", "printed"}
        ``method="paper"``: Stokes signs; "printed" reproduces the paper's 90 deg AoP error.
    fixed_zenith : bool
        ``method="compensated"``: fix the sun zenith to the ephemeris (needs good roll/pitch).
    loss : {"linear", "huber", "cauchy"}
        Loss of the joint ML (IRLS); robust losses down-weight outlier pixels.
    sun_exclusion_deg : float
        Pixels closer than this to the sun are not used [deg].
    dop_min : float
        Minimum degree of polarization.
    snr_min : float
        Minimum polarized intensity in units of its noise sigma_L: rejects unpolarized
        scenery (occluders, ground, clouds) whose noise alone would pass ``dop_min``.
    kappa : float
        Correlated-error inflation factor, ``kappa^2 = N/N_eff`` (SPEC 10.2).
    sigma_floor_deg : float
        Model-error floor of the heading [deg].
    tilt_std : float
        1-sigma roll/pitch error about the horizontal axis towards the sun [rad]; adds
        ``cot(Z) tilt_std`` to the heading sigma.
    yaw_gate : float or None
        Refuse if the heading differs from the prior yaw by more than this [rad].
    gradient_max : float or None
        Maximum relative intensity gradient ``|grad S0|/S0`` [1/superpixel]; None: no test.
    redundancy_max_sigma : float
        Maximum redundancy residual ``|nu|`` in channel-noise sigmas (SPEC 7.3).
    s0_min_dn : float
        Minimum S0 [DN] (dark / occluded pixels).
    min_pixels : int
        Refuse with fewer valid pixels.
    eigen_gap_min : float
        Refuse if the normalised eigen-gap is below this (SPEC 10.1).
    residual_rms_max : float or None
        Refuse if the RMS normalised residual exceeds this (e.g. a wrong channel
        calibration, clouds); None: no test (real skies have model errors far above the
        noise, so a threshold must come from field data).
    zenith_min_deg : float
        Refuse if the sun is closer than this to the zenith [deg].
    horizon_fallback_deg : float
        Below this sun elevation [deg] the prior yaw chooses between yaw and yaw + 180 deg.
    gn_pixels : int
        Target number of pixels of the Gauss-Newton subsample (0: all pixels every
        iteration); the last step always uses all valid pixels.
    max_iterations : int
        Gauss-Newton iterations on the subsample.
    epsilon0 : float
        Starting epsilon (e.g. the previous image's estimate).
    """

    gain_correction: bool = True
    weighted: bool = True
    paper_eq22: str = "scale-consistent"
    paper_kc: float = 20.0
    paper_gain_final: bool = True
    paper_eq14: str = "fixed"
    fixed_zenith: bool = True
    loss: str = "linear"
    sun_exclusion_deg: float = 10.0
    dop_min: float = 0.03
    snr_min: float = 3.0
    kappa: float = 1.0
    sigma_floor_deg: float = 0.1
    tilt_std: float = 0.0
    yaw_gate: float | None = None
    gradient_max: float | None = 0.05
    redundancy_max_sigma: float = 4.0
    s0_min_dn: float = 10.0
    min_pixels: int = 500
    eigen_gap_min: float = 0.5
    residual_rms_max: float | None = None
    zenith_min_deg: float = 5.0
    horizon_fallback_deg: float = 5.0
    gn_pixels: int = 15_000
    max_iterations: int = 10
    epsilon0: float = 0.0

    def __post_init__(self) -> None:
        if self.paper_eq22 not in ("scale-consistent", "printed"):
            raise ValueError(f"paper_eq22={self.paper_eq22!r}: 'scale-consistent' or 'printed'")
        if self.paper_eq14 not in ("fixed", "printed"):
            raise ValueError(f"paper_eq14={self.paper_eq14!r}: expected 'fixed' or 'printed'")
        if self.loss not in LOSSES:
            raise ValueError(f"loss={self.loss!r}: expected one of {LOSSES}")
        for name in ("kappa", "sun_exclusion_deg", "sigma_floor_deg", "tilt_std"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name}={getattr(self, name)} must be >= 0")
        if not 0 <= self.dop_min < 1:
            raise ValueError(f"dop_min={self.dop_min} outside [0, 1)")
        if self.min_pixels < 3 or self.max_iterations < 1 or self.gn_pixels < 0:
            raise ValueError("min_pixels >= 3, max_iterations >= 1 and gn_pixels >= 0 required")


def _options(options: dict[str, Any]) -> MeasureOptions:
    valid = [f.name for f in dataclasses.fields(MeasureOptions)]
    unknown = sorted(set(options) - set(valid))
    if unknown:
        raise TypeError(f"unknown measure option(s) {unknown}; valid options: {', '.join(valid)}")
    return MeasureOptions(**options)


@dataclass(frozen=True)
class Measurement:
    """One polarization heading measurement (CONVENTIONS.md).

    Attributes
    ----------
    ok : bool
        False when the image was refused; then every number is NaN.
    reason : str
        Why it was refused ("" when ok).
    method : str
    yaw : float
        ENU yaw of body x [rad], counter-clockwise from East, in (-pi, pi].
    yaw_std : float
        1-sigma for a filter [rad]: ``sqrt(kappa^2 yaw_std_meas^2 + floor^2 + cot^2 Z tilt^2)``.
    yaw_std_meas : float
        Un-inflated measurement sigma [rad] (Gauss-Newton or eigen-gap sandwich).
    heading_deg : float
        Compass heading of body x [deg], clockwise from North, in [0, 360).
    sun_b, sun_l, sun_c : (3,)
        Unit sun vector in the body, level and camera frames.
    sun_std : float
        1-sigma of the sun direction along the azimuth [rad], inflated like yaw_std (without
        the tilt term, which belongs in the filter's Jacobian for a vector measurement):
        ``sqrt(kappa^2 (sin Z yaw_std_meas)^2 + (sin Z floor)^2)``. With ``fixed_zenith`` the
        elevation of sun_b comes from the ephemeris and the prior tilt, not from the image.
    epsilon, epsilon_std : float
        Direct-sunlight coefficient and its sigma ("compensated"; "paper": median per-pixel
        k_m / 4 without a sigma; "traditional": NaN).
    n_pixels : int
        Valid pixels used.
    eigen_gap : float
        Normalised eigen-gap of the eigen solution (SPEC 10.1).
    residual_rms : float
        RMS of the normalised AoP-orthogonal residual ``n_i . L_i / sigma_L`` (about 1 when
        the sky model and the camera noise model hold; much larger for a wrong calibration).
    noise_std_est : float
        Per-channel noise [DN] estimated from the redundancy residual (SPEC 7.3).
    """

    ok: bool
    reason: str
    method: str
    yaw: float
    yaw_std: float
    yaw_std_meas: float
    heading_deg: float
    sun_b: FloatArray
    sun_l: FloatArray
    sun_c: FloatArray
    sun_std: float
    epsilon: float
    epsilon_std: float
    n_pixels: int
    eigen_gap: float
    residual_rms: float
    noise_std_est: float = float("nan")

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict (vectors as lists, NaN as None)."""

        def clean(v: Any) -> Any:
            if isinstance(v, np.ndarray):
                return [clean(x) for x in v.tolist()]
            if isinstance(v, float | np.floating):
                return None if not np.isfinite(v) else float(v)
            if isinstance(v, np.integer | np.bool_):
                return v.item()
            return v

        return {f.name: clean(getattr(self, f.name)) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class MeasurementMaps:
    """Per-superpixel images of one measurement, ``(Hs, Ws)`` (NaN outside the field of view).

    aop [rad], dop [-], valid (pixels used), residual (normalised residual at the estimate,
    NaN where not used), unpolarized [DN].
    """

    aop: FloatArray
    dop: FloatArray
    valid: NDArray[np.bool_]
    residual: FloatArray


# ----------------------------------------------------------------------------- camera cache
@dataclass(frozen=True, eq=False)
class _CameraCache:
    """Per-camera constants of the field-of-view pixel set, component-first."""

    pixels: PixelSet
    rays: NDArray  # (3, n)
    basis: NDArray  # (3, 2, n) inverse lens basis
    forward: NDArray  # (3, 2n) packed forward rows [q1 | q2]
    projection: bool

    @property
    def lens_rays(self) -> NDArray | None:
        """Rays for the ML's closed-form forward model (projection lens model only)."""
        return self.rays if self.projection else None


@lru_cache(maxsize=8)
def _camera_cache64(cam: CameraModel) -> _CameraCache:
    pixels = pixel_set(cam)
    rays = np.ascontiguousarray(pixel_rays_c(cam).reshape(-1, 3)[pixels.index].T)
    basis = _lens_basis_rows(rays, cam.polarization_model)
    forward = _pack_forward(_lens_forward_rows(rays, cam.polarization_model), np.float64)
    return _CameraCache(pixels, rays, basis, forward, cam.polarization_model == "projection")


@lru_cache(maxsize=8)
def _camera_cache32(cam: CameraModel) -> _CameraCache:
    c = _camera_cache64(cam)
    return _CameraCache(
        c.pixels,
        np.ascontiguousarray(c.rays, dtype=np.float32),
        np.ascontiguousarray(c.basis, dtype=np.float32),
        np.ascontiguousarray(c.forward, dtype=np.float32),
        c.projection,
    )


def _camera_cache(cam: CameraModel, dtype: type) -> _CameraCache:
    """Per-camera pixel set, rays and lens constants, cached (float32 or float64)."""
    return _camera_cache32(cam) if dtype == np.float32 else _camera_cache64(cam)


@dataclass(frozen=True, eq=False)
class _Subsample:
    """Every ``stride``-th pixel of the field-of-view set, with its lens constants."""

    index: NDArray  # positions in the field-of-view set
    rays: NDArray
    basis: NDArray
    forward: NDArray  # packed
    projection: bool

    @property
    def lens_rays(self) -> NDArray | None:
        return self.rays if self.projection else None


@lru_cache(maxsize=16)
def _subsample(cam: CameraModel, dtype_name: str, stride: int) -> _Subsample:
    c = _camera_cache(cam, np.dtype(dtype_name).type)
    idx = np.arange(0, c.pixels.size, stride)
    n = c.pixels.size
    fwd = np.concatenate([c.forward[:, idx], c.forward[:, n + idx]], axis=1)
    return _Subsample(
        idx,
        np.ascontiguousarray(c.rays[:, idx]),
        np.ascontiguousarray(c.basis[..., idx]),
        np.ascontiguousarray(fwd),
        c.projection,
    )


# ----------------------------------------------------------------------------- helpers
_NAN3 = np.full(3, np.nan)


def _refused(method: str, reason: str, n_pixels: int = 0) -> Measurement:
    return Measurement(
        ok=False,
        reason=reason,
        method=method,
        yaw=np.nan,
        yaw_std=np.nan,
        yaw_std_meas=np.nan,
        heading_deg=np.nan,
        sun_b=_NAN3.copy(),
        sun_l=_NAN3.copy(),
        sun_c=_NAN3.copy(),
        sun_std=np.nan,
        epsilon=np.nan,
        epsilon_std=np.nan,
        n_pixels=n_pixels,
        eigen_gap=np.nan,
        residual_rms=np.nan,
    )


def _check_sun_and_prior(sun_n: ArrayLike, rot_nb_prior: Rotation) -> FloatArray:
    s = np.asarray(sun_n, dtype=float)
    if s.shape != (3,) or not np.all(np.isfinite(s)) or not np.linalg.norm(s) > 0:
        raise ValueError(f"sun_n must be a finite (3,) ENU vector, got {s!r}")
    if not isinstance(rot_nb_prior, Rotation) or not rot_nb_prior.single:
        raise ValueError("rot_nb_prior must be a single scipy Rotation (body -> ENU)")
    return s / np.linalg.norm(s)


def _eigen(
    s1: NDArray,
    s2: NDArray,
    inv_sigma2: NDArray | float,
    basis: NDArray,
    projection: bool,
    mat_lc: NDArray,
    weighted: bool,
    mask: NDArray | None = None,
) -> tuple[EigenSolution, NDArray, NDArray]:
    """Level-frame eigen solution (SPEC 9.1); also the unnormalised camera-frame E-vectors
    and their weights ``omega = w/|e|^2`` (0 for masked pixels), in float64.

    The moment matrix is summed in float64: its smallest eigenvalue is ~0, and float32
    accumulation over 4e5 pixels would move the eigenvector by ~1e-5 rad."""
    e = _evector_rows(s1, s2, basis, projection)
    norm2 = e[0] * e[0]
    norm2 += e[1] * e[1]
    norm2 += e[2] * e[2]
    norm2 += e.dtype.type(1e-30)  # sanitised invalid pixels have e = 0
    omega = (s1 * s1 + s2 * s2) * inv_sigma2 / norm2 if weighted else 1.0 / norm2
    if mask is not None:
        omega *= mask
    n = int(np.count_nonzero(omega))
    e = e.astype(np.float64, copy=False)
    omega = omega.astype(np.float64, copy=False)
    moment_c = _moment(e, omega)
    sol = _eigen_from_moment(mat_lc @ moment_c @ mat_lc.T, _dot(omega, norm2), n)
    return sol, e, omega


def _frames(rot_nb: Rotation, cam: CameraModel) -> tuple[float, NDArray, NDArray, NDArray]:
    """Prior yaw [rad] and the matrices ``mat_lb`` (body -> level), ``mat_cl`` (level ->
    camera) and ``mat_cn`` (ENU -> camera); ``rot_nb = Rz(yaw) rot_lb`` (SPEC 2)."""
    yaw = float(yaw_from_rot_nb(rot_nb))
    c, s = np.cos(yaw), np.sin(yaw)
    mat_nl = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    mat_nb = rot_nb.as_matrix()
    mat_lb = mat_nl.T @ mat_nb
    return yaw, mat_lb, (mat_lb @ cam.mat_bc).T, (mat_nb @ cam.mat_bc).T


def _sigma_scaled(r: NDArray, data: _MLData) -> NDArray:
    """Residuals divided by a common sigma_L (per-pixel sigma is applied by the evaluation)."""
    return r if isinstance(data.inv_sigma, np.ndarray) else r * r.dtype.type(data.inv_sigma)


def _excluded_sun(sun_c: NDArray, rays: NDArray, cos_excl: float) -> NDArray:
    return _dot_rows(sun_c.astype(rays.dtype), rays) > cos_excl


# ----------------------------------------------------------------------------- measure
def measure(
    raw: ArrayLike,
    cam: CameraModel,
    *,
    sun_n: ArrayLike,
    rot_nb_prior: Rotation,
    method: str = "compensated",
    **options: Any,
) -> Measurement:
    """Heading and sun vector from one raw DoFP image (SPEC 7-10).

    Parameters
    ----------
    raw : array_like, (H, W)
        Full-resolution raw mosaic of shape ``cam.shape``, unsigned integer (float mosaics are
        accepted too; their non-finite pixels are masked). Integer mosaics are processed in
        float32, float mosaics in float64.
    cam : CameraModel
    sun_n : array_like, (3,)
        Unit ENU sun vector from the ephemeris (apparent position).
    rot_nb_prior : Rotation
        Prior body -> ENU attitude. Its roll and pitch rotate the E-vectors into the level
        frame; its yaw is used only near the horizon (180 deg choice), by ``yaw_gate`` and by
        ``method="paper"`` (which needs it for the sunlight angle).
    method : {"compensated", "traditional", "paper"}
    **options
        Fields of :class:`MeasureOptions`.

    Returns
    -------
    Measurement
        ``ok=False`` with a reason when the image cannot give a heading.

    Raises
    ------
    ValueError
        Wrong image shape or dtype, bad ``sun_n`` or ``rot_nb_prior``, unknown method.
    TypeError
        Unknown option.
    """
    return _measure(raw, cam, sun_n, rot_nb_prior, method, _options(options), maps=False)[0]


def measure_with_maps(
    raw: ArrayLike,
    cam: CameraModel,
    *,
    sun_n: ArrayLike,
    rot_nb_prior: Rotation,
    method: str = "compensated",
    **options: Any,
) -> tuple[Measurement, MeasurementMaps | None]:
    """:func:`measure` plus per-pixel images (AoP, DoP, valid mask, residual) for plots and
    diagnostics; slower. The maps are None when the image was refused before the Stokes step.
    """
    return _measure(raw, cam, sun_n, rot_nb_prior, method, _options(options), maps=True)


def _measure(
    raw: ArrayLike,
    cam: CameraModel,
    sun_n: ArrayLike,
    rot_nb_prior: Rotation,
    method: str,
    opt: MeasureOptions,
    *,
    maps: bool,
) -> tuple[Measurement, MeasurementMaps | None]:
    arr = check_raw(raw, cam)
    if method not in METHODS:
        raise ValueError(f"method={method!r}: expected one of {METHODS}")
    s_n = _check_sun_and_prior(sun_n, rot_nb_prior)

    # Frames: l is level with x_l the horizontal projection of body x (CONVENTIONS.md).
    yaw_prior, mat_lb, mat_cl, mat_cn = _frames(rot_nb_prior, cam)
    mat_lc = mat_cl.T
    zenith = float(np.arccos(np.clip(s_n[2], -1.0, 1.0)))
    if s_n[2] <= 0.0:
        return _refused(method, "sun below the horizon"), None
    if zenith < np.radians(opt.zenith_min_deg):
        reason = f"sun within {opt.zenith_min_deg:g} deg of the zenith: heading unobservable"
        return _refused(method, reason), None

    # Stokes of the field-of-view pixels and the sun-independent quality masks (SPEC 7).
    # Precision follows the input: integer mosaics (quantised to 1 DN) in float32, whose
    # rounding is 4 orders below the quantisation noise; float mosaics in float64.
    dtype = np.float64 if np.issubdtype(arr.dtype, np.floating) else np.float32
    cache = _camera_cache(cam, dtype)
    channels = _gather(arr, cache.pixels, dtype)
    cal = stokes_calibration(cam, opt.gain_correction)
    rows = _stokes_rows(channels, cal, dtype)
    sigma2 = stokes_noise_variance(cam, rows[0])
    valid = _valid_rows(
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
    cos_excl = float(np.cos(np.radians(opt.sun_exclusion_deg)))
    k_m = None
    if method == "paper":
        est_rows, k_m = _paper_rows(
            channels,
            cam,
            sun_c_prior,
            eq22=opt.paper_eq22,
            kc=opt.paper_kc,
            gain_final=opt.paper_gain_final,
            eq14=opt.paper_eq14,
        )
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
    sub = _subsample(cam, np.dtype(dtype).name, stride)
    rows_sub = est_rows.take(sub.index, axis=1)
    valid_sub = valid[sub.index]
    s0d, s1d, s2d = rows_sub
    keep = valid_sub & ~_excluded_sun(sun_c_prior, sub.rays, cos_excl)
    p2 = s1d * s1d + s2d * s2d
    keep &= p2 >= opt.dop_min**2 * (s0d * s0d)
    keep &= p2 >= opt.snr_min**2 / inv_sigma2_at(sub.index)
    if np.count_nonzero(keep) * stride < opt.min_pixels:
        n_est = int(np.count_nonzero(keep)) * stride
        return _refused(method, f"too few valid pixels ({n_est} < {opt.min_pixels})", n_est), None
    eig0, _, _ = _eigen(
        s1d,
        s2d,
        inv_sigma2_at(sub.index),
        sub.basis,
        cache.projection,
        mat_lc,
        opt.weighted,
        mask=keep,
    )
    sun_l0 = _resolve_sign(eig0.sun, s_n, yaw_prior, opt.horizon_fallback_deg)

    # 2. Subsample selection with this sun; the DoP cut along the predicted direction.
    sel_sub = _Selection(
        valid_sub, sub.rays, cos_excl, opt.dop_min, opt.snr_min / inv_sigma_at(sub.index)
    )
    fixed = opt.fixed_zenith and method == "compensated"
    zen_arg = zenith if fixed else None
    a0 = float(np.arctan2(sun_l0[1], sun_l0[0]))
    z0 = float(np.arccos(np.clip(sun_l0[2], -1.0, 1.0)))
    theta = np.array([a0, opt.epsilon0] if fixed else [a0, z0, opt.epsilon0])
    data_sub = _ml_data(
        rows_sub[0],
        rows_sub[1],
        rows_sub[2],
        sub.forward,
        inv_sigma_at(sub.index),
        packed=True,
        rays=sub.lens_rays,
    )
    full_select = _Selection(
        valid, cache.rays, cos_excl, opt.dop_min, opt.snr_min / inv_sigma_at(None)
    )
    data_full = _ml_data(
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
            ml, _ = _gauss_newton(
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
                return _refused(method, "joint ML did not converge", ml.n * stride), None
            theta = ml.theta
        # 3. One Gauss-Newton step on all valid pixels (iterate if there is no subsample).
        ml, mask = _gauss_newton(
            data_full,
            theta,
            zen_arg,
            mat_cl,
            loss=opt.loss,
            max_iterations=1 if stride > 1 else opt.max_iterations,
            select=full_select,
        )
        if stride == 1 and not ml.converged:
            return _refused(method, "joint ML did not converge", ml.n), None
        assert mask is not None
        theta = ml.theta
        sun_l = ml.sun_l
        var_yaw = float(ml.covariance[0, 0])
        epsilon, epsilon_std = float(theta[-1]), float(np.sqrt(ml.covariance[-1, -1]))
        residual_rms = ml.residual_rms
    else:
        # 3. Eigen solution on all valid pixels, selected with the starting sun.
        mask = _selection_mask(data_full, full_select, mat_cl @ sun_l0)
        eig, e, omega = _eigen(
            est_rows[1],
            est_rows[2],
            inv_sigma_l2,
            cache.basis,
            cache.projection,
            mat_lc,
            opt.weighted,
            mask=mask,
        )
        sun_l = _resolve_sign(eig.sun, s_n, yaw_prior, opt.horizon_fallback_deg)
        gap = eigen_gap(eig)
        middle = _sandwich_middle(e, omega, mat_cl @ sun_l)
        var_yaw = yaw_variance_from_sun_covariance(
            sun_l, _sandwich(eig, mat_lc @ middle @ mat_lc.T)
        )
        theta = np.array([np.arctan2(sun_l[1], sun_l[0]), np.arccos(np.clip(sun_l[2], -1, 1)), 0.0])
        zen_arg = None
        epsilon, epsilon_std = float("nan"), float("nan")
        if k_m is not None:
            epsilon = float(np.nanmedian(k_m[mask])) / 4.0
        r_sub, _, _, _ = _ml_evaluate(
            dataclasses.replace(data_sub, mask=valid_sub), theta, None, mat_cl, False
        )
        r_sub = _sigma_scaled(r_sub, data_sub)
        n_sub = max(int(np.count_nonzero(valid_sub)), 1)
        residual_rms = float(np.sqrt(_dot(r_sub, r_sub) / n_sub))

    n_pixels = int(np.count_nonzero(mask))
    if n_pixels < opt.min_pixels:
        return _refused(
            method, f"too few valid pixels ({n_pixels} < {opt.min_pixels})", n_pixels
        ), None
    nu = rows[3] * mask
    noise_std_est = float(np.sqrt(_dot(nu, nu) / n_pixels))
    yaw = yaw_from_sun_level(sun_l, s_n)
    mapped = _maps(cache, est_rows, mask, data_full, theta, zen_arg, mat_cl) if maps else None

    if not gap >= opt.eigen_gap_min:
        return _refused(method, f"eigen-gap {gap:.3f} below {opt.eigen_gap_min}", n_pixels), mapped
    if opt.yaw_gate is not None and abs(float(wrap_angle(yaw - yaw_prior))) > opt.yaw_gate:
        return _refused(method, "heading outside the gate around the prior yaw", n_pixels), mapped
    if opt.residual_rms_max is not None and not residual_rms <= opt.residual_rms_max:
        reason = f"residual RMS {residual_rms:.3g} above {opt.residual_rms_max:g}"
        return _refused(method, reason, n_pixels), mapped
    if not np.isfinite(var_yaw) or var_yaw < 0:
        return _refused(method, "singular covariance", n_pixels), mapped

    std_meas = float(np.sqrt(var_yaw))
    floor = np.radians(opt.sigma_floor_deg)
    sin_z, cot_z = np.sin(zenith), np.cos(zenith) / np.sin(zenith)
    yaw_std = float(np.sqrt((opt.kappa * std_meas) ** 2 + floor**2 + (cot_z * opt.tilt_std) ** 2))
    sun_std = float(np.sqrt((opt.kappa * sin_z * std_meas) ** 2 + (sin_z * floor) ** 2))
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


def _resolve_sign(sun_l: NDArray, sun_n: NDArray, yaw_prior: float, fallback_deg: float) -> NDArray:
    """SPEC 10.1: the sun is above the horizon (s_l_z > 0); within ``fallback_deg`` of the
    horizon the prior yaw chooses between s and -s (yaw and yaw + 180 deg)."""
    s = sun_l if sun_l[2] >= 0 else -sun_l
    if s[2] < np.sin(np.radians(fallback_deg)):
        err = abs(float(wrap_angle(yaw_from_sun_level(s, sun_n) - yaw_prior)))
        err_flip = abs(float(wrap_angle(yaw_from_sun_level(-s, sun_n) - yaw_prior)))
        if err_flip < err:
            s = -s
    return np.asarray(s, dtype=float)


def _maps(
    cache: _CameraCache,
    est_rows: NDArray,
    mask: NDArray,
    data: _MLData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
) -> MeasurementMaps:
    s0, s1, s2 = (r.astype(np.float64) for r in est_rows)
    with np.errstate(invalid="ignore", divide="ignore"):
        dop_v = np.hypot(s1, s2) / s0
    r, _, _, _ = _ml_evaluate(dataclasses.replace(data, mask=mask), theta, zenith, mat_cl, False)
    r = _sigma_scaled(r, data)
    residual = np.where(mask, r, np.nan)
    px = cache.pixels
    return MeasurementMaps(
        aop=px.to_image(0.5 * np.arctan2(s2, s1)),
        dop=px.to_image(dop_v),
        valid=px.to_image(mask, fill=0.0).astype(bool),
        residual=px.to_image(residual),
    )


# ----------------------------------------------------------------------------- CRLB
def yaw_crlb(
    cam: CameraModel,
    sun_n: ArrayLike,
    rot_nb: Rotation,
    *,
    dop_max: float,
    radiance: float,
    noise_std: float,
    epsilon: float = 0.0,
    pixel_mask: ArrayLike | None = None,
    fixed_zenith: bool = True,
    sun_exclusion_deg: float = 10.0,
    dop_min: float = 0.03,
    snr_min: float = 3.0,
) -> float:
    """Cramer-Rao lower bound of the yaw [rad] for a clear Rayleigh sky (AUDIT section 5).

    Per pixel ``L_i = p_i r(zeta_i(theta)) + eps u_i w(theta) + n_i``, ``n_i ~ N(0, sigma_L^2 I)``
    with ``sigma_L = noise_std * sigma_l_factor`` (ideal sqrt(2) sigma); the polarized
    intensities p_i are nuisance parameters, so only the component along
    ``n_i = (-sin 2zeta_i, cos 2zeta_i)`` informs theta = (A_l[, Z_l], eps)::

        F = sum_i g_i g_i^T / sigma_L^2,   g_i = d(n_i . m_i)/d theta,   CRLB(yaw) = sqrt([F^-1]_AA)

    Parameters
    ----------
    sun_n : (3,) ENU sun. rot_nb : true body -> ENU attitude.
    dop_max, radiance : Rayleigh sky (SPEC 6.1, constant radiance [DN]).
    noise_std : per-channel Gaussian noise [DN].
    epsilon : direct-sunlight coefficient (always estimated).
    pixel_mask : (Hs, Ws) bool, optional
        Pixels used; default the field of view, ``sun_exclusion_deg``, ``DoP >= dop_min`` and
        polarized intensity ``>= snr_min sigma_L`` (the estimator's masks on a noise-free
        image).
    fixed_zenith : bool
        Zenith known (the default estimator) or estimated as well.
    """
    s_n = _check_sun_and_prior(sun_n, rot_nb)
    cache = _camera_cache(cam, np.float64)
    rays = pixel_rays_c(cam).reshape(-1, 3)[cache.pixels.index]
    rot_lb = rot_lb_from_rot_nb(rot_nb)
    mat_cl = (rot_lb * cam.rot_bc).inv().as_matrix()
    sun_l = Rotation.from_euler("Z", -yaw_from_rot_nb(rot_nb)).apply(s_n)
    sun_c = mat_cl @ sun_l
    cos_t = rays @ sun_c
    dop_v = dop_max * (1 - cos_t**2) / (1 + cos_t**2)
    sigma_l = noise_std * stokes_calibration(cam).sigma_l_factor
    if pixel_mask is None:
        use = (cos_t <= np.cos(np.radians(sun_exclusion_deg))) & (dop_v >= dop_min)
        use &= radiance * dop_v >= snr_min * sigma_l
    else:
        mask = np.asarray(pixel_mask, dtype=bool)
        if mask.shape != cam.superpixel_shape:
            raise ValueError(f"pixel_mask must have shape {cam.superpixel_shape}")
        use = mask.reshape(-1)[cache.pixels.index]
    forward = _lens_forward_rows(np.ascontiguousarray(rays[use].T), cam.polarization_model)
    xy = np.einsum("jkn,k->jn", forward, sun_c)
    e2 = xy[0] ** 2 + xy[1] ** 2
    p = radiance * dop_v[use]
    stokes_sky = np.stack(
        [
            np.full(p.shape, radiance),
            p * (xy[0] ** 2 - xy[1] ** 2) / e2,
            p * 2 * xy[0] * xy[1] / e2,
        ],
        -1,
    )
    stokes = sunlight_stokes(stokes_sky, epsilon, sunlight_direction(sun_c))
    data = _ml_data(stokes[:, 0], stokes[:, 1], stokes[:, 2], forward, 1.0)
    a_l, z_l = np.arctan2(sun_l[1], sun_l[0]), np.arccos(np.clip(sun_l[2], -1, 1))
    theta = np.array([a_l, epsilon] if fixed_zenith else [a_l, z_l, epsilon])
    _, jac, _, _ = _ml_evaluate(data, theta, z_l if fixed_zenith else None, mat_cl, True)
    assert jac is not None
    fisher = jac @ jac.T / sigma_l**2
    return float(np.sqrt(np.linalg.inv(fisher)[0, 0]))
