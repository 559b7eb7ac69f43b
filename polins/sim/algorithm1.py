"""The paper's Algorithm 1, reproduced on purpose with its degenerate step (reproduction only).

Algorithm 1 of the paper (Eqs. 14, 10-11, 22-24; docs/model.md §8.2) divides the channels
by their gains beta_k, estimates a per-pixel sunlight coefficient k_m from Eq. 22, subtracts
the predicted sunlight from the intensities (Eq. 23) and forms the Stokes vector (Eq. 24).
**Not for operational use**: the scale-consistent Eq. 22 numerator is identically zero for
noise-free data (k_m is pure noise, amplified by k_c), and the printed one gives
``k_m ~ 80/(1 - d)`` and heading errors of about 90 deg (docs/errata.md §1, Eq. 22). The
switches reproduce the printed or the scale-consistent reading.

:func:`measure_algorithm1` composes the stages of the measurement chain
(:mod:`polins.compass.chain`) with these Stokes vectors in place of the least-squares ones,
followed by the eigen solution (the paper's Eq. 31 with ``weighted=False``);
:func:`measure_baseline` runs the chain's ``"traditional"`` method as the paper's baselines
(without the channel-gain calibration, with equal weights). :mod:`polins.sim.reproduction`
uses both for the reproduction of the paper's Section 4.1.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.compass.chain import check_sun, measure_stokes
from polins.compass.heading import Geometry, image_geometry
from polins.compass.image import fill_invalid, image_stokes
from polins.compass.measurement import Measurement, MeasurementMaps, Refusal, measure_options
from polins.compass.pixels import check_raw
from polins.errors import UserInputError
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

EQ22 = ("scale-consistent", "printed")
EQ14 = ("fixed", "printed")

__all__ = [
    "EQ14",
    "EQ22",
    "algorithm1_rows",
    "check_switches",
    "measure_algorithm1",
    "measure_baseline",
    "paper_algorithm1",
]


def check_switches(
    eq22: str = "scale-consistent", kc: float = 20.0, gain_final: bool = True, eq14: str = "fixed"
) -> None:
    """Check the switches of :func:`paper_algorithm1` before any work.

    Raises
    ------
    ValueError
        ``eq22`` outside :data:`EQ22`, ``eq14`` outside :data:`EQ14`, or a non-finite ``kc``.
    """
    if eq22 not in EQ22:
        raise ValueError(f"eq22={eq22!r}: expected one of {EQ22}")
    if eq14 not in EQ14:
        raise ValueError(f"eq14={eq14!r}: expected one of {EQ14}")
    if not np.isfinite(kc):
        raise ValueError(f"kc={kc}: expected a finite number")


def algorithm1_rows(
    channels: NDArray,
    cam: CameraModel,
    sun_c_prior: NDArray,
    *,
    eq22: str,
    kc: float,
    gain_final: bool,
    eq14: str,
) -> tuple[NDArray, NDArray]:
    """Algorithm 1 on component-first channels ``(4, n)`` [DN]: Stokes rows
    (I_in, s1_hat, s2_hat) ``(3, n)`` and the per-pixel k_m ``(n,)`` (the row kernel of
    :func:`paper_algorithm1`)."""
    check_switches(eq22, kc, gain_final, eq14)
    dt = channels.dtype if np.issubdtype(channels.dtype, np.floating) else np.float32
    dark = (channels.astype(dt) - cam.dark_offset_dn.astype(dt)[:, None]).astype(dt)
    beta = cam.gain.astype(dt)[:, None]
    i_hat = dark / beta  # Algorithm 1 step 2
    sign = 1.0 if eq14 == "fixed" else -1.0
    i_in = i_hat[0] + i_hat[2]
    s1 = sign * (i_hat[0] - i_hat[2])
    s2 = sign * (i_hat[1] - i_hat[3])
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(s1 * s1 + s2 * s2) / i_in
    sun_azimuth_c = float(np.arctan2(sun_c_prior[1], sun_c_prior[0]))
    p_k = 0.5 * np.cos(sun_azimuth_c - np.pi / 2 - cam.transmission_angle) ** 2  # Eq. 10-11
    p_hat = 0.5 * (1.0 - cam.efficiency[:, None].astype(dt) * d) * (p_k[:, None] - 0.5).astype(dt)
    m = 4.0 if eq22 == "printed" else 2.0
    # Dark pixels (I_in = 0) give non-finite d and k_m; they stay NaN and the masks drop them.
    with np.errstate(invalid="ignore", divide="ignore"):
        k_m = kc * (i_hat.sum(axis=0) - m * i_in) / (i_in * p_hat.sum(axis=0))  # Eq. 22
        corrected = dark - p_hat * (i_in * k_m)  # Eq. 23 (subtracted from the raw intensities)
    if gain_final:
        corrected = corrected / beta
    s1_hat = sign * (corrected[0] - corrected[2])  # Eq. 24
    s2_hat = sign * (corrected[1] - corrected[3])
    return np.stack([i_in, s1_hat, s2_hat]), k_m


def paper_algorithm1(
    channels: ArrayLike,
    cam: CameraModel,
    sun_c_prior: ArrayLike,
    *,
    eq22: str = "scale-consistent",
    kc: float = 20.0,
    gain_final: bool = True,
    eq14: str = "fixed",
) -> tuple[FloatArray, FloatArray]:
    """The paper's Algorithm 1 (Eqs. 14, 10-11, 22-24) per pixel (docs/model.md §8.2).

    **Not for operational use** (see the module docstring).

    Parameters
    ----------
    channels : array_like, (..., 4)
        Raw channel intensities [DN], ordered by channel index (0, 45, 90, 135 deg).
    sun_c_prior : array_like, (3,)
        Sun vector in the camera frame from the *prior* attitude (the paper's Eq. 13,
        evaluated in the image-plane convention of docs/model.md §3).
    eq22 : {"scale-consistent", "printed"}
        ``m = 2`` or the printed ``m = 4`` in ``k_m = k_c (sum I_k - m I_in)/(I_in sum P_k)``.
    kc : float
        The paper's empirical constant k_c (20).
    gain_final : bool
        Divide the compensated intensities by beta_k (Algorithm 1 as printed: False).
    eq14 : {"fixed", "printed"}
        Stokes sign: fixed (``I0 - I90``) or the paper's printed ``I90 - I0`` (turns the AoP
        by 90 deg).

    Returns
    -------
    stokes : ndarray, (..., 3)
        (I_in, s1_hat, s2_hat) with I_in = I0/beta + I90/beta.
    k_m : ndarray, (...)
        The per-pixel k_m of Eq. 22.
    """
    ch = np.asarray(channels, dtype=float)
    if ch.shape[-1:] != (4,):
        raise ValueError(f"channels must have shape (..., 4), got {ch.shape}")
    rows, k_m = algorithm1_rows(
        ch.reshape(-1, 4).T,
        cam,
        np.asarray(sun_c_prior, dtype=float),
        eq22=eq22,
        kc=kc,
        gain_final=gain_final,
        eq14=eq14,
    )
    return rows.T.reshape(*ch.shape[:-1], 3), k_m.reshape(ch.shape[:-1])


def _ephemeris_geometry(
    cam: CameraModel, sun_n: ArrayLike | None, rot_nb_prior: Rotation | None, caller: str
) -> Geometry:
    """The image geometry of a measurement that needs the ephemeris sun and the prior."""
    if sun_n is None or rot_nb_prior is None:
        raise UserInputError(f"{caller} needs sun_n and rot_nb_prior")
    return image_geometry(cam, sun_n, rot_nb_prior)


def measure_algorithm1(
    raw: ArrayLike,
    cam: CameraModel,
    *,
    sun_n: ArrayLike,
    rot_nb_prior: Rotation,
    eq22: str = "scale-consistent",
    kc: float = 20.0,
    gain_final: bool = True,
    eq14: str = "fixed",
    weighted: bool = True,
    maps: bool = False,
    **options: Any,
) -> tuple[Measurement, MeasurementMaps | None]:
    """Heading from one raw image with the paper's Algorithm 1 and the eigen solution.

    Parameters
    ----------
    raw, cam, sun_n, rot_nb_prior
        As for ``polins.measure``; the prior yaw sets the sunlight angle of Eqs. 10-11.
    eq22, kc, gain_final, eq14
        The switches of :func:`paper_algorithm1`.
    weighted : bool
        Eigen weights ``p^2/sigma_L^2``; False: the paper's equal weights of Eq. 31.
    maps : bool
        Also return the per-pixel maps (else None).
    **options
        Fields of :class:`~polins.compass.measurement.MeasureOptions`.

    Returns
    -------
    Measurement, and MeasurementMaps or None
        ``method="paper"``; ``epsilon`` is the median per-pixel ``k_m / 4`` of the used
        pixels, without a sigma.
    """
    check_switches(eq22, kc, gain_final, eq14)
    opt = measure_options(**options)
    arr = check_raw(raw, cam)
    geo = _ephemeris_geometry(cam, sun_n, rot_nb_prior, "measure_algorithm1")
    try:
        check_sun(geo)
    except Refusal as r:
        return Measurement.refused("paper", r.reason), None
    img = image_stokes(arr, cam, opt, channels=True)
    assert img.channels is not None
    rows, k_m = algorithm1_rows(img.channels, cam, geo.mat_cn @ geo.sun_n, eq22=eq22, kc=kc,
                                gain_final=gain_final, eq14=eq14)  # fmt: skip
    estimate: NDArray = rows.astype(img.dtype)
    valid = img.valid & np.isfinite(rows).all(axis=0)
    fill_invalid(estimate, 1.0, valid)
    # k_m = 4 epsilon (the paper's Eq. 12)
    img = dataclasses.replace(img, estimate=estimate, valid=valid, epsilon_px=k_m / 4.0)
    m, mapped = measure_stokes(img, cam, geo, opt, method="traditional", maps=maps,
                               weighted=weighted)  # fmt: skip
    return dataclasses.replace(m, method="paper"), mapped


def measure_baseline(
    raw: ArrayLike,
    cam: CameraModel,
    *,
    sun_n: ArrayLike,
    rot_nb_prior: Rotation,
    gain_correction: bool = True,
    weighted: bool = True,
    **options: Any,
) -> Measurement:
    """The ``"traditional"`` method as the paper's baselines: without the channel-gain
    calibration (``gain_correction=False``, the paper's uncorrected "traditional") and with
    equal eigen weights (``weighted=False``, its Eq. 31)."""
    opt = measure_options(**options)
    arr = check_raw(raw, cam)
    geo = _ephemeris_geometry(cam, sun_n, rot_nb_prior, "measure_baseline")
    try:
        check_sun(geo)
    except Refusal as r:
        return Measurement.refused("traditional", r.reason)
    img = image_stokes(arr, cam, opt, gain_correction=gain_correction)
    return measure_stokes(img, cam, geo, opt, method="traditional", weighted=weighted)[0]
