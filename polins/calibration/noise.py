"""Photon transfer: read noise and conversion gain from pairs of flat frames.

Record pairs of frames of the same uniform light at several levels, from dark to near
saturation (docs/calibrate.md#noise). For each pair and channel, the mean signal
``mu = mean((a + b)/2) - o_k`` [DN] and the temporal variance ``var = var(a - b) / 2``
[DN^2] (the difference cancels the fixed pattern) follow the noise model of
docs/model.md §4, ``var = read_noise^2 + mu / G_e`` with ``G_e`` the conversion gain
[e-/DN]: a straight line in ``mu``, fitted by weighted least squares (scipy).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import curve_fit

from polins.calibration.images import channel_stack, provenance
from polins.errors import UserInputError
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = ["NoiseResult", "calibrate_noise"]


@dataclass(frozen=True)
class NoiseResult:
    """Read noise and conversion gain from a photon-transfer curve.

    Attributes
    ----------
    read_noise_dn : float
        Read noise [DN] (the intercept's square root).
    read_noise_std_dn : float
        Its standard error [DN].
    conversion_gain_e_per_dn : float
        Conversion gain G_e [e-/DN] (1 / slope); ``inf`` when no shot noise is seen.
    conversion_gain_std_e_per_dn : float
        Its standard error [e-/DN].
    signal_dn : (p, 4)
        Mean signal of each pair and channel [DN] (the curve's abscissae).
    variance_dn2 : (p, 4)
        Temporal variance of each pair and channel [DN^2] (the ordinates).
    residuals : (p, 4)
        Variance minus the fitted line, over the fitted variance [-].
    provenance : dict
    """

    read_noise_dn: float
    read_noise_std_dn: float
    conversion_gain_e_per_dn: float
    conversion_gain_std_e_per_dn: float
    signal_dn: FloatArray
    variance_dn2: FloatArray
    residuals: FloatArray
    provenance: dict[str, Any] = field(default_factory=dict)

    def camera_changes(self) -> dict[str, Any]:
        """The camera-model fields this calibration sets."""
        return {
            "read_noise_dn": self.read_noise_dn,
            "conversion_gain_e_per_dn": self.conversion_gain_e_per_dn,
        }


def _line(mu: FloatArray, read_var: float, slope: float) -> FloatArray:
    return read_var + slope * mu


def calibrate_noise(
    raws: Sequence[ArrayLike] | ArrayLike, cam: CameraModel, *, mask: ArrayLike | None = None
) -> NoiseResult:
    """Read noise and conversion gain from flat frames taken in pairs.

    Parameters
    ----------
    raws : array_like, (2p, H, W)
        Raw flat mosaics [DN], consecutive frames forming a pair at one light level
        (frames 0-1, 2-3, ...); at least three levels.
    cam : CameraModel
        Base camera: its dark offsets are subtracted.
    mask : array_like of bool, (Hs, Ws), optional
        Superpixels to use (default: all); saturated superpixels are always dropped.

    Returns
    -------
    NoiseResult

    Raises
    ------
    UserInputError
        An odd number of frames, fewer than three pairs, wrong shapes.
    """
    stack = channel_stack(raws, cam, min_images=6, what="noise")
    m = stack.n_images
    if m % 2:
        raise UserInputError(f"noise calibration takes frames in pairs, got an odd number ({m})")
    pairs = stack.channels.reshape(m // 2, 2, *stack.channels.shape[1:])
    sat = stack.saturated.reshape(m // 2, 2, *stack.saturated.shape[1:]).any(axis=1)
    used = np.ones(cam.superpixel_shape, dtype=bool) if mask is None else np.asarray(mask, bool)
    if used.shape != cam.superpixel_shape:
        raise UserInputError(f"noise mask has shape {used.shape}, expected {cam.superpixel_shape}")
    rounding = 1.0 / 12.0 if stack.integer else 0.0
    ok = used[None] & ~sat  # (p, Hs, Ws)
    count = ok.sum(axis=(1, 2))[:, None]  # (p, 1)
    if np.any(count < 16):
        raise UserInputError("noise calibration: a pair has fewer than 16 unsaturated superpixels")
    w = ok[..., None].astype(float)
    mean = (pairs.mean(axis=1) * w).sum(axis=(1, 2)) / count - cam.dark_offset_dn  # (p, 4)
    diff = (pairs[:, 0] - pairs[:, 1]) * w
    diff_mean = diff.sum(axis=(1, 2)) / count
    var = ((diff**2).sum(axis=(1, 2)) / count - diff_mean**2) * count / (count - 1) / 2.0 - rounding
    mu, v = mean.ravel(), var.ravel()
    # Var(sample variance) = 2 var^2 / (n - 1): weight each point by it.
    sigma = np.maximum(v, 1e-6) * np.sqrt(2.0 / (np.repeat(count.ravel(), 4) - 1))
    (read_var, slope), cov = curve_fit(
        _line, mu, v, p0=(max(float(v.min()), 1e-3), 0.01), sigma=sigma, absolute_sigma=False
    )
    if read_var <= 0:
        raise UserInputError(
            "photon transfer: the fitted read-noise variance is not positive; add darker pairs"
        )
    read = float(np.sqrt(read_var))
    read_std = float(np.sqrt(cov[0, 0]) / (2.0 * read))
    if slope > 3.0 * np.sqrt(cov[1, 1]):
        gain_e = float(1.0 / slope)
        gain_e_std = float(np.sqrt(cov[1, 1]) / slope**2)
    else:  # no shot noise detected
        gain_e, gain_e_std = float("inf"), float("nan")
    residuals = (var - _line(mean, read_var, slope)) / _line(mean, read_var, slope)
    return NoiseResult(
        read_noise_dn=read,
        read_noise_std_dn=read_std,
        conversion_gain_e_per_dn=gain_e,
        conversion_gain_std_e_per_dn=gain_e_std,
        signal_dn=mean,
        variance_dn2=var,
        residuals=residuals,
        provenance=provenance(
            "noise",
            "photon transfer: var((a - b)/sqrt 2) against the mean of flat pairs (docs/calibrate.md#noise)",
            m,
            n_levels=m // 2,
            residual_rms=float(f"{np.sqrt(np.mean(residuals**2)):.3g}"),
        ),
    )
