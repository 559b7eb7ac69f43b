"""An independent, deliberately plain DoFP sky renderer for the measurement-chain tests.

It shares no code with ``polins.compass`` (nor with ``polins.sim``): the rays come from its own Kannala-Brandt Newton inversion, the
E-vectors from ``s x p`` written out here, the AoP from its own lens-model lines, and the
four channels from Malus' law. All four channels are sampled at the superpixel centre (no
mosaic IFOV offset). Only the camera *model* (a ``CameraModel`` with its numbers) and scipy's
``Rotation`` are taken from outside.

Sensor model (docs/model.md §6.2 written in Malus form; channel k with transmission axis alpha_k, gain
g_k, efficiency eta_k, dark offset o_k)::

    I_k = g_k [ R (1 - d)/2 + R d (eta_k cos^2(zeta - alpha_k) + (1 - eta_k)/2) ]   sky
        + g_k eps u [ -1/2 + eta_k (2 P_k - 1/2) ],  P_k = cos^2(a - alpha_k)/2         sunlight
        + o_k + noise,   u = R (1 - d),  a = (sun azimuth in the image) - 90 deg
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def superpixel_rays(cam) -> np.ndarray:
    """Unit camera-frame rays (Hs, Ws, 3) by Newton inversion of the Kannala-Brandt model."""
    if cam.projection != "kannala-brandt":
        raise NotImplementedError("render_simple only knows the Kannala-Brandt lens")
    hs, ws = cam.height_px // 2, cam.width_px // 2
    v, u = np.mgrid[0:hs, 0:ws].astype(float)
    k = cam.camera_matrix
    x = (u - k[0, 2]) / k[0, 0]
    y = (v - k[1, 2]) / k[1, 1]
    theta_d = np.hypot(x, y)
    k1, k2, k3, k4 = cam.distortion
    theta = theta_d.copy()
    for _ in range(40):
        t2 = theta**2
        f = theta * (1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4) - theta_d
        df = 1 + 3 * k1 * t2 + 5 * k2 * t2**2 + 7 * k3 * t2**3 + 9 * k4 * t2**4
        theta = theta - f / df
    phi = np.arctan2(y, x)
    rays = np.stack(
        [np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1
    )
    rays[theta > np.radians(89.0)] = np.nan  # beyond the lens model's useful range
    return rays


def image_aop(evec: np.ndarray, rays: np.ndarray, model: str) -> np.ndarray:
    """Image-plane AoP [rad] of camera-frame E-vectors (docs/model.md §6.1, models P and M)."""
    if model == "projection":
        return np.arctan2(evec[..., 1], evec[..., 0])
    gamma = np.arccos(rays[..., 2])
    alpha = np.arctan2(rays[..., 1], rays[..., 0])
    e_gamma = np.stack(
        [np.cos(gamma) * np.cos(alpha), np.cos(gamma) * np.sin(alpha), -np.sin(gamma)], -1
    )
    e_alpha = np.stack([-np.sin(alpha), np.cos(alpha), np.zeros_like(alpha)], -1)
    return alpha + np.arctan2(np.sum(evec * e_alpha, -1), np.sum(evec * e_gamma, -1))


def render(
    cam,
    sun_n,
    rot_nb: Rotation,
    *,
    dop_max: float = 0.75,
    radiance: float = 220.0,
    rayleigh_radiance: bool = False,
    epsilon: float = 0.0,
    noise_std: float = 0.0,
    rng: np.random.Generator | None = None,
    occluder_az_deg: tuple[float, float] | None = None,
    occluder_el_deg: float = 40.0,
    polarizer_deg: float | None = None,
    dtype=np.float64,
) -> np.ndarray:
    """Full-resolution raw mosaic (H, W) of a clear Rayleigh sky seen by ``cam``.

    Parameters
    ----------
    sun_n : (3,) unit ENU sun vector.
    rot_nb : body -> ENU rotation; the camera is ``rot_nb * cam.rot_bc``.
    epsilon : direct-sunlight coefficient (docs/model.md §6.2).
    noise_std : Gaussian per-channel noise [DN] (needs ``rng``).
    occluder_az_deg : world-fixed occluder, compass azimuth range [deg] (clockwise from
        North), below ``occluder_el_deg``; occluded pixels read 0 DN (plus noise).
    polarizer_deg : if given, the scene is a uniform, fully polarized field with this
        image-plane angle (the rotating-polarizer test of docs/model.md §3.4) instead of the sky.
    dtype : output dtype; integer dtypes are rounded and clipped to the sensor range.
    """
    rays = superpixel_rays(cam)
    rot_nc = rot_nb * Rotation.from_matrix(cam.mat_bc)
    sun_c = rot_nc.inv().apply(np.asarray(sun_n, dtype=float))
    with np.errstate(invalid="ignore"):
        if polarizer_deg is not None:
            zeta = np.full(rays.shape[:2], np.radians(polarizer_deg))
            dop = np.ones(rays.shape[:2])
            rad = np.full(rays.shape[:2], radiance)
        else:
            evec = np.cross(sun_c, rays)  # Rayleigh E-vector, perpendicular to the sun and the ray
            zeta = image_aop(evec, rays, cam.polarization_model)
            cos_scat = rays @ sun_c
            dop = dop_max * (1 - cos_scat**2) / (1 + cos_scat**2)
            rad = radiance * (1 + cos_scat**2) if rayleigh_radiance else np.full_like(dop, radiance)
        a = np.arctan2(sun_c[1], sun_c[0]) - np.pi / 2
        unpol = rad * (1 - dop)
        channels = []
        for k in range(4):
            alpha, g, eta = cam.transmission_angle[k], cam.gain[k], cam.efficiency[k]
            sky = rad * (1 - dop) / 2 + rad * dop * (
                eta * np.cos(zeta - alpha) ** 2 + (1 - eta) / 2
            )
            p_k = 0.5 * np.cos(a - alpha) ** 2
            sun = epsilon * unpol * (-0.5 + eta * (2 * p_k - 0.5))
            channels.append(g * (sky + sun) + cam.dark_offset_dn[k])
        image = np.stack(channels, axis=-1)  # (Hs, Ws, 4), channel index order
        if occluder_az_deg is not None:
            rays_n = rot_nc.apply(np.nan_to_num(rays).reshape(-1, 3)).reshape(rays.shape)
            az = np.degrees(np.arctan2(rays_n[..., 0], rays_n[..., 1])) % 360.0
            el = np.degrees(np.arcsin(np.clip(rays_n[..., 2], -1, 1)))
            lo, hi = occluder_az_deg
            image[(az >= lo) & (az <= hi) & (el < occluder_el_deg)] = 0.0
    image = np.nan_to_num(image, nan=0.0)
    raw = np.empty((cam.height_px, cam.width_px))
    for r in range(2):
        for c in range(2):
            raw[r::2, c::2] = image[..., cam.channel_at[r, c]]
    if noise_std > 0:
        if rng is None:
            raise ValueError("noise_std > 0 needs an rng")
        raw = raw + rng.normal(0.0, noise_std, raw.shape)
    if np.issubdtype(dtype, np.integer):
        return np.clip(np.round(raw), 0, 2**cam.bit_depth - 1).astype(dtype)
    return raw.astype(dtype)


def random_attitude(rng: np.random.Generator, tilt_max_deg: float) -> Rotation:
    """Body -> ENU rotation with uniform yaw and a tilt of up to ``tilt_max_deg``."""
    yaw = rng.uniform(-np.pi, np.pi)
    tilt = np.radians(tilt_max_deg) * np.sqrt(rng.uniform())
    direction = rng.uniform(-np.pi, np.pi)
    roll, pitch = tilt * np.cos(direction), tilt * np.sin(direction)
    return Rotation.from_euler("ZYX", [yaw, pitch, roll])
