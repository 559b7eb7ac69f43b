"""Raw DoFP sky images: the sensor model of docs/model.md §6.2 rendered into a mosaic.

:func:`render_raw` turns a sun vector and an attitude into the full-resolution raw mosaic a
division-of-focal-plane camera (``polins.models.CameraModel``) would deliver:

1. every sample point (the superpixel centre, or with ``ifov=True`` each channel's own
   full-resolution pixel) is back-projected to a camera ray (``polins.compass.camera``) and rotated
   to ENU with ``rot_nb`` and the camera's mount ``mat_bc``;
2. the scene Stokes vector there: a Rayleigh or Berry sky (``polins.sky.scattering``) with constant or
   Rayleigh ``1 + cos^2`` radiance, optional depolarizing cloud patches, world-fixed
   occluders (tree lines, buildings) and the ground below the horizon, unpolarized and dark;
   the sky E-vector goes to the image-plane AoP through the camera's lens polarization
   model (``polins.compass.camera.doubled_aop_from_evector``);
3. the paper's direct-sunlight term in Stokes form (docs/model.md §6.2), ``dS0 = -eps u``,
   ``dL = eps u w``, ``w = -(cos 2 alpha_s^c, sin 2 alpha_s^c)``, with ``alpha_s^c`` the sun's
   camera-frame azimuth and ``u`` the pixel's unpolarized intensity (off when the sun is
   occluded or below the horizon);
4. the channel response ``I_k = g_k 1/2 [S0 + eta_k (S1 cos 2 alpha_k + S2 sin 2 alpha_k)] + o_k``
   (docs/model.md §6.2) with the camera model's gains, efficiencies, transmission angles and dark
   offsets (per pixel where the camera has maps), placed at the mosaic positions of
   ``cam.channel_at``;
5. Poisson shot noise (optional, ``cam.conversion_gain_e_per_dn``) and Gaussian read noise,
   a saturated sun disc, rounding to integer DN and clipping to ``[0, cam.saturation_dn]``.

Azimuths of occluders and clouds are compass azimuths (clockwise from North, like the solar
azimuth of ``polins.sky.ephemeris``); elevations are above the horizon. All in degrees, as the
``_deg`` names say.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.compass.camera import doubled_aop_from_evector, pixel_rays_c, superpixel_uv, unproject
from polins.models import CameraModel
from polins.sky.scattering import berry_dop, berry_evector, rayleigh_dop, rayleigh_evector

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

SKY_MODELS = ("rayleigh", "berry")
RADIANCE_MODELS = ("constant", "rayleigh")


@dataclass(frozen=True)
class CloudPatch:
    """A round cloud patch fixed in the sky, which brightens and depolarizes skylight.

    Attributes
    ----------
    azimuth_deg, elevation_deg : float
        Centre [deg]: compass azimuth (clockwise from North) and elevation.
    radius_deg : float
        Angular radius [deg].
    depolarization : float
        Fraction of the sky's degree of polarization removed at the centre, in [0, 1].
    brightness : float
        Radiance multiplier at the centre (> 0; clouds are usually brighter than blue sky).
    softness : float
        Fraction of the radius over which the edge fades out, in (0, 1].
    """

    azimuth_deg: float
    elevation_deg: float
    radius_deg: float
    depolarization: float = 0.8
    brightness: float = 1.5
    softness: float = 0.3

    def __post_init__(self) -> None:
        if not self.radius_deg > 0:
            raise ValueError(f"CloudPatch radius_deg={self.radius_deg} must be > 0")
        if not 0.0 <= self.depolarization <= 1.0:
            raise ValueError(f"CloudPatch depolarization={self.depolarization} outside [0, 1]")
        if not self.brightness > 0:
            raise ValueError(f"CloudPatch brightness={self.brightness} must be > 0")
        if not 0.0 < self.softness <= 1.0:
            raise ValueError(f"CloudPatch softness={self.softness} outside (0, 1]")


# ----------------------------------------------------------------------------- geometry
def direction_n(azimuth_deg: ArrayLike, elevation_deg: ArrayLike) -> FloatArray:
    """ENU unit vector ``(..., 3)`` of compass azimuth (clockwise from North) and elevation
    [deg]."""
    a = np.radians(np.asarray(azimuth_deg, dtype=float))
    e = np.radians(np.asarray(elevation_deg, dtype=float))
    return np.stack(
        np.broadcast_arrays(np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)), -1
    )


def azimuth_elevation_deg(dir_n: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Compass azimuth in [0, 360) and elevation [deg] of ENU vectors ``(..., 3)``."""
    d = np.asarray(dir_n, dtype=float)
    az = np.mod(np.degrees(np.arctan2(d[..., 0], d[..., 1])), 360.0)
    el = np.degrees(np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1])))
    return az, el


def azimuth_band(
    azimuth_from_deg: float,
    azimuth_to_deg: float,
    elevation_max_deg: float,
    elevation_min_deg: float = -90.0,
) -> FloatArray:
    """Occluder polygon ``(4, 2)`` [deg] covering compass azimuths from ``azimuth_from_deg``
    clockwise to ``azimuth_to_deg`` and elevations below ``elevation_max_deg`` (a tree line,
    a building front)."""
    span = np.mod(azimuth_to_deg - azimuth_from_deg, 360.0)
    if not 0.0 < span < 360.0:
        raise ValueError("azimuth_band needs two different azimuths")
    a0, a1 = azimuth_from_deg, azimuth_from_deg + span
    return np.array(
        [
            [a0, elevation_min_deg],
            [a1, elevation_min_deg],
            [a1, elevation_max_deg],
            [a0, elevation_max_deg],
        ]
    )


def occluded(dir_n: ArrayLike, polygons: Sequence[ArrayLike]) -> BoolArray:
    """Which ENU directions ``(..., 3)`` fall inside any occluder polygon.

    Parameters
    ----------
    dir_n : array_like, (..., 3)
        Directions in ENU.
    polygons : sequence of array_like, each (K, 2)
        Vertices ``[azimuth_deg, elevation_deg]`` (compass azimuth, clockwise from North),
        K >= 3, traversed in order (azimuths may run past 360; a polygon may span less
        than 360 deg of azimuth). Even-odd rule in the (azimuth, elevation) plane.
    """
    d = np.asarray(dir_n, dtype=float)
    inside = np.zeros(d.shape[:-1], dtype=bool)
    if not len(polygons):
        return inside
    az, el = azimuth_elevation_deg(d)
    for poly in polygons:
        v = np.asarray(poly, dtype=float)
        if v.ndim != 2 or v.shape[1] != 2 or v.shape[0] < 3:
            raise ValueError(
                f"occluder polygon must be (K >= 3, 2) [azimuth_deg, elevation_deg], got {v.shape}"
            )
        va = np.degrees(np.unwrap(np.radians(v[:, 0])))
        if np.ptp(va) >= 360.0:
            raise ValueError("an occluder polygon must span less than 360 deg of azimuth")
        # Pixel azimuths unwrapped into [centre - 180, centre + 180).
        centre = 0.5 * (va.min() + va.max())
        x = centre + np.mod(az - centre + 180.0, 360.0) - 180.0
        y = el
        xv, yv = va, v[:, 1]
        hit = np.zeros_like(inside)
        for i in range(len(xv)):  # loop over edges, vectorised over pixels
            x0, y0, x1, y1 = xv[i - 1], yv[i - 1], xv[i], yv[i]
            if y0 == y1:
                continue
            crosses = (y0 > y) != (y1 > y)
            x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
            hit ^= crosses & (x < x_at)
        inside |= hit
    return inside


def cloud_cover(dir_n: ArrayLike, clouds: Sequence[CloudPatch]) -> FloatArray:
    """DoP and radiance factors of cloud patches at ENU directions ``(..., 3)``.

    Each cloud has a weight in [0, 1] per direction (1 inside its core, a smoothstep to 0
    over the soft edge); overlapping clouds take the strongest effect.

    Returns
    -------
    ndarray, (2, ...)
        Factor on the DoP (``1 - depolarization * weight``) and on the radiance
        (``1 + (brightness - 1) * weight``) per direction.
    """
    d = np.asarray(dir_n, dtype=float)
    dop_factor = np.ones(d.shape[:-1])
    rad_factor = np.ones(d.shape[:-1])
    for cloud in clouds:
        centre = direction_n(cloud.azimuth_deg, cloud.elevation_deg)
        ang = np.degrees(np.arccos(np.clip(d @ centre, -1.0, 1.0)))
        edge = cloud.radius_deg * cloud.softness
        t = np.clip((cloud.radius_deg - ang) / edge, 0.0, 1.0)
        weight = t * t * (3.0 - 2.0 * t)  # smoothstep
        dop_factor = np.minimum(dop_factor, 1.0 - cloud.depolarization * weight)
        rad_factor = np.maximum(rad_factor, 1.0 + (cloud.brightness - 1.0) * weight)
    return np.stack([dop_factor, rad_factor])


@lru_cache(maxsize=8)
def mosaic_rays_c(cam: CameraModel, row: int, col: int) -> FloatArray:
    """Camera rays ``(Hs, Ws, 3)`` of the full-resolution pixels at mosaic position
    ``(row % 2, col % 2) = (row, col)``; cached per camera.

    Full-resolution pixel (r, c) sits at superpixel coordinates ``((c - 0.5)/2, (r - 0.5)/2)``
    (docs/model.md §5: ``c_full = 2 c + 0.5``), so the four channels of superpixel (i, j) look a
    quarter superpixel off its centre in u and v.
    """
    if row not in (0, 1) or col not in (0, 1):
        raise ValueError(f"mosaic position must be 0 or 1, got ({row}, {col})")
    uv = superpixel_uv(cam) + np.array([(col - 0.5) / 2.0, (row - 0.5) / 2.0])
    rays = unproject(cam, uv)
    rays.setflags(write=False)
    return rays


# ----------------------------------------------------------------------------- radiometry
def sky_stokes(
    rays_c: FloatArray,
    mat_nc: FloatArray,
    sun_n: FloatArray,
    *,
    polarization_model: str,
    dop_max: float,
    radiance: float,
    sky: str = "rayleigh",
    neutral_sep: float = np.radians(35.0),
    radiance_model: str = "constant",
    occluders: Sequence[ArrayLike] = (),
    ground_radiance: float = 40.0,
    clouds: Sequence[CloudPatch] = (),
) -> tuple[FloatArray, BoolArray]:
    """Scene Stokes vector ``(..., 3)`` [DN] in the image-plane convention at camera rays.

    Sky pixels: ``S0 = R``, ``(S1, S2) = R d (cos 2 zeta, sin 2 zeta)`` (docs/model.md
    §6.1/§6.2) with the sky model's E-vector taken to the image plane by the lens polarization
    model. Occluded pixels and the ground below the horizon: unpolarized ``ground_radiance``.
    NaN rays (outside the lens' image circle): zero. Returns the Stokes array and the "blocked"
    mask (ground or occluder).
    """
    valid = np.isfinite(rays_c[..., 2])  # unproject gives all-NaN rays outside the lens
    rays_n = rays_c @ mat_nc.T
    if sky == "rayleigh":
        evec_n = rayleigh_evector(sun_n, rays_n)
        dop = rayleigh_dop(sun_n, rays_n, dop_max)
    elif sky == "berry":
        evec_n = berry_evector(sun_n, rays_n, neutral_sep)
        dop = berry_dop(sun_n, rays_n, dop_max, neutral_sep)
    else:
        raise ValueError(f"unknown sky model {sky!r}: expected one of {SKY_MODELS}")
    if radiance_model == "constant":
        rad = np.full(dop.shape, float(radiance))
    elif radiance_model == "rayleigh":
        cos_t = rays_n @ sun_n
        rad = radiance * (1.0 + cos_t * cos_t)
    else:
        raise ValueError(
            f"unknown radiance model {radiance_model!r}: expected one of {RADIANCE_MODELS}"
        )
    if clouds:
        dop_factor, rad_factor = cloud_cover(rays_n, clouds)
        dop = dop * dop_factor
        rad = rad * rad_factor
    evec_c = evec_n @ mat_nc  # = (mat_nc^T e_n^T)^T: ENU -> camera
    with np.errstate(invalid="ignore", divide="ignore"):
        aop2 = doubled_aop_from_evector(evec_c, rays_c, polarization_model)
    aop2 = np.where(np.isfinite(aop2), aop2, 0.0)  # undefined only where d = 0 (sun, neutral pts)
    blocked = ((rays_n[..., 2] < 0.0) | occluded(rays_n, occluders)) & valid
    s0 = np.where(blocked, ground_radiance, np.where(valid, rad, 0.0))
    pol = np.where(blocked | ~valid, 0.0, rad * dop)
    stokes = np.stack([s0, pol * aop2[..., 0], pol * aop2[..., 1]], axis=-1)
    return stokes, blocked


def add_direct_sunlight(stokes: FloatArray, sun_c: FloatArray, epsilon: float) -> FloatArray:
    """Add the direct-sunlight pseudo-polarization of docs/model.md §6.2 (paper Eqs. 8/12 in
    Stokes form) to scene Stokes vectors ``(..., 3)`` [DN].

    Written independently of the estimator's forward model
    (:func:`polins.compass.sunlight.stokes_with_sunlight`) on purpose: the tests compare
    the two, so the renderer must not call the code it checks.

    ``u = S0 - |L|`` (the unpolarized intensity R (1 - d)), ``S0 -= eps u``,
    ``L += eps u w`` with ``w = -(cos 2 alpha_s^c, sin 2 alpha_s^c)``,
    ``alpha_s^c = atan2(s^c_y, s^c_x)`` the sun's azimuth in the camera frame (docs/model.md §3.5).
    """
    if epsilon == 0.0:
        return stokes
    alpha = np.arctan2(sun_c[1], sun_c[0])
    w = -np.array([np.cos(2 * alpha), np.sin(2 * alpha)])
    u = np.maximum(stokes[..., 0] - np.hypot(stokes[..., 1], stokes[..., 2]), 0.0)
    out = stokes.copy()
    out[..., 0] -= epsilon * u
    out[..., 1:] += epsilon * u[..., None] * w
    return out


def channel_intensity(stokes: FloatArray, cam: CameraModel, channel: int) -> FloatArray:
    """Noise-free response [DN] of polarizer channel ``channel`` (docs/model.md §6.2):
    ``g_k 1/2 [S0 + eta_k (S1 cos 2 alpha_k + S2 sin 2 alpha_k)] + o_k``.

    A camera with per-pixel maps (``CameraModel.gain_map``, ``transmission_angle_map``,
    ``efficiency_map``; NaN entries: the channel's value) responds pixel by pixel: then
    ``stokes`` must be a whole superpixel image ``(Hs, Ws, 3)``.
    """
    g: FloatArray | float = cam.gain[channel]
    eta: FloatArray | float = cam.efficiency[channel]
    a: FloatArray | float = cam.transmission_angle[channel]
    if cam.has_pixel_maps:
        if stokes.shape[:-1] != cam.superpixel_shape:
            raise ValueError(
                f"camera {cam.name!r} has per-pixel maps: Stokes must be a superpixel image "
                f"{(*cam.superpixel_shape, 3)}, got {stokes.shape}"
            )
        g, a, eta = (values[..., channel] for values in cam.pixel_calibration())
    return (
        g
        * 0.5
        * (stokes[..., 0] + eta * (stokes[..., 1] * np.cos(2 * a) + stokes[..., 2] * np.sin(2 * a)))
        + cam.dark_offset_dn[channel]
    )


def _check_render_args(
    cam: CameraModel,
    sun_n: ArrayLike,
    rot_nb: Rotation,
    *,
    dop_max: float,
    radiance: float,
    epsilon: float,
    noise_std: float,
    rng: np.random.Generator | None,
    sun_disc_deg: float,
    shot_noise: bool,
) -> FloatArray:
    """Check the arguments of :func:`render_raw`; returns the unit sun vector ``sun_n``."""
    if not isinstance(cam, CameraModel):
        raise TypeError(f"cam must be a polins CameraModel, got {type(cam).__name__}")
    s_n = _unit_sun_n(sun_n)
    if not isinstance(rot_nb, Rotation) or not rot_nb.single:
        raise ValueError("rot_nb must be one scipy Rotation (body -> ENU), not a stack")
    if not 0.0 <= dop_max <= 1.0:
        raise ValueError(f"dop_max={dop_max} outside [0, 1]")
    if not radiance > 0:
        raise ValueError(f"radiance={radiance} must be > 0 [DN]")
    if not 0.0 <= epsilon < 0.5:
        raise ValueError(f"epsilon={epsilon} outside [0, 0.5)")
    if not noise_std >= 0:
        raise ValueError(f"noise_std={noise_std} must be >= 0 [DN]")
    if rng is not None and not isinstance(rng, np.random.Generator):
        raise TypeError(
            "rng must be a numpy.random.Generator (np.random.default_rng(seed)) or None"
        )
    if not sun_disc_deg >= 0:
        raise ValueError(f"sun_disc_deg={sun_disc_deg} must be >= 0")
    if shot_noise and rng is not None and not np.isfinite(cam.conversion_gain_e_per_dn):
        raise ValueError(
            f"shot_noise needs a finite noise.conversion_gain_e_per_dn in camera {cam.name!r}"
        )
    return s_n


def _unit_sun_n(sun_n: ArrayLike) -> FloatArray:
    """``sun_n`` checked (a finite, non-zero ENU 3-vector) and normalised."""
    s_n = np.asarray(sun_n, dtype=float)
    if s_n.shape != (3,) or not np.all(np.isfinite(s_n)) or not np.linalg.norm(s_n) > 0:
        raise ValueError(f"sun_n must be a finite ENU 3-vector, got {sun_n!r}")
    return s_n / np.linalg.norm(s_n)


@dataclass(frozen=True)
class _SkyView:
    """What one camera sees of one sky: the camera attitude ``mat_nc``, the unit sun
    ``sun_n``, the direct-sunlight coefficient ``eps`` (0 when the sun is hidden), the
    cosine of the saturated sun disc's radius (``None``: no disc) and the sky options of
    :func:`sky_stokes`."""

    mat_nc: FloatArray
    sun_n: FloatArray
    eps: float
    cos_disc: float | None
    scene: dict[str, Any]

    def sample(self, rays_c: FloatArray) -> tuple[FloatArray, BoolArray]:
        """Stokes vectors (with direct sunlight) along camera rays, and which rays fall on
        the sun disc."""
        stokes, blocked = sky_stokes(rays_c, self.mat_nc, self.sun_n, **self.scene)
        sun_c = self.mat_nc.T @ self.sun_n
        with np.errstate(invalid="ignore"):
            disc = (
                (rays_c @ sun_c >= self.cos_disc) & ~blocked if self.cos_disc is not None else None
            )
        return add_direct_sunlight(stokes, sun_c, self.eps), (
            disc if disc is not None else np.zeros(blocked.shape, dtype=bool)
        )


def _mosaic_signal(cam: CameraModel, view: _SkyView, ifov: bool) -> tuple[FloatArray, BoolArray]:
    """The noise-free mosaic signal [DN] and its saturated (sun-disc) pixels: each channel
    sampled at the superpixel centre, or with ``ifov`` at its own pixel."""
    h, w = cam.shape
    signal = np.empty((h, w))
    saturated = np.zeros((h, w), dtype=bool)
    if not ifov:
        stokes, disc = view.sample(pixel_rays_c(cam))
    for r0 in (0, 1):
        for c0 in (0, 1):
            if ifov:
                stokes, disc = view.sample(mosaic_rays_c(cam, r0, c0))
            signal[r0::2, c0::2] = channel_intensity(stokes, cam, int(cam.channel_at[r0, c0]))
            saturated[r0::2, c0::2] = disc
    return signal, saturated


def _add_sensor_noise(
    signal: FloatArray,
    cam: CameraModel,
    rng: np.random.Generator,
    noise_std: float,
    shot_noise: bool,
) -> FloatArray:
    """``signal`` [DN] with Poisson photon noise above the dark offset (``shot_noise``),
    then Gaussian read noise of ``noise_std`` [DN]."""
    h, w = cam.shape
    if shot_noise:
        offset = np.empty((h, w))
        for r0 in (0, 1):
            for c0 in (0, 1):
                offset[r0::2, c0::2] = cam.dark_offset_dn[int(cam.channel_at[r0, c0])]
        gain_e = cam.conversion_gain_e_per_dn
        electrons = rng.poisson(np.maximum(signal - offset, 0.0) * gain_e)
        signal = electrons / gain_e + offset
    if noise_std > 0:
        signal = signal + noise_std * rng.standard_normal((h, w))
    return signal


# ----------------------------------------------------------------------------- renderer
def render_raw(
    cam: CameraModel,
    sun_n: ArrayLike,
    rot_nb: Rotation,
    *,
    dop_max: float = 0.75,
    radiance: float = 220.0,
    epsilon: float = 0.0125,
    noise_std: float = 1.5,
    rng: np.random.Generator | None = None,
    sky: str = "rayleigh",
    neutral_sep: float = np.radians(35.0),
    radiance_model: str = "constant",
    polarization_model: str | None = None,
    shot_noise: bool = False,
    occluders: Sequence[ArrayLike] = (),
    ground_radiance: float | None = None,
    clouds: Sequence[CloudPatch] = (),
    sun_disc_deg: float = 2.0,
    ifov: bool = False,
    quantize: bool = True,
) -> NDArray:
    """Render the raw DoFP mosaic of a sky image (docs/model.md §6.2 sensor model).

    Parameters
    ----------
    cam : CameraModel
        Camera (sensor size, mosaic layout ``channel_at``, per-channel gain / efficiency /
        transmission angle / dark offset, or its per-pixel maps of them, lens, mount
        ``mat_bc``, saturation).
    sun_n : array_like, (3,)
        Unit sun vector in ENU (``polins.sun_vector_n``).
    rot_nb : scipy.spatial.transform.Rotation
        Body-to-ENU attitude (one rotation); the camera is ``rot_nb * cam.rot_bc``.
    dop_max : float
        Maximum degree of polarization of the sky (90 deg from the sun), in [0, 1].
    radiance : float
        Sky radiance R [DN] (the paper's I_in = 220); with ``radiance_model="rayleigh"``
        the radiance 90 deg from the sun.
    epsilon : float
        Direct-sunlight coefficient of docs/model.md §6.2 (0.0125 = the paper's k_m = 0.05 in
        Eq. 12).
    noise_std : float
        Gaussian read noise per pixel [DN].
    rng : numpy.random.Generator, optional
        Noise source; ``None`` renders noise-free (``noise_std`` and ``shot_noise`` ignored).
    sky : {"rayleigh", "berry"}
        Sky polarization model (``polins.sky.scattering``).
    neutral_sep : float
        Berry sky: separation [rad] of the Babinet and Brewster points.
    radiance_model : {"constant", "rayleigh"}
        Sky radiance: constant ``radiance`` or ``radiance (1 + cos^2 Theta)``.
    polarization_model : {"projection", "meridian"}, optional
        Lens polarization model; default the camera model's (docs/model.md §6.1).
    shot_noise : bool
        Add Poisson photon noise with ``cam.conversion_gain_e_per_dn`` [e-/DN].
    occluders : sequence of (K, 2) arrays
        World-fixed occluder polygons ``[azimuth_deg, elevation_deg]`` (compass azimuth),
        see :func:`azimuth_band`. The ground below the horizon is always occluded.
    ground_radiance : float, optional
        Unpolarized radiance [DN] of occluders and ground; default ``0.15 * radiance``.
    clouds : sequence of CloudPatch
        Depolarizing, brightening cloud patches fixed in the sky.
    sun_disc_deg : float
        Angular radius [deg] around the sun rendered saturated (sun disc and bloom); 0: none.
    ifov : bool
        Sample each channel at its own full-resolution pixel (the real DoFP
        instantaneous-field-of-view mismatch) instead of all four at the superpixel centre.
    quantize : bool
        Round to integer DN and return ``uint16`` (default); ``False`` returns the clipped
        float64 signal (for tests of the model itself).

    Returns
    -------
    ndarray, (H, W) = cam.shape
        Raw mosaic, ``uint16`` in ``[0, cam.saturation_dn]``.
    """
    s_n = _check_render_args(
        cam, sun_n, rot_nb, dop_max=dop_max, radiance=radiance, epsilon=epsilon,
        noise_std=noise_std, rng=rng, sun_disc_deg=sun_disc_deg, shot_noise=shot_noise,
    )  # fmt: skip
    ground = 0.15 * radiance if ground_radiance is None else float(ground_radiance)
    model = cam.polarization_model if polarization_model is None else polarization_model

    mat_nc = (rot_nb * cam.rot_bc).as_matrix()
    sun_visible = s_n[2] > 0.0 and not occluded(s_n, occluders)
    scene = dict(
        polarization_model=model,
        dop_max=dop_max,
        radiance=radiance,
        sky=sky,
        neutral_sep=neutral_sep,
        radiance_model=radiance_model,
        occluders=occluders,
        ground_radiance=ground,
        clouds=clouds,
    )
    sky_view = _SkyView(
        mat_nc=mat_nc,
        sun_n=s_n,
        eps=epsilon if sun_visible else 0.0,
        cos_disc=np.cos(np.radians(sun_disc_deg)) if sun_visible and sun_disc_deg > 0 else None,
        scene=scene,
    )
    signal, saturated = _mosaic_signal(cam, sky_view, ifov)
    if rng is not None:
        signal = _add_sensor_noise(signal, cam, rng, noise_std, shot_noise)
    signal[saturated] = cam.saturation_dn
    np.clip(signal, 0.0, cam.saturation_dn, out=signal)
    if not quantize:
        return signal
    return np.rint(signal).astype(np.uint16)
