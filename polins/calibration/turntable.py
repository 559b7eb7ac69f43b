"""Turntable score: how well a camera measures relative headings over a sequence of known turns.

A turntable sequence (the camera looking up, turned about the vertical by known angles
between images) tests a camera file without a clock or a site (docs/calibrate.md#check).
Each image is measured sun-free (``polins.measure`` without ``sun_n``): the sun's azimuth
in the body frame. The body's relative heading is minus its change. The truth is the turn
plus the sun's azimuth change during the sequence, which is unknown without a clock: an
offset and a drift linear in the images' clock (their time stamps, a frame counter, or
their order) are fitted and taken out, and what remains is the error. A narrow field
cannot tell the sun from the antisun, so errors are taken modulo 180 deg.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.compass.measure import NoiseModelWarning, measure
from polins.errors import UserInputError
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = ["TurntableScore", "relative_heading_errors", "score_turntable"]


@dataclass(frozen=True)
class TurntableScore:
    """Relative-heading errors of a turntable sequence.

    Attributes
    ----------
    error : (m,)
        Heading error [rad] of each image after the fitted offset and drift (NaN where the
        image gave no heading).
    sigma : (m,)
        The measurement's heading sigma [rad] (``sun_azimuth_b_std``).
    rmse : float
        RMS of ``error`` [rad] over the images with a heading.
    rms_z : float
        RMS of ``error / sigma`` [-] (near 1 when the sigma is honest; the fitted offset and
        drift take two degrees of freedom, so it is scaled by ``sqrt(n / (n - 2))``).
    max_z : float
        Largest ``|error / sigma|`` [-].
    n_ok : int
        Images with a heading.
    ms_per_image : float
        Mean measurement time per image [ms], the first image excluded (its call builds
        the per-camera caches).
    """

    error: FloatArray
    sigma: FloatArray
    rmse: float
    rms_z: float
    max_z: float
    n_ok: int
    ms_per_image: float

    def summary(self) -> str:
        """One line: RMSE [deg], RMS(err/sigma), max, images and time."""
        return (
            f"relative heading over {self.n_ok} images: RMSE {np.degrees(self.rmse):.3f} deg, "
            f"RMS(err/sigma) {self.rms_z:.2f}, max {self.max_z:.1f} sigma "
            f"({self.ms_per_image:.1f} ms per image)"
        )


def relative_heading_errors(heading: ArrayLike, turns: ArrayLike, clock: ArrayLike) -> FloatArray:
    """Errors [rad] of relative headings against known turns, modulo pi, after an offset and
    a drift linear in ``clock`` are fitted and taken out.

    Parameters
    ----------
    heading : array_like, (m,)
        Measured heading of each image [rad] (NaN: none).
    turns : array_like, (m,)
        Turn of the camera about the vertical [rad], counter-clockwise seen from above (the
        body's yaw change; with a camera looking up and ``mat_bc`` identity, the turn from
        +u towards +v of docs/conventions.md).
    clock : array_like, (m,)
        Time stamp or counter of each image (any unit).
    """
    h = np.asarray(heading, dtype=float)
    d = h - np.asarray(turns, dtype=float)
    t = np.asarray(clock, dtype=float)
    ok = np.isfinite(d)
    if ok.sum() < 3:
        raise UserInputError(f"turntable score: {int(ok.sum())} images with a heading; need 3")
    t = (t - t[ok].mean()) / max(float(np.ptp(t[ok])), 1e-300)
    design = np.column_stack([np.ones_like(t), t])
    ref = d[ok][0]
    wrapped = np.mod(d - ref + 0.5 * np.pi, np.pi) - 0.5 * np.pi  # about the first heading
    for _ in range(3):  # the fit and the branch modulo pi settle together
        coef, *_ = np.linalg.lstsq(design[ok], wrapped[ok], rcond=None)
        fit = design @ coef
        wrapped = fit + np.mod(wrapped - fit + 0.5 * np.pi, np.pi) - 0.5 * np.pi
    return np.where(ok, wrapped - fit, np.nan)


def score_turntable(
    raws: Sequence[ArrayLike] | ArrayLike,
    cam: CameraModel,
    turns: ArrayLike,
    clock: ArrayLike | None = None,
    **options: object,
) -> TurntableScore:
    """Measure each image sun-free and score the relative headings against ``turns`` [rad].

    ``clock`` (default: the image order) carries the drift of the sun's azimuth; ``options``
    go to ``polins.measure``. The noise-model warning is not repeated per image.
    """
    import time

    turns_arr = np.asarray(turns, dtype=float)
    images = list(raws) if isinstance(raws, Sequence) else list(np.asarray(raws))
    m = len(images)
    if turns_arr.shape != (m,):
        raise UserInputError(f"turntable score: {turns_arr.size} turns for {m} images")
    heading, sigma, times = np.full(m, np.nan), np.full(m, np.nan), []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoiseModelWarning)
        for j, raw in enumerate(images):
            start = time.perf_counter()
            meas = measure(raw, cam, **options)  # type: ignore[arg-type]
            times.append(time.perf_counter() - start)
            if meas.ok:
                heading[j], sigma[j] = -meas.sun_azimuth_b, meas.sun_azimuth_b_std
    err = relative_heading_errors(heading, turns_arr, np.arange(m) if clock is None else clock)
    ok = np.isfinite(err)
    n = int(ok.sum())
    z = err[ok] / sigma[ok]
    return TurntableScore(
        error=err,
        sigma=sigma,
        rmse=float(np.sqrt(np.mean(err[ok] ** 2))),
        rms_z=float(np.sqrt(np.sum(z**2) / max(n - 2, 1))),
        max_z=float(np.max(np.abs(z))),
        n_ok=n,
        ms_per_image=1e3 * float(np.mean(times[1:] if m > 1 else times)),
    )
