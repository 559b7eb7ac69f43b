"""Polarizer calibration: transmission angles, efficiencies and gains from a rotating linear polarizer.

Put a linear polarizer (a good one: extinction ratio above 1000) between a uniform,
unpolarized source and the camera, and record it at m >= 6 angles over at least 180 deg
(docs/calibrate.md#polarizer). Each channel k then reads (docs/model.md §6.2)::

    I_jk = s_j g_k / 2 [1 + eta_k D cos 2(theta_j - alpha_k)] + o_k

with theta_j the polarizer's angle in the image plane (+u towards +v,
docs/conventions.md) and D its degree of polarization. The channel means give the channel
gains, efficiencies and transmission angles by a nonlinear least-squares fit
(:func:`polins.calibration.malus.fit_turning_polarization`); the polarizer angles may be
known or fitted. Fitted angles need a stable light source (one intensity for all frames:
otherwise per-frame intensities and angles trade against the channel parameters), and
their common offset is unidentifiable: the base camera's mean angle offset is kept.
With known angles the source may drift (a per-frame intensity is fitted). With the angles known or fitted, every pixel follows the linear
model ``I_jp = s_j/2 [1, D cos 2theta_j, D sin 2theta_j] . x_p`` with
``x_p = g_p [1, eta_p cos 2alpha_p, eta_p sin 2alpha_p]``, one least-squares solve for all
pixels at once: the super-pixel calibration of Powell & Gruev (Opt. Express 21, 2013),
which gives per-pixel gain, efficiency and angle maps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.calibration.images import channel_changes, channel_stack, provenance
from polins.calibration.malus import fit_turning_polarization
from polins.errors import UserInputError
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = ["PolarizerResult", "calibrate_polarizer"]


@dataclass(frozen=True)
class PolarizerResult:
    """Channel calibration fitted to rotating-polarizer frames.

    Attributes
    ----------
    gain, gain_std : (4,)
        Channel gains g_k [-] (mean: the base camera's) and standard errors.
    transmission_angle, transmission_angle_std : (4,)
        Transmission angles alpha_k [rad] and standard errors.
    efficiency, efficiency_std : (4,)
        Efficiencies eta_k [-] (relative to the polarizer's DoP ``D``) and standard errors.
    polarizer_angle : (m,)
        Polarizer angles theta_j [rad] (given, or fitted: in [0, pi), up to the common offset).
    gain_map, angle_map, efficiency_map : (Hs, Ws, 4) or None
        Per-pixel maps (gain normalised to the mean of ``gain``; vignetting included), when
        asked for. Store them with :func:`polins.calibration.save_pixel_map`.
    pixel_residual_rms_dn : float or None
        RMS residual of the per-pixel fit [DN], when maps were asked for.
    residuals : (m, 4)
        Channel means minus the model [DN].
    provenance : dict
    """

    gain: FloatArray
    gain_std: FloatArray
    transmission_angle: FloatArray
    transmission_angle_std: FloatArray
    efficiency: FloatArray
    efficiency_std: FloatArray
    polarizer_angle: FloatArray
    gain_map: FloatArray | None
    angle_map: FloatArray | None
    efficiency_map: FloatArray | None
    pixel_residual_rms_dn: float | None
    residuals: FloatArray
    provenance: dict[str, Any] = field(default_factory=dict)

    def camera_changes(self) -> dict[str, Any]:
        """The camera-model fields this calibration sets."""
        return channel_changes(self.gain, self.gain_std, self.transmission_angle, self.efficiency,
                               self.transmission_angle_std, self.efficiency_std)  # fmt: skip


def calibrate_polarizer(
    raws: Sequence[ArrayLike] | ArrayLike,
    cam: CameraModel,
    polarizer_angles: ArrayLike | None = None,
    *,
    polarizer_dop: float = 1.0,
    mask: ArrayLike | None = None,
    pixel_maps: bool = False,
) -> PolarizerResult:
    """Channel gains, efficiencies and transmission angles from a rotating linear polarizer.

    Parameters
    ----------
    raws : array_like, (m, H, W)
        m >= 6 raw mosaics [DN] of uniform light through the polarizer.
    cam : CameraModel
        Base camera: dark offsets (subtracted), starting values and conventions.
    polarizer_angles : array_like, (m,), optional
        Polarizer angles in the image plane [rad] (+u towards +v); fitted when None (then
        the source must be stable from frame to frame).
    polarizer_dop : float
        Degree of polarization D of the light behind the polarizer [-] (1 for an ideal one;
        ``(r - 1)/(r + 1)`` for an extinction ratio r).
    mask : array_like of bool, (Hs, Ws), optional
        Superpixels to use (default: all never saturated and lit).
    pixel_maps : bool
        Also fit the per-pixel gain, efficiency and angle maps.

    Returns
    -------
    PolarizerResult

    Raises
    ------
    UserInputError
        Fewer than 6 frames, angles not matching the frames, no usable superpixel.
    """
    stack = channel_stack(raws, cam, min_images=6, what="polarizer")
    m = stack.n_images
    if polarizer_angles is not None:
        theta_given = np.asarray(polarizer_angles, dtype=float)
        if theta_given.shape != (m,):
            raise UserInputError(f"polarizer: {theta_given.size} angles for {m} frames")
    if not 0.0 < polarizer_dop <= 1.0:
        raise UserInputError(f"polarizer_dop={polarizer_dop} outside (0, 1]")
    signal = stack.channels - cam.dark_offset_dn  # (m, Hs, Ws, 4)
    used = ~stack.saturated.any(axis=0) & (
        signal.max(axis=(0, 3)) > 20.0 * max(cam.read_noise_dn, 1.0)
    )
    if mask is not None:
        used &= np.asarray(mask, dtype=bool)
    n_used = int(used.sum())
    if n_used < 16:
        raise UserInputError(f"polarizer: only {n_used} usable superpixels (lit, unsaturated)")
    y = signal[:, used].mean(axis=1)[:, None, :]  # (m, 1, 4)
    var = cam.read_noise_dn**2 + (
        np.maximum(y, 0.0) / cam.conversion_gain_e_per_dn
        if np.isfinite(cam.conversion_gain_e_per_dn)
        else 0.0
    )
    source = np.array([[1.0, polarizer_dop, 0.0]]) * float(np.mean(y[:, 0]))
    fit = fit_turning_polarization(
        y,
        np.sqrt(var / n_used),
        cam,
        turn=polarizer_angles,
        sources=source,
        constant_scale=polarizer_angles is None,
    )
    gain_map = angle_map = eff_map = None
    pixel_rms = None
    if pixel_maps:
        # Powell & Gruev: one linear least-squares solve shared by all pixels.
        two_t = 2.0 * fit.turn
        design = (
            0.5
            * fit.scale[:, None]
            * fit.sources[0, 0]
            * np.stack(
                [np.ones(m), polarizer_dop * np.cos(two_t), polarizer_dop * np.sin(two_t)], -1
            )
        )  # (m, 3)
        data = signal[:, used].reshape(m, -1)  # (m, n * 4)
        x, *_ = np.linalg.lstsq(design, data, rcond=None)  # (3, n * 4)
        pixel_rms = float(np.sqrt(np.mean((design @ x - data) ** 2)))
        x = x.reshape(3, n_used, 4)
        g = x[0]
        g_scaled = g * float(np.mean(fit.gain) / np.mean(g))
        maps = [np.full((*cam.superpixel_shape, 4), np.nan) for _ in range(3)]
        maps[0][used] = g_scaled
        maps[1][used] = np.hypot(x[1], x[2]) / g
        angle = 0.5 * np.arctan2(x[2], x[1])
        # Keep each pixel's angle on the branch of its channel's fitted angle.
        maps[2][used] = angle + np.pi * np.round((fit.angle - angle) / np.pi)
        gain_map, eff_map, angle_map = maps
    return PolarizerResult(
        gain=fit.gain,
        gain_std=fit.gain_std,
        transmission_angle=fit.angle,
        transmission_angle_std=fit.angle_std,
        efficiency=fit.efficiency,
        efficiency_std=fit.efficiency_std,
        polarizer_angle=fit.turn if polarizer_angles is not None else np.mod(fit.turn, np.pi),
        gain_map=gain_map,
        angle_map=angle_map,
        efficiency_map=eff_map,
        pixel_residual_rms_dn=pixel_rms,
        residuals=fit.residuals[:, 0, :],
        provenance=provenance(
            "polarizer",
            "rotating linear polarizer, Malus-law fit of channel means"
            + (" and per-pixel linear fit (Powell & Gruev 2013)" if pixel_maps else "")
            + (", known angles" if polarizer_angles is not None else ", fitted angles")
            + " (docs/calibrate.md#polarizer)",
            m,
            polarizer_dop=polarizer_dop,
            residual_rms_dn=float(f"{np.sqrt(np.mean(fit.residuals**2)):.3g}"),
            chi2_dof=float(f"{fit.chi2_dof:.3g}"),
        ),
    )
