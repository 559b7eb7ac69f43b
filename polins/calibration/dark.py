"""Dark calibration: per-channel dark offsets and the read noise from frames taken in the dark.

Cap the lens (or close the shutter) and record at least two frames at the exposure and gain
of the sky images. Channel ``k`` then reads ``I_k = o_k + n`` (docs/model.md §6.2 with no
light): the dark offset ``o_k`` is the mean over pixels and frames, and the read noise the
temporal standard deviation, pooled over pixels from the frame-to-frame variance of each
pixel, so that the fixed pattern (DSNU) does not count as noise. Integer frames carry
1/12 DN^2 of rounding variance, which is removed (Sheppard's correction).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.calibration.images import channel_stack, provenance
from polins.errors import UserInputError
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = ["DarkResult", "calibrate_dark"]

CLIPPED_FRACTION_MAX = 1e-3  # more dark pixels at 0 DN than this biases the estimates


@dataclass(frozen=True)
class DarkResult:
    """Dark offsets and read noise fitted to dark frames.

    Attributes
    ----------
    dark_offset_dn : (4,)
        Per-channel dark offset o_k [DN] (channel order of the camera model).
    dark_offset_std_dn : (4,)
        Standard error of ``dark_offset_dn`` [DN] (from the frame-to-frame scatter).
    read_noise_dn : float
        Temporal read noise [DN], all channels pooled.
    read_noise_channel_dn : (4,)
        Temporal read noise of each channel [DN].
    read_noise_std_dn : float
        Standard error of ``read_noise_dn`` [DN].
    dsnu_dn : (4,)
        Dark-signal non-uniformity: the pixel-to-pixel standard deviation of the frame mean [DN].
    dark_map_dn : (Hs, Ws, 4) or None
        Per-pixel dark offset (mean of the frames) [DN], when asked for.
    residuals : (m, 4)
        Per-frame channel mean minus ``dark_offset_dn`` [DN] (drift between frames).
    provenance : dict
        Kind, date, method, number of frames and fit figures.
    """

    dark_offset_dn: FloatArray
    dark_offset_std_dn: FloatArray
    read_noise_dn: float
    read_noise_channel_dn: FloatArray
    read_noise_std_dn: float
    dsnu_dn: FloatArray
    dark_map_dn: FloatArray | None
    residuals: FloatArray
    provenance: dict[str, Any] = field(default_factory=dict)

    def camera_changes(self) -> dict[str, Any]:
        """The camera-model fields this calibration sets."""
        return {"dark_offset_dn": self.dark_offset_dn.copy(), "read_noise_dn": self.read_noise_dn}


def calibrate_dark(
    raws: Sequence[ArrayLike] | ArrayLike, cam: CameraModel, *, pixel_map: bool = False
) -> DarkResult:
    """Dark offsets and read noise from ``m >= 2`` dark frames.

    Parameters
    ----------
    raws : array_like, (m, H, W)
        Raw dark mosaics [DN] of ``cam.shape``, all at one exposure and analogue gain.
    cam : CameraModel
        Supplies the mosaic layout and the saturation level.
    pixel_map : bool
        Also return the per-pixel dark map ``(Hs, Ws, 4)`` [DN].

    Returns
    -------
    DarkResult

    Raises
    ------
    UserInputError
        Fewer than two frames, wrong shapes, light in the frames (saturated pixels), or
        frames clipped at 0 DN (the camera's black level is too low to see the noise).
    """
    stack = channel_stack(raws, cam, min_images=2, what="dark")
    ch = stack.channels  # (m, Hs, Ws, 4)
    m = stack.n_images
    if stack.saturated.any():
        raise UserInputError("dark frames hold saturated pixels: is the lens capped?")
    clipped = float(np.mean(ch <= 0.0))
    if clipped > CLIPPED_FRACTION_MAX:
        raise UserInputError(
            f"{100 * clipped:.2g}% of the dark pixels read 0 DN: raise the camera's black level "
            "so that the dark noise is not clipped"
        )
    frame_means = ch.mean(axis=(1, 2))  # (m, 4)
    offset = frame_means.mean(axis=0)
    offset_std = frame_means.std(axis=0, ddof=1) / np.sqrt(m)
    pixel_mean = ch.mean(axis=0)  # (Hs, Ws, 4)
    temporal_var = ch.var(axis=0, ddof=1).mean(axis=(0, 1))  # (4,) [DN^2]
    rounding = 1.0 / 12.0 if stack.integer else 0.0
    var_channel = np.maximum(temporal_var - rounding, 0.0)
    read_channel = np.sqrt(var_channel)
    read = float(np.sqrt(var_channel.mean()))
    n_samples = (m - 1) * ch.shape[1] * ch.shape[2] * 4  # degrees of freedom of the pooled variance
    read_std = read / np.sqrt(2.0 * n_samples)
    # The frame mean still holds temporal noise of variance var/m; what is left is DSNU.
    dsnu = np.sqrt(np.maximum(pixel_mean.var(axis=(0, 1)) - temporal_var / m, 0.0))
    return DarkResult(
        dark_offset_dn=offset,
        dark_offset_std_dn=offset_std,
        read_noise_dn=read,
        read_noise_channel_dn=read_channel,
        read_noise_std_dn=float(read_std),
        dsnu_dn=dsnu,
        dark_map_dn=pixel_mean if pixel_map else None,
        residuals=frame_means - offset,
        provenance=provenance(
            "dark",
            "mean and pooled temporal variance of dark frames (docs/calibrate.md#dark)",
            m,
            read_noise_dn=round(read, 4),
            dsnu_dn=[round(float(x), 4) for x in dsnu],
            drift_rms_dn=round(float(np.sqrt(np.mean((frame_means - offset) ** 2))), 4),
        ),
    )
