"""Flat-field calibration: per-channel gains (and a per-pixel gain map) from unpolarized light.

Under uniform, unpolarized light (an integrating sphere, an opal diffuser, an overcast sky
through a diffuser) the sensor model of docs/model.md §6.2 reduces to
``I_k = g_k S0 / 2 + o_k``: after subtracting the dark offsets, the channel means are
proportional to the gains. Only ratios are identifiable (the common gain trades against
the unknown light level); by the convention of docs/calibrate.md the fitted gains keep the
base camera's mean gain. The per-pixel map also holds vignetting and the illumination's
non-uniformity; it is normalised to the same mean.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.calibration.images import channel_changes, channel_stack, provenance
from polins.errors import UserInputError
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = ["FlatResult", "calibrate_flat"]


@dataclass(frozen=True)
class FlatResult:
    """Channel gains fitted to flat frames.

    Attributes
    ----------
    gain : (4,)
        Per-channel gain g_k [-], mean equal to the base camera's mean gain.
    gain_std : (4,)
        Standard error of ``gain`` [-] from the frame-to-frame scatter of the ratios.
    gain_map : (Hs, Ws, 4) or None
        Per-pixel gain (vignetting and illumination included) [-], when asked for; its mean
        over the used pixels equals the mean of ``gain``. Store it with
        :func:`polins.calibration.save_pixel_map`.
    used : (Hs, Ws) bool
        Superpixels used (in the field of view, never saturated, signal above the dark).
    residuals : (m, 4)
        Per-frame relative gain minus ``gain``, over ``gain`` [-].
    provenance : dict
    """

    gain: FloatArray
    gain_std: FloatArray
    gain_map: FloatArray | None
    used: NDArray[np.bool_]
    residuals: FloatArray
    provenance: dict[str, Any] = field(default_factory=dict)

    def camera_changes(self) -> dict[str, Any]:
        """The camera-model fields this calibration sets."""
        return channel_changes(self.gain, self.gain_std)


def calibrate_flat(
    raws: Sequence[ArrayLike] | ArrayLike,
    cam: CameraModel,
    *,
    mask: ArrayLike | None = None,
    pixel_map: bool = False,
    signal_min_dn: float = 20.0,
) -> FlatResult:
    """Channel gains from ``m >= 1`` frames of uniform unpolarized light.

    Parameters
    ----------
    raws : array_like, (m, H, W)
        Raw flat mosaics [DN]; the light level may change between frames.
    cam : CameraModel
        Base camera: its dark offsets are subtracted (calibrate them first,
        :func:`polins.calibration.calibrate_dark`) and its mean gain is kept.
    mask : array_like of bool, (Hs, Ws), optional
        Superpixels to use (default: all that are lit and unsaturated).
    pixel_map : bool
        Also return the per-pixel gain map ``(Hs, Ws, 4)``.
    signal_min_dn : float
        Superpixels whose darkest channel is less than this above its dark offset [DN] are
        not used.

    Returns
    -------
    FlatResult

    Raises
    ------
    UserInputError
        Wrong shapes, or no usable superpixel.
    """
    stack = channel_stack(raws, cam, min_images=1, what="flat")
    signal = stack.channels - cam.dark_offset_dn  # (m, Hs, Ws, 4)
    used = ~stack.saturated.any(axis=0) & (signal.min(axis=(0, 3)) >= signal_min_dn)
    if mask is not None:
        mask_arr = np.asarray(mask, dtype=bool)
        if mask_arr.shape != cam.superpixel_shape:
            raise UserInputError(
                f"flat mask has shape {mask_arr.shape}, expected {cam.superpixel_shape}"
            )
        used &= mask_arr
    if used.sum() < 16:
        raise UserInputError(
            f"flat frames: only {int(used.sum())} superpixels are lit above {signal_min_dn} DN and unsaturated"
        )
    m = stack.n_images
    level = float(np.mean(cam.gain))
    frame_means = signal[:, used].mean(axis=1)  # (m, 4)
    frame_gain = level * frame_means / frame_means.mean(axis=1, keepdims=True)
    gain = frame_gain.mean(axis=0)
    gain_std = frame_gain.std(axis=0, ddof=1) / np.sqrt(m) if m > 1 else np.full(4, np.nan)
    gain_map = None
    if pixel_map:
        mean_image = signal.mean(axis=0)  # (Hs, Ws, 4)
        gain_map = level * mean_image / mean_image[used].mean()
        gain_map[~used] = np.nan
    residuals = frame_gain / gain - 1.0
    return FlatResult(
        gain=gain,
        gain_std=gain_std,
        gain_map=gain_map,
        used=used,
        residuals=residuals,
        provenance=provenance(
            "flat",
            "channel means of unpolarized flat frames, dark subtracted (docs/calibrate.md#flat)",
            m,
            n_superpixels=int(used.sum()),
            residual_rms=float(f"{np.sqrt(np.mean(residuals**2)):.3g}"),
        ),
    )
