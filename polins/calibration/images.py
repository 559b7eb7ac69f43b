"""Calibration images: stacks of raw DoFP mosaics split into their four polarizer channels.

Every estimator of :mod:`polins.calibration` starts here. A stack of ``m`` raw mosaics
``(m, H, W)`` becomes a channel stack ``(m, Hs, Ws, 4)`` [DN]: channel ``k`` (ordered by the
camera's nominal labels) of superpixel (i, j) is the raw pixel at row ``2i + r``, column
``2j + c`` with ``cam.channel_at[r, c] == k`` (docs/conventions.md, "Images and sensor").
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from polins.errors import UserInputError
from polins.models import CameraModel
from polins.models.camera import mixing_std

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["ChannelStack", "centred_channels", "channel_stack", "provenance", "zero_sum_basis"]


@dataclass(frozen=True)
class ChannelStack:
    """Raw mosaics split into channels, with the masks every estimator needs.

    Attributes
    ----------
    channels : ndarray, (m, Hs, Ws, 4)
        Channel intensities [DN], dark offset included.
    saturated : ndarray of bool, (m, Hs, Ws)
        A channel of the superpixel is at or above ``cam.saturation_dn``.
    integer : bool
        The input was integer (quantised to 1 DN: a variance carries 1/12 DN^2 of rounding).
    """

    channels: FloatArray
    saturated: BoolArray
    integer: bool

    @property
    def n_images(self) -> int:
        """Number of images ``m``."""
        return int(self.channels.shape[0])


def channel_stack(
    raws: Sequence[ArrayLike] | ArrayLike, cam: CameraModel, *, min_images: int = 1, what: str = ""
) -> ChannelStack:
    """Split raw mosaics ``(m, H, W)`` (or a sequence of ``(H, W)``) into channels.

    Raises
    ------
    UserInputError
        Fewer than ``min_images`` images, a wrong shape or dtype (one line).
    """
    label = f"{what} " if what else ""
    try:
        arr = np.asarray(raws)
    except ValueError:
        raise UserInputError(f"{label}images differ in shape; camera expects {cam.shape}") from None
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1:] != cam.shape:
        raise UserInputError(
            f"{label}images have shape {arr.shape[1:] if arr.ndim == 3 else arr.shape}; camera "
            f"{cam.name!r} expects full-resolution mosaics {cam.shape} (H, W)"
        )
    if arr.shape[0] < min_images:
        raise UserInputError(
            f"{label}calibration needs at least {min_images} images, got {arr.shape[0]}"
        )
    integer = bool(np.issubdtype(arr.dtype, np.integer))
    if not (integer or np.issubdtype(arr.dtype, np.floating)):
        raise UserInputError(f"{label}images have dtype {arr.dtype}; expected integer or float DN")
    m, (hs, ws) = arr.shape[0], cam.superpixel_shape
    # (m, H, W) -> (m, Hs, r, Ws, c) -> (m, Hs, Ws, r, c) -> (m, Hs, Ws, mosaic position r*2+c)
    by_position = arr.reshape(m, hs, 2, ws, 2).transpose(0, 1, 3, 2, 4).reshape(m, hs, ws, 4)
    channels = np.empty((m, hs, ws, 4))
    channels[..., np.asarray(cam.channel_at).ravel()] = by_position
    if not np.all(np.isfinite(channels)):
        raise UserInputError(f"{label}images hold non-finite values")
    saturated = np.any(channels >= cam.saturation_dn, axis=-1)
    return ChannelStack(channels, saturated, integer)


def centred_channels(channels: FloatArray, cam: CameraModel, *, order: int = 1) -> FloatArray:
    """Channels ``(..., Hs, Ws, 4)`` interpolated to their superpixel centres [DN].

    The four pixels of a superpixel look in slightly different directions (the DoFP
    instantaneous-field-of-view error): the pixel at mosaic position (r, c) sits at
    superpixel coordinates ``(u + (c - 1/2)/2, v + (r - 1/2)/2)`` (docs/model.md §5). Each
    channel image is resampled at the centres (``scipy.ndimage.shift``, a spline of
    ``order``; edges repeat the nearest value), so that all four see the same direction.
    The default, bilinear, smooths the four channels alike (each moves a quarter
    superpixel in u and in v), so the smoothing makes no channel-to-channel difference.
    """
    ch = np.asarray(channels, dtype=float)
    out = np.empty_like(ch)
    lead = (0,) * (ch.ndim - 3)
    for r in range(2):
        for c in range(2):
            k = int(cam.channel_at[r, c])
            out[..., k] = ndimage.shift(ch[..., k], (*lead, (r - 0.5) / 2, (c - 0.5) / 2),
                                        order=order, mode="nearest")  # fmt: skip
    return out


def zero_sum_basis(n: int) -> FloatArray:
    """Orthonormal basis ``(n, n - 1)`` of the vectors whose entries sum to zero.

    Relative quantities (channel gains, angle offsets) are fitted in this basis, so the
    unidentifiable common part stays fixed by construction.
    """
    q, _ = np.linalg.qr(np.vstack([np.ones(n), np.eye(n)[: n - 1]]).T)
    return q[:, 1:]


def channel_changes(
    gain: FloatArray,
    gain_std: FloatArray,
    transmission_angle: FloatArray | None = None,
    efficiency: FloatArray | None = None,
    transmission_angle_std: FloatArray | None = None,
    efficiency_std: FloatArray | None = None,
) -> dict[str, Any]:
    """The camera-model fields a channel calibration sets: the fitted ``gain`` (and
    ``transmission_angle`` [rad], ``efficiency`` when fitted), ``instrumental_dop_std``,
    the camera-fixed polarization [-, 1-sigma per Stokes component] that gains known to
    ``gain_std`` leave, and with the angles' and efficiencies' standard errors
    ``instrumental_mixing_std`` (:func:`mixing_std`; docs/measurement.md §12).

    A relative gain error ``e_k`` of channel k adds ``(e_0 - e_90)/2`` to ``S1/S0`` and
    ``(e_45 - e_135)/2`` to ``S2/S0``; with independent errors of 1-sigma ``s_k`` each
    component has ``sqrt(s_a^2 + s_b^2)/2``, whose mean square over the two is
    ``mean(s^2)/2``. Left out when a standard error is unknown (NaN).
    """
    changes: dict[str, Any] = {"gain": gain.copy()}
    if transmission_angle is not None:
        changes["transmission_angle"] = transmission_angle.copy()
    if efficiency is not None:
        changes["efficiency"] = efficiency.copy()
    rel = np.asarray(gain_std, dtype=float) / np.asarray(gain, dtype=float)
    if np.all(np.isfinite(rel)):
        changes["instrumental_dop_std"] = float(np.sqrt(np.mean(rel**2) / 2.0))
    if (transmission_angle is not None and efficiency is not None
            and transmission_angle_std is not None and efficiency_std is not None):  # fmt: skip
        mixing = mixing_std(gain, transmission_angle, efficiency, transmission_angle_std,
                            efficiency_std)  # fmt: skip
        if np.isfinite(mixing):
            changes["instrumental_mixing_std"] = mixing
    return changes


def provenance(kind: str, method: str, n_images: int, **figures: Any) -> dict[str, Any]:
    """The provenance record of a calibration: kind, UTC date, method, images, fit figures."""
    return {
        "kind": kind,
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "method": method,
        "n_images": int(n_images),
        **figures,
    }
