"""Realistic skies and cameras: a raw DoFP renderer that shares no code with the estimator.

The honesty tests of ``polins.measure`` (docs/measurement.md §12) need images that nobody
modelled for the estimator. :func:`render_real_raw` renders them from its own code (it
imports nothing from ``polins.compass``; the rays come from OpenCV and the camera file):

* radiance: the ISO 15469 / CIE S 011 standard general sky (:func:`cie_relative_luminance`),
  ``L/L_z = f(chi) phi(Z) / (f(Z_s) phi(0))`` with the gradation
  ``phi(Z) = 1 + a exp(b / cos Z)`` and the indicatrix
  ``f(chi) = 1 + c (exp(d chi) - exp(d pi/2)) + e cos^2 chi`` (:data:`CIE_SKY_TYPES`);
* polarization: the four-neutral-point sky of Berry, Dennis and Lee (2004)
  (:func:`berry_sky`): Babinet and Brewster points on the solar vertical ``neutral_sep / 2``
  above and below the sun, Arago and the fourth point at their antipodes; the complex
  polarization ``w = -4 (z - z1)(z - z2)(1 + z conj z1)(1 + z conj z2) / ((1 + |z|^2)^2
  (1 + |z1|^2)(1 + |z2|^2))`` in the stereographic plane ``z`` (projection from the nadir),
  ``AoP = arg(w) / 2``, ``DoP = d_max |w| / (2 - |w|)``, less towards the horizon;
* thin clouds (:class:`ThinCloud`): Gaussian patches that brighten, depolarize and rotate
  the AoP by a few degrees;
* the direct-sunlight term of docs/model.md §6.2 (``epsilon``), vignetting, channel-gain
  residuals, a channel-dependent radial shading (each channel's gain changing with the
  square of the field angle, as measured on a real DoFP camera: docs/calibrate.md#sky-rotation),
  Poisson shot noise and Gaussian read noise, a saturated sun disc.

:func:`random_real_sky` draws such a sky. Angles in radians; radiances in DN.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = [
    "CIE_SKY_TYPES",
    "RealSky",
    "ThinCloud",
    "berry_sky",
    "cie_relative_luminance",
    "random_real_sky",
    "render_real_raw",
]

CIE_SKY_TYPES: dict[int, tuple[float, float, float, float, float]] = {
    11: (-1.0, -0.55, 10.0, -3.0, 0.45),  # white-blue sky with a distinct solar corona
    12: (-1.0, -0.32, 10.0, -3.0, 0.45),  # CIE standard clear sky, low turbidity
    13: (-1.0, -0.32, 16.0, -3.0, 0.30),  # CIE standard clear sky, polluted atmosphere
    14: (-1.0, -0.15, 16.0, -3.0, 0.30),  # cloudless turbid sky with a broad solar corona
}
"""ISO 15469 / CIE S 011 standard general sky types: ``(a, b, c, d, e)`` of the gradation
and indicatrix functions (the clear-sky types 11-14)."""


@dataclass(frozen=True)
class ThinCloud:
    """A thin cloud: a Gaussian patch fixed in the sky.

    Attributes
    ----------
    center_n : (3,)
        Unit ENU direction of its centre.
    radius : float
        1/e radius of the Gaussian profile [rad].
    depolarization : float
        Fraction of the degree of polarization removed at the centre, in [0, 1].
    brightening : float
        Relative radiance added at the centre (unpolarized), >= 0.
    aop_rotation : float
        Rotation of the E-vector about the ray at the centre [rad] (a few degrees).
    """

    center_n: FloatArray
    radius: float
    depolarization: float = 0.3
    brightening: float = 0.3
    aop_rotation: float = 0.0

    def __post_init__(self) -> None:
        if not self.radius > 0 or not 0 <= self.depolarization <= 1 or self.brightening < 0:
            raise ValueError("ThinCloud: radius > 0, depolarization in [0, 1], brightening >= 0")


@dataclass(frozen=True)
class RealSky:
    """A realistic sky and camera imperfections for :func:`render_real_raw`.

    Attributes
    ----------
    sky_type : int
        ISO 15469 sky type, a key of :data:`CIE_SKY_TYPES`.
    zenith_dn : float
        Zenith radiance [DN] (before vignetting).
    dop_max : float
        Largest degree of polarization of the sky [-].
    neutral_sep : float
        Angular separation of the Babinet and Brewster points [rad] (0: the Rayleigh sky).
    horizon_depolarization : float
        Fraction of the degree of polarization lost at the horizon (multiple scattering),
        fading with elevation as ``exp(-elevation / 0.3 rad)``.
    clouds : tuple of ThinCloud
    epsilon : float
        Direct-sunlight coefficient of docs/model.md §6.2 [-].
    vignetting : float
        Relative radiance lost at 90 deg field angle: ``V = 1 - vignetting (theta / (pi/2))^2``.
    gain_residual : (4,)
        Relative channel-gain errors the camera file does not know (channel order of the
        file, e.g. +-0.005).
    channel_shading : (4,)
        Channel-dependent radial shading: channel k's gain is ``1 + c_k theta^2`` at the
        field angle ``theta`` [rad] (channel order of the file; a real DoFP camera:
        0.19, -0.02, -0.19, 0.03).
    sun_disc : float
        Angular radius of the saturated sun disc [rad].
    ground : float
        Radiance of the unpolarized ground below the horizon relative to ``zenith_dn`` [-]
        (before vignetting; grass or asphalt in sunlight: 0.2-0.4).
    """

    sky_type: int = 12
    zenith_dn: float = 500.0
    dop_max: float = 0.7
    neutral_sep: float = 0.5
    horizon_depolarization: float = 0.3
    clouds: tuple[ThinCloud, ...] = ()
    epsilon: float = 0.0
    vignetting: float = 0.3
    gain_residual: FloatArray = field(default_factory=lambda: np.zeros(4))
    channel_shading: FloatArray = field(default_factory=lambda: np.zeros(4))
    sun_disc: float = float(np.radians(1.0))
    ground: float = 0.3

    def __post_init__(self) -> None:
        if self.sky_type not in CIE_SKY_TYPES:
            raise ValueError(f"sky_type={self.sky_type}: expected one of {sorted(CIE_SKY_TYPES)}")
        if not 0 <= self.neutral_sep < np.pi or not 0 <= self.dop_max <= 1:
            raise ValueError("neutral_sep in [0, pi) and dop_max in [0, 1] required")


def cie_relative_luminance(
    cos_zenith: ArrayLike, cos_chi: ArrayLike, cos_zenith_sun: float, sky_type: int = 12
) -> FloatArray:
    """Sky luminance relative to the zenith, ``L/L_z`` (ISO 15469 / CIE S 011).

    Parameters
    ----------
    cos_zenith : array_like
        Cosine of the zenith angle Z of the sky element (> 0).
    cos_chi : array_like
        Cosine of its angular distance chi to the sun.
    cos_zenith_sun : float
        Cosine of the sun's zenith angle Z_s.
    sky_type : int
        A key of :data:`CIE_SKY_TYPES`.
    """
    a, b, c, d, e = CIE_SKY_TYPES[sky_type]
    cz = np.asarray(cos_zenith, dtype=float)
    chi = np.arccos(np.clip(np.asarray(cos_chi, dtype=float), -1.0, 1.0))

    def indicatrix(angle: FloatArray | float) -> FloatArray:
        return 1.0 + c * (np.exp(d * angle) - np.exp(d * np.pi / 2)) + e * np.cos(angle) ** 2

    with np.errstate(divide="ignore", over="ignore"):
        gradation = 1.0 + a * np.exp(b / np.maximum(cz, 1e-6))
    zs = float(np.arccos(np.clip(cos_zenith_sun, -1.0, 1.0)))
    return indicatrix(chi) * gradation / (indicatrix(zs) * (1.0 + a * np.exp(b)))


def _stereo(v: FloatArray) -> NDArray[np.complex128]:
    """Stereographic coordinate of ENU unit vectors from the nadir: ``(x + i y)/(1 + z)``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray((v[..., 0] + 1j * v[..., 1]) / (1.0 + v[..., 2]), dtype=np.complex128)


def berry_sky(
    rays_n: ArrayLike, sun_n: ArrayLike, neutral_sep: float
) -> tuple[FloatArray, FloatArray]:
    """E-vectors and unnormalised polarization ``|w|`` of the Berry sky at ENU rays.

    Parameters
    ----------
    rays_n : array_like, (..., 3)
        Unit ENU rays (above the nadir).
    sun_n : array_like, (3,)
        Unit ENU sun (not at the zenith).
    neutral_sep : float
        Separation of the Babinet and Brewster points [rad].

    Returns
    -------
    evec_n : (..., 3)
        Unit ENU E-vectors (sign arbitrary).
    w_abs : (...,)
        ``|w|`` in [0, 1]: zero at the four neutral points, ``sin^2`` of the scattering
        angle for ``neutral_sep = 0``.
    """
    p = np.asarray(rays_n, dtype=float)
    s = np.asarray(sun_n, dtype=float)
    s = s / np.linalg.norm(s)
    up = np.array([0.0, 0.0, 1.0])
    toward_up = up - s[2] * s
    toward_up /= np.linalg.norm(toward_up)
    h = 0.5 * neutral_sep
    z1 = _stereo(np.cos(h) * s + np.sin(h) * toward_up)  # Babinet
    z2 = _stereo(np.cos(h) * s - np.sin(h) * toward_up)  # Brewster
    z = _stereo(p)
    num = (z - z1) * (z - z2) * (1.0 + z * np.conj(z1)) * (1.0 + z * np.conj(z2))
    den = (1.0 + np.abs(z) ** 2) ** 2 * (1.0 + abs(z1) ** 2) * (1.0 + abs(z2) ** 2)
    w = -4.0 * num / den
    # The unit tangent at p whose stereographic image points along +real, and p x it (+imag).
    xi, eta = z.real, z.imag
    r2 = 1.0 + xi * xi + eta * eta
    t1 = np.stack([(1.0 + eta * eta - xi * xi) / r2, -2.0 * xi * eta / r2, -2.0 * xi / r2], -1)
    t2 = np.cross(p, t1)
    chi = 0.5 * np.angle(w)
    evec = np.cos(chi)[..., None] * t1 + np.sin(chi)[..., None] * t2
    return evec, np.abs(w)


@lru_cache(maxsize=8)
def _rays_c(cam: CameraModel) -> FloatArray:
    """Unit camera-frame rays of the superpixel centres ``(Hs, Ws, 3)`` by OpenCV's
    undistortion (NaN outside the lens model's invertible range)."""
    hs, ws = cam.superpixel_shape
    v, u = np.mgrid[0:hs, 0:ws].astype(np.float64)
    pts = np.stack([u, v], -1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    if cam.projection == "kannala-brandt":
        xy = cv2.fisheye.undistortPoints(
            pts, cam.camera_matrix, cam.distortion[:4], criteria=criteria
        )
    else:
        xy = cv2.undistortPoints(pts, cam.camera_matrix, cam.distortion, criteria=criteria)
    xy = np.asarray(xy, dtype=float).reshape(hs, ws, 2)
    rays = np.concatenate([xy, np.ones((hs, ws, 1))], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    if cam.projection == "kannala-brandt":
        # Beyond the peak of theta_d(theta) the undistortion is not unique.
        theta = np.arccos(rays[..., 2])
        k = cam.distortion[:4]
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
        r_img = np.hypot((u - cam.camera_matrix[0, 2]) / cam.camera_matrix[0, 0],
                         (v - cam.camera_matrix[1, 2]) / cam.camera_matrix[1, 1])  # fmt: skip
        rays[np.abs(theta_d - r_img) > 1e-6] = np.nan
    rays.setflags(write=False)
    return rays


def _image_plane_doubled_aop(evec_c: FloatArray, rays_c: FloatArray, model: str) -> FloatArray:
    """(cos 2zeta, sin 2zeta) of camera-frame E-vectors under the lens polarization model
    (docs/model.md §6.1): the image-plane projection (P), or the angle to the ray's meridian
    kept (M)."""
    if model == "projection":
        ex, ey = evec_c[..., 0], evec_c[..., 1]
    else:
        rho = np.hypot(rays_c[..., 0], rays_c[..., 1])
        safe = np.where(rho > 1e-12, rho, 1.0)
        ca = np.where(rho > 1e-12, rays_c[..., 0] / safe, 1.0)
        sa = np.where(rho > 1e-12, rays_c[..., 1] / safe, 0.0)
        along = (evec_c[..., 0] * ca + evec_c[..., 1] * sa) * rays_c[..., 2] - evec_c[..., 2] * rho
        across = -evec_c[..., 0] * sa + evec_c[..., 1] * ca
        ex, ey = along * ca - across * sa, along * sa + across * ca
    n2 = ex * ex + ey * ey
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.stack([(ex * ex - ey * ey) / n2, 2 * ex * ey / n2], -1)


def _rotate_about(v: FloatArray, axis: FloatArray, angle: FloatArray) -> FloatArray:
    """Rotate vectors ``v`` perpendicular to unit ``axis`` by ``angle`` about it."""
    return np.cos(angle)[..., None] * v + np.sin(angle)[..., None] * np.cross(axis, v)


def render_real_raw(
    cam: CameraModel,
    sun_n: ArrayLike,
    rot_nb: Rotation,
    sky: RealSky,
    rng: np.random.Generator | None,
) -> NDArray[np.uint16]:
    """Full-resolution raw DoFP mosaic ``cam.shape`` of a realistic sky (module notes).

    Parameters
    ----------
    cam : CameraModel
        Geometry, channel response, noise (read noise, and shot noise when
        ``cam.conversion_gain_e_per_dn`` is finite) and saturation.
    sun_n : array_like, (3,)
        Unit ENU sun, above the horizon.
    rot_nb : Rotation
        True body -> ENU attitude.
    sky : RealSky
    rng : numpy Generator or None
        Noise source; None renders noise-free (still rounded to DN).
    """
    s_n = np.asarray(sun_n, dtype=float)
    s_n = s_n / np.linalg.norm(s_n)
    mat_nc = rot_nb.as_matrix() @ cam.mat_bc
    rays_c = _rays_c(cam)
    rays_n = rays_c @ mat_nc.T
    ok = np.isfinite(rays_n[..., 2])
    rays_n = np.where(ok[..., None], rays_n, np.array([0.0, 0.0, 1.0]))
    sky_px = ok & (rays_n[..., 2] > 0.0)
    cos_z = np.clip(rays_n[..., 2], 1e-3, 1.0)
    cos_chi = rays_n @ s_n
    radiance = sky.zenith_dn * cie_relative_luminance(cos_z, cos_chi, s_n[2], sky.sky_type)
    evec_n, w_abs = berry_sky(rays_n, s_n, sky.neutral_sep)
    dop = sky.dop_max * w_abs / (2.0 - w_abs)
    elevation = np.arcsin(cos_z)
    dop *= 1.0 - sky.horizon_depolarization * np.exp(-elevation / 0.3)
    for cloud in sky.clouds:
        c_n = np.asarray(cloud.center_n, dtype=float)
        angle = np.arccos(np.clip(rays_n @ (c_n / np.linalg.norm(c_n)), -1.0, 1.0))
        weight = np.exp(-((angle / cloud.radius) ** 2))
        dop *= 1.0 - cloud.depolarization * weight
        radiance *= 1.0 + cloud.brightening * weight
        evec_n = _rotate_about(evec_n, rays_n, cloud.aop_rotation * weight)
    evec_c = evec_n @ mat_nc  # ENU -> camera
    c2, s2 = np.moveaxis(_image_plane_doubled_aop(evec_c, rays_c, cam.polarization_model), -1, 0)
    s0 = radiance
    s1 = radiance * dop * c2
    s2 = radiance * dop * s2
    if sky.epsilon:
        sun_c = mat_nc.T @ s_n
        two_a = 2.0 * np.arctan2(sun_c[1], sun_c[0])
        u = sky.epsilon * radiance * (1.0 - dop)
        s0 = s0 - u
        s1 = s1 - u * np.cos(two_a)
        s2 = s2 - u * np.sin(two_a)
    theta = np.arccos(np.clip(rays_c[..., 2], -1.0, 1.0))
    vig = 1.0 - sky.vignetting * (theta / (0.5 * np.pi)) ** 2
    stokes = np.stack([s0, s1, s2], -1)
    stokes[~sky_px] = 0.0
    stokes[ok & ~sky_px, 0] = sky.ground * sky.zenith_dn  # unpolarized ground
    stokes = np.nan_to_num(stokes * np.where(ok, vig, 0.0)[..., None])
    gain = cam.gain * (1.0 + np.asarray(sky.gain_residual, dtype=float))
    alpha, eta = cam.transmission_angle, cam.efficiency
    response = (
        0.5
        * gain[:, None]
        * np.stack([np.ones(4), eta * np.cos(2 * alpha), eta * np.sin(2 * alpha)], -1)
    )  # (4, 3)
    shading = 1.0 + np.nan_to_num(theta)[..., None] ** 2 * np.asarray(sky.channel_shading)
    channels = (stokes @ response.T) * shading + cam.dark_offset_dn  # (Hs, Ws, 4)
    channels[np.arccos(np.clip(cos_chi, -1, 1)) < sky.sun_disc] = cam.saturation_dn
    raw = np.empty(cam.shape)
    for r in range(2):
        for c in range(2):
            raw[r::2, c::2] = channels[..., cam.channel_at[r, c]]
    if rng is not None:
        if np.isfinite(cam.conversion_gain_e_per_dn):
            k = cam.conversion_gain_e_per_dn
            signal = np.maximum(raw - _dark_mosaic(cam), 0.0)
            raw = raw + (rng.poisson(signal * k) / k - signal)
        raw = raw + rng.normal(0.0, cam.read_noise_dn, raw.shape)
    return np.clip(np.round(raw), 0, cam.saturation_dn).astype(np.uint16)


def _dark_mosaic(cam: CameraModel) -> FloatArray:
    """Dark offset of every mosaic pixel [DN], ``cam.shape``."""
    out = np.empty(cam.shape)
    for r in range(2):
        for c in range(2):
            out[r::2, c::2] = cam.dark_offset_dn[cam.channel_at[r, c]]
    return out


def random_real_sky(
    rng: np.random.Generator,
    sun_n: ArrayLike,
    *,
    n_clouds: int = 2,
    aop_jitter: float = float(np.radians(3.0)),
    gain_residual: float = 0.005,
) -> RealSky:
    """A random realistic sky: CIE type 11-14, ``zenith_dn`` 300-700, ``dop_max`` 0.5-0.8,
    neutral-point separation 25-40 deg, vignetting 0.1-0.4, epsilon 0-0.02, channel-gain
    residuals uniform in ``+-gain_residual``, and ``n_clouds`` thin clouds in the upper sky
    (radius 8-20 deg, depolarization 0.1-0.5, brightening 0-0.5, AoP rotation uniform in
    ``+-aop_jitter`` [rad]). ``sun_n`` is the unit ENU sun (unused but for the cloud
    placement, which avoids the sun's 15 deg)."""
    s = np.asarray(sun_n, dtype=float)
    clouds: list[ThinCloud] = []
    while len(clouds) < n_clouds:
        az = rng.uniform(0, 2 * np.pi)
        el = np.arcsin(rng.uniform(np.sin(np.radians(25.0)), 1.0))
        c = np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
        if c @ s > np.cos(np.radians(15.0)):
            continue
        clouds.append(
            ThinCloud(
                center_n=c,
                radius=float(np.radians(rng.uniform(8.0, 20.0))),
                depolarization=float(rng.uniform(0.1, 0.5)),
                brightening=float(rng.uniform(0.0, 0.5)),
                aop_rotation=float(rng.uniform(-aop_jitter, aop_jitter)),
            )
        )
    return RealSky(
        sky_type=int(rng.choice(sorted(CIE_SKY_TYPES))),
        zenith_dn=float(rng.uniform(300.0, 700.0)),
        dop_max=float(rng.uniform(0.5, 0.8)),
        neutral_sep=float(np.radians(rng.uniform(25.0, 40.0))),
        clouds=tuple(clouds),
        epsilon=float(rng.uniform(0.0, 0.02)),
        vignetting=float(rng.uniform(0.1, 0.4)),
        gain_residual=rng.uniform(-gain_residual, gain_residual, 4),
    )
