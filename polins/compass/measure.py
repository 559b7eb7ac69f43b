"""The polarization compass's entry point: ``polins.measure``, raw DoFP image -> heading.

Two methods return the same :class:`~polins.compass.measurement.Measurement`:

``"compensated"`` (default)
    Joint maximum likelihood of the sun azimuth (and zenith, unless fixed from the
    ephemeris) and the direct-sunlight coefficient epsilon over the whole image
    (docs/model.md §9.2), with the compensation angle taken from the estimated sun, not the
    INS prior, and the Berry four-neutral-point sky with its separation fitted
    (docs/model.md §6.3; ``sky_model="rayleigh"`` for the Rayleigh sky). Gauss-Newton runs on a pixel subsample and finishes with one Gauss-Newton
    step on all valid pixels.
``"traditional"``
    Gain-corrected least-squares Stokes, E-vectors built in the camera frame and rotated
    with the prior roll/pitch, weighted eigen sun vector (docs/model.md §9.1), eigen-gap
    sandwich covariance (docs/model.md §10.2).

The paper's Algorithm 1 is not a method: it is reproduced in :mod:`polins.sim.algorithm1`.

The chain itself is :mod:`polins.compass.chain`; the options are
:class:`~polins.compass.measurement.MeasureOptions`.
"""

from __future__ import annotations

import warnings
from typing import Any

from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from polins.compass.chain import measure_image
from polins.compass.measurement import (
    METHODS,
    NOISE_RATIO_BAND,
    Measurement,
    MeasurementMaps,
    MeasureOptions,
    NoiseModelWarning,
    check_method,
    measure_options,
)
from polins.models import CameraModel

__all__ = [
    "METHODS",
    "MeasureOptions",
    "Measurement",
    "MeasurementMaps",
    "NoiseModelWarning",
    "check_measure_options",
    "measure",
    "measure_options",
    "measure_with_maps",
]


def measure(
    raw: ArrayLike,
    cam: CameraModel,
    *,
    sun_n: ArrayLike | None = None,
    rot_nb_prior: Rotation | None = None,
    method: str = "compensated",
    sun_azimuth_b_prior: float | None = None,
    **options: Any,
) -> Measurement:
    """Heading and sun vector from one raw DoFP image (docs/model.md §7-10).

    Parameters
    ----------
    raw : array_like, (H, W)
        Full-resolution raw mosaic of shape ``cam.shape``, unsigned integer (float mosaics are
        accepted too; their non-finite pixels are masked). Integer mosaics are processed in
        float32, float mosaics in float64.
    cam : CameraModel
    sun_n : array_like, (3,), optional
        Unit ENU sun vector from the ephemeris (apparent position). Without it the image
        gives the sun in the body frame only (``sun_azimuth_b``, ``sun_b``, ``yaw`` NaN;
        docs/measurement.md §11), with the zenith estimated.
    rot_nb_prior : Rotation, optional
        Prior body -> ENU attitude, required with ``sun_n``. Its roll and pitch rotate the
        E-vectors into the level frame; its yaw is used only near the horizon (180 deg
        choice) and by ``yaw_gate``. Without ``sun_n`` only its tilt is used; None means a
        level body.
    method : {"compensated", "traditional"}
    sun_azimuth_b_prior : float, optional
        Without ``sun_n``: a prior body-frame sun azimuth [rad] (e.g. the previous image's)
        that chooses the 180 deg branch when the elevation and the sky brightness cannot.
    **options
        Fields of :class:`~polins.compass.measurement.MeasureOptions`.

    Returns
    -------
    Measurement
        ``ok=False`` with a reason when the image cannot give a heading. ``ok=True`` with a
        reason when the compensated estimate fell back to ``"traditional"`` or the 180 deg
        branch is ambiguous.

    Warns
    -----
    NoiseModelWarning
        The measured noise is outside :data:`NOISE_RATIO_BAND` times the camera file's.

    Raises
    ------
    ValueError
        Wrong image shape or dtype, bad ``sun_n`` or ``rot_nb_prior``, unknown method.
    TypeError
        Unknown option.
    """
    return _dispatch(
        raw, cam, sun_n, rot_nb_prior, method, sun_azimuth_b_prior, options, maps=False
    )[0]


def measure_with_maps(
    raw: ArrayLike,
    cam: CameraModel,
    *,
    sun_n: ArrayLike | None = None,
    rot_nb_prior: Rotation | None = None,
    method: str = "compensated",
    sun_azimuth_b_prior: float | None = None,
    **options: Any,
) -> tuple[Measurement, MeasurementMaps | None]:
    """:func:`measure` plus per-pixel images (AoP, DoP, valid mask, residual) for plots and
    diagnostics; slower. The maps are None when the image was refused before the Stokes step.
    """
    return _dispatch(raw, cam, sun_n, rot_nb_prior, method, sun_azimuth_b_prior, options, maps=True)


def check_measure_options(method: str, options: dict[str, Any]) -> MeasureOptions:
    """Check a method and its keyword options once, before any image (docs/faults.md).

    Returns the :class:`~polins.compass.measurement.MeasureOptions` they give.

    Raises
    ------
    ValueError
        Unknown method or an impossible value.
    TypeError
        Unknown option.
    """
    check_method(method)
    return measure_options(**options)


def _dispatch(
    raw: ArrayLike,
    cam: CameraModel,
    sun_n: ArrayLike | None,
    rot_nb_prior: Rotation | None,
    method: str,
    sun_azimuth_b_prior: float | None,
    options: dict[str, Any],
    *,
    maps: bool,
) -> tuple[Measurement, MeasurementMaps | None]:
    check_method(method)
    opt: MeasureOptions = measure_options(**options)
    result = measure_image(
        raw,
        cam,
        sun_n,
        rot_nb_prior,
        opt,
        method=method,
        maps=maps,
        sun_azimuth_b_prior=sun_azimuth_b_prior,
    )
    m = result[0]
    low, high = NOISE_RATIO_BAND
    # Noise-free input (a simulation: ratio zero to rounding) is not warned about.
    if m.ok and m.noise_ratio > 1e-3 and not low <= m.noise_ratio <= high:
        warnings.warn(
            f"measured noise is {m.noise_ratio:.2f} x the camera file's noise model (outside "
            f"[{low:g}, {high:g}]): check read_noise_dn, the channel gains and dark offsets",
            NoiseModelWarning,
            stacklevel=3,
        )
    return result
