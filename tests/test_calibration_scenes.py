"""Calibration scenes for the round-trip tests of polins.calibration, written independently of it.

The forward model of a DoFP pixel (docs/model.md §6.2), written out here::

    I_k = g_k (S0 + eta_k (S1 cos 2 alpha_k + S2 sin 2 alpha_k)) / 2 + o_k + noise

with Poisson shot noise (conversion gain G_e [e-/DN]), Gaussian read noise, rounding to DN
and clipping to the camera's range. Channel k goes to the mosaic positions where
``cam.channel_at == k`` (docs/conventions.md, "Images and sensor"). Nothing here calls
polins.calibration; the test below ties the forward model to the simulator's channel model.
"""

from dataclasses import replace

import numpy as np

import polins
from polins.sim.render import channel_intensity

BASE = polins.load_camera("paper-table1")


def small_camera(factor: int = 8, **changes):
    """The shipped camera at 1/factor resolution with ideal channels (gain 1, eta 1)."""
    cam = BASE.downscaled(factor)
    return replace(cam, **{"gain": np.ones(4), "efficiency": np.ones(4), **changes})


def perturbed_camera(cam, rng, *, gain=0.03, angle_deg=1.0, eff=(0.96, 1.0), dark=(10.0, 40.0)):
    """``cam`` with random channel gains (1 +- gain), angle errors (+- angle_deg),
    efficiencies in ``eff`` and dark offsets in ``dark`` [DN]."""
    nominal = np.radians(cam.nominal_angle_deg)
    return replace(
        cam,
        gain=1.0 + rng.uniform(-gain, gain, 4),
        transmission_angle=nominal + np.radians(rng.uniform(-angle_deg, angle_deg, 4)),
        efficiency=rng.uniform(*eff, 4),
        dark_offset_dn=rng.uniform(*dark, 4),
    )


def response(stokes, gain, efficiency, angle, dark):
    """Noise-free channels ``(..., 4)`` [DN] of Stokes ``(..., 3)``; the channel parameters
    broadcast against ``(..., 4)`` (per channel, or per-pixel maps)."""
    s = np.asarray(stokes, dtype=float)[..., None, :]
    two_a = 2.0 * np.asarray(angle, dtype=float)
    pol = s[..., 1] * np.cos(two_a) + s[..., 2] * np.sin(two_a)
    return gain * (s[..., 0] + efficiency * pol) / 2.0 + dark


def mosaic(channels, cam):
    """Raw mosaic ``(..., H, W)`` of channels ``(..., Hs, Ws, 4)``."""
    ch = np.asarray(channels, dtype=float)
    out = np.empty((*ch.shape[:-3], *cam.shape))
    for r in range(2):
        for c in range(2):
            out[..., r::2, c::2] = ch[..., cam.channel_at[r, c]]
    return out


def sensor(signal, dark_mosaic, cam, rng, *, read_noise_dn, conversion_gain=np.inf):
    """Noisy, rounded, clipped uint16 mosaic of a noise-free mosaic [DN]."""
    out = np.asarray(signal, dtype=float)
    if np.isfinite(conversion_gain):
        electrons = rng.poisson(np.maximum(out - dark_mosaic, 0.0) * conversion_gain)
        out = electrons / conversion_gain + dark_mosaic
    out = out + read_noise_dn * rng.standard_normal(out.shape)
    return np.clip(np.rint(out), 0, cam.saturation_dn).astype(np.uint16)


def dark_mosaic_of(cam, shape_prefix=()):
    """The camera's dark offsets as a mosaic."""
    return mosaic(
        np.broadcast_to(cam.dark_offset_dn, (*shape_prefix, *cam.superpixel_shape, 4)), cam
    )


def test_forward_model_matches_the_simulator_channel_model():
    rng = np.random.default_rng(0)
    cam = perturbed_camera(small_camera(), rng)
    stokes = rng.normal(size=(50, 3)) * [10, 5, 5] + [100, 0, 0]
    ours = response(stokes, cam.gain, cam.efficiency, cam.transmission_angle, cam.dark_offset_dn)
    for k in range(4):
        np.testing.assert_allclose(ours[:, k], channel_intensity(stokes, cam, k), rtol=1e-12)


def test_mosaic_places_channels_by_layout():
    cam = small_camera()
    ch = np.zeros((*cam.superpixel_shape, 4))
    ch[..., 0] = 1.0  # the 0 deg channel sits at row 1, column 1 of the IMX250MZR mosaic
    raw = mosaic(ch, cam)
    assert raw[1::2, 1::2].min() == 1.0 and raw.sum() == ch.sum()
