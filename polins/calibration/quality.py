"""Calibration check: how well a camera file explains a set of images.

Two figures, both computed by the same Stokes step as the measurement chain
(:func:`polins.compass.polarimetry.stokes_from_channels`, docs/model.md §7.2-7.3):

* the **redundancy residual** ``nu``: four channels measure three Stokes components, and the
  combination left over is blind to any incoming light. Its RMS over the declared noise
  ``sqrt(read_noise^2 + I/G_e)`` (the camera file's) is about 1 when gains, efficiencies,
  angles, dark offsets and the noise model are right; well above 1 is a calibration error
  (or a noise model that is too optimistic);
* on images of **unpolarized** light (flat frames), the **residual polarization**: the DoP of
  the Stokes vector summed over all used pixels and images, which is zero for a right
  calibration; a gain error of x % shows as a DoP of about x/2 %.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from polins.calibration.images import channel_stack
from polins.compass.camera import fov_mask
from polins.compass.polarimetry import stokes_from_channels, stokes_noise_variance
from polins.models import CameraModel

__all__ = ["CheckReport", "check", "mosaic_pairing"]

PAIRING_RATIO = 0.5  # another pairing's residual below this fraction of the file's: flagged


def mosaic_pairing(channels: ArrayLike, used: ArrayLike, cam: CameraModel) -> str:
    """Check the mosaic layout from polarized data: "" when it holds, else a sentence.

    Orthogonal channels sum to S0 (``I_0 + I_90 = I_45 + I_135`` for any polarization, up to
    the channel gains), so of the three ways to pair the four mosaic positions the true one
    leaves the smallest residual, and a wrong pairing leaves the polarized signal. ``channels``
    ``(..., 4)`` [DN] are ordered by the file's labels, ``used`` selects the superpixels
    (images of a polarized scene: a clear sky). Which channel of a pair is which (0 vs 90
    deg) is not seen here: that turns every angle of polarization by 90 deg.
    """
    ch = np.asarray(channels, dtype=float)[np.asarray(used, dtype=bool)]
    if ch.shape[0] == 0:
        return ""
    labels = np.asarray(cam.nominal_angle_deg, dtype=float)
    pairings = [((0, 2), (1, 3)), ((0, 1), (2, 3)), ((0, 3), (1, 2))]  # the file's first
    rms = [float(np.sqrt(np.mean((ch[:, a].sum(-1) - ch[:, b].sum(-1)) ** 2)))
           for a, b in pairings]  # fmt: skip
    best = int(np.argmin(rms))
    if best == 0 or rms[best] >= PAIRING_RATIO * rms[0]:
        return ""
    (a0, a1), (b0, b1) = pairings[best]
    return (
        f"the data pair the channels labelled {labels[a0]:g} and {labels[a1]:g} deg (and "
        f"{labels[b0]:g}, {labels[b1]:g}) as orthogonal: residual {rms[best]:.3g} DN against "
        f"{rms[0]:.3g} DN for the file's layout; check sensor.mosaic_layout_deg"
    )


@dataclass(frozen=True)
class CheckReport:
    """How well a camera model explains a set of images.

    Attributes
    ----------
    n_images, n_pixels : int
        Images and superpixels (per image) used.
    redundancy_rms_dn : float
        RMS redundancy residual [DN].
    noise_declared_dn : float
        RMS per-channel noise the camera file declares at the images' levels [DN].
    noise_ratio : float
        ``redundancy_rms_dn / noise_declared_dn`` (about 1 for a right calibration).
    flagged_fraction : float
        Fraction of superpixels whose residual exceeds 4 declared sigmas (about 6e-5 for
        Gaussian noise).
    residual_dop : float
        DoP of the Stokes vector summed over all used pixels and images [-]: meaningful on
        unpolarized frames only (``unpolarized=True``), NaN otherwise.
    layout_note : str
        "" when the file's mosaic layout pairs the orthogonal channels as the data do; else
        which channels the data pair (:func:`mosaic_pairing`).
    """

    n_images: int
    n_pixels: int
    redundancy_rms_dn: float
    noise_declared_dn: float
    noise_ratio: float
    flagged_fraction: float
    residual_dop: float
    layout_note: str = ""

    def summary(self) -> str:
        """One line per figure, for the command line."""
        lines = [
            f"images: {self.n_images}, superpixels used per image: {self.n_pixels}",
            f"redundancy residual: {self.redundancy_rms_dn:.3g} DN RMS against "
            f"{self.noise_declared_dn:.3g} DN declared noise (ratio {self.noise_ratio:.2f}; "
            "about 1 for a right calibration)",
            f"pixels beyond 4 sigma: {100 * self.flagged_fraction:.3g}%",
        ]
        if self.layout_note:
            lines.append(f"mosaic layout: {self.layout_note}")
        if np.isfinite(self.residual_dop):
            lines.append(
                f"residual polarization on the unpolarized frames: DoP {100 * self.residual_dop:.3g}%"
            )
        return "\n".join(lines)


def check(
    cam: CameraModel,
    raws: Sequence[ArrayLike] | ArrayLike,
    *,
    unpolarized: bool = False,
    s0_min_dn: float = 10.0,
) -> CheckReport:
    """Score the camera model ``cam`` on images (docs/calibrate.md#check).

    Parameters
    ----------
    cam : CameraModel
        The camera file to check.
    raws : array_like, (m, H, W)
        Raw mosaics [DN]: sky images, or frames of unpolarized light.
    unpolarized : bool
        The images show unpolarized light (flat frames): report the residual DoP.
    s0_min_dn : float
        Superpixels darker than this S0 [DN] are not used.

    Returns
    -------
    CheckReport

    Raises
    ------
    UserInputError
        Wrong shapes (from the channel split).
    """
    stack = channel_stack(raws, cam, what="check")
    stokes, nu = stokes_from_channels(stack.channels, cam)  # (m, Hs, Ws, 3), (m, Hs, Ws)
    used = fov_mask(cam)[None] & ~stack.saturated & (stokes[..., 0] >= s0_min_dn)
    var = np.broadcast_to(stokes_noise_variance(cam, stokes[..., 0]), nu.shape)
    nu_used, var_used = nu[used], var[used]
    n_used = int(used.sum())
    rms = float(np.sqrt(np.mean(nu_used**2))) if n_used else float("nan")
    declared = float(np.sqrt(np.mean(var_used))) if n_used else float("nan")
    flagged = float(np.mean(nu_used**2 > 16.0 * var_used)) if n_used else float("nan")
    residual_dop = float("nan")
    if unpolarized and n_used:
        total = stokes[used].sum(axis=0)
        residual_dop = float(np.hypot(total[1], total[2]) / total[0])
    layout = "" if unpolarized else mosaic_pairing(stack.channels, used, cam)
    return CheckReport(
        n_images=stack.n_images,
        n_pixels=n_used // max(stack.n_images, 1),
        redundancy_rms_dn=rms,
        noise_declared_dn=declared,
        noise_ratio=rms / declared,
        flagged_fraction=flagged,
        residual_dop=residual_dop,
        layout_note=layout,
    )
