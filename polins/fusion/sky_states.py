"""The measurement-side error states of the sky: the error of an approximate site, the sun's azimuth without a clock, and a heading-measurement bias.

Each is an error-state block of the ESKF (:mod:`polins.fusion.eskf.blocks`); this module
holds their mathematics (docs/filter.md, "Approximate site", "No clock", "Heading-measurement
bias"):

* **Site error**: ``(d_lat, d_lon)`` [rad], true minus the site the ENU sun vectors were
  computed at, turns the local ENU frame by ``psi_n = S(lat) (d_lat, d_lon)``
  (:func:`site_frame_jacobian`), so the sun seen by the camera is ``sun_n + [sun_n x]
  psi_n``: exactly the form of an attitude error, and the columns of ``psi_n`` in a heading
  measurement are its attitude columns (:func:`sun_attitude_columns`). The error is common
  to every image, so ``psi_n`` is a state (three random constants), not an inflation of R:
  an R inflation averages down over the images while the error does not. Its three
  components are independent with the 1-sigmas of :func:`site_rotation_std`, which bound
  ``S Sigma S^T``: the exact model links the tilt part of ``psi_n`` (seen against gravity)
  to its heading part through ``d_lon``, so that a tilt error of the filter (accelerometer,
  camera mounting) would leak into the heading; the bound drops that link on purpose.
* **Sun azimuth** (no clock): the sun's ENU azimuth and its rate are states; a
  ``"sun_azimuth"`` measurement sees them through ``dh / d azimuth = -H_theta[2]``
  (:func:`sun_azimuth_jacobian`).
* **Heading-measurement bias** ``b`` [rad], the measured heading minus the true one, a
  first-order Gauss-Markov process: it enters every heading measurement as a rotation of
  the measured sun about the vertical, ``d h / d b = H_theta[2]`` (:func:`heading_bias_jacobian`).
  By default its 1-sigma comes from the images: each heading row's ``yaw_std_model`` is
  its part correlated from image to image, the state's variance follows the median of
  their squares (:class:`ModelPart`) and each row keeps the rest of its sigma
  (:func:`without_bias_part`).
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections import deque
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from polins.fusion.items import HEADING_KINDS, MeasurementItem
from polins.fusion.measurement import Linearized

FloatArray = NDArray[np.float64]


def site_frame_jacobian(lat: float) -> FloatArray:
    """``d psi_n / d (lat, lon)``, (3, 2): the rotation of the local ENU frame [rad] per
    radian of latitude and longitude at latitude ``lat`` [rad].

    North by ``d_lat`` turns the frame about East by ``-d_lat``; East by ``d_lon`` turns it
    about the Earth's axis, ``(0, cos lat, sin lat)`` in ENU, by ``d_lon``.
    """
    return np.array([[-1.0, 0.0], [0.0, math.cos(lat)], [0.0, math.sin(lat)]])


def site_frame_cov(lat: float, site_std: float) -> FloatArray:
    """Covariance (3, 3) [rad^2] of the ENU frame rotation for a site whose latitude and
    longitude each have the 1-sigma ``site_std`` [rad]."""
    S = site_frame_jacobian(lat)
    return (S @ S.T) * site_std**2


def sun_attitude_columns(item: MeasurementItem, lin: Linearized) -> FloatArray:
    """The attitude columns ``d h / d theta`` (dim, 3) of a heading item's model in its
    dependence on the ENU sun vector: for a sun vector and a tilt-coupled yaw ``lin.H[:,
    0:3]``; for a yaw with ``sun_n`` the tilt-coupled form with the prior at the estimate,
    ``(-s_x s_z, -s_y s_z, s_x^2 + s_y^2) / (s_x^2 + s_y^2)``; for a yaw without ``sun_n``
    the vertical only, ``(0, 0, 1)``; zero for the other kinds."""
    out = np.zeros((lin.H.shape[0], 3))
    if item.kind == "sun":
        out[:] = lin.H[:, 0:3]
    elif item.kind == "yaw" and item.sun_n is not None:
        s = item.sun_n
        h2 = float(s[0] * s[0] + s[1] * s[1])
        out[0] = (-s[0] * s[2] / h2, -s[1] * s[2] / h2, 1.0)
    elif item.kind == "yaw":
        out[0, 2] = 1.0
    return out


def site_rotation_std(lat: float, site_std: float) -> tuple[float, float, float]:
    """1-sigmas [rad] of the three independent components of the ENU frame rotation of a
    site whose latitude and longitude have the 1-sigma ``site_std`` [rad], at latitude
    ``lat`` [rad]: ``(site_std, sqrt(2) site_std |cos lat|, sqrt(2) site_std |sin lat|)``.

    Their covariance bounds the exact one, ``S S^T site_std^2`` (:func:`site_frame_cov`):
    the difference is ``site_std^2 (0, cos lat, -sin lat)(0, cos lat, -sin lat)^T >= 0``.
    """
    r2 = math.sqrt(2.0) * site_std
    return (site_std, r2 * abs(math.cos(lat)), r2 * abs(math.sin(lat)))


def heading_bias_jacobian(item: MeasurementItem, lin: Linearized) -> FloatArray:
    """Column (dim, 1) of the heading-measurement bias: ``H_theta[:, 2]`` for the heading
    kinds (1 for a yaw, -1 for a no-clock sun azimuth), zero for the others."""
    if item.kind not in HEADING_KINDS:
        return np.zeros((lin.H.shape[0], 1))
    return lin.H[:, 2:3].copy()


def sun_azimuth_jacobian(item: MeasurementItem, lin: Linearized) -> FloatArray:
    """Column (dim, 1) of the sun's ENU azimuth state in a ``"sun_azimuth"`` item,
    ``-H_theta[:, 2]`` (docs/filter.md, "No clock"); zero for the other kinds."""
    if item.kind != "sun_azimuth":
        return np.zeros((lin.H.shape[0], 1))
    return -lin.H[:, 2:3]


def link_acquired_yaw(
    P: FloatArray,
    index: Mapping[str, slice],
    sun_n: FloatArray | None = None,
    yaw: int = 2,
    tilt_gain: FloatArray | None = None,
) -> FloatArray:
    """The covariance after a yaw acquisition from headings that carry heading offsets.

    The yaw was set to agree with the headings, so its error is the acquisition's own
    (``P[yaw, yaw]`` on entry, uncorrelated) minus the offsets: ``e = n - c . x`` with ``c``
    1 on the heading bias and, on the site rotation ``site_rot_n``, the heading's
    sensitivity to a frame rotation: ``(-s_x s_z, -s_y s_z, s_x^2 + s_y^2) / (s_x^2 +
    s_y^2)`` for the ENU sun ``sun_n`` of the headings, ``(0, 0, 1)`` without it, and on
    the tilt (the attitude error's East and North, rows ``yaw - 2 .. yaw - 1``) the
    tilt-coupled headings' ``tilt_gain`` (docs/filter.md §7.1). ``P`` becomes ``A P A^T``
    for that linear map (the offsets' own rows unchanged). Without such states ``P`` is
    returned unchanged.
    """
    coupled = tilt_gain is not None and bool(np.any(tilt_gain))
    if "heading_bias" not in index and "site_rot_n" not in index and not coupled:
        return P
    c = np.zeros(P.shape[0])
    if coupled:
        c[yaw - 2 : yaw] = tilt_gain
    if "heading_bias" in index:
        c[index["heading_bias"]] = 1.0
    if "site_rot_n" in index:
        s = sun_n
        h2 = 0.0 if s is None else float(s[0] * s[0] + s[1] * s[1])
        c[index["site_rot_n"]] = (0.0, 0.0, 1.0) if s is None or h2 < 1e-12 else (
            -s[0] * s[2] / h2, -s[1] * s[2] / h2, 1.0)  # fmt: skip
    row = -(c @ P)
    var = float(P[yaw, yaw] + c @ P @ c)
    P = P.copy()
    P[yaw, :] = row
    P[:, yaw] = row
    P[yaw, yaw] = var
    return P


def without_bias_part(item: MeasurementItem, var: float) -> MeasurementItem:
    """A heading item without the part of its sigma a heading-bias state of variance ``var``
    [rad^2] carries: ``min(item.model_std^2, var)``, at least 1 % of the heading variance
    left (docs/filter.md §5.7).

    A yaw or sun azimuth loses it from ``std``; a sun vector from its azimuth displacement,
    the heading variance times ``cos^2`` of the sun's body elevation (along the unit
    tangent of the body azimuth, as :func:`polins.fusion.measurement.sun_direction_cov_b`).
    Other items and items without a model part are returned unchanged.
    """
    part = min(item.model_std**2, var)
    if item.kind not in HEADING_KINDS or not part > 0.0 or not item.valid:
        return item
    if item.kind != "sun":
        return dataclasses.replace(item, std=math.sqrt(max(item.std**2 - part, 0.01 * item.std**2)))
    assert item.sun_b is not None  # a valid sun item
    s = item.sun_b / np.linalg.norm(item.sun_b)
    horiz = math.hypot(float(s[0]), float(s[1]))
    if horiz < 1e-9:  # the sun at the body zenith: no azimuth
        return item
    u_a = np.array([-s[1], s[0], 0.0]) / horiz
    cov = item.std**2 * np.eye(3) if item.cov_b is None else item.cov_b
    var_a = float(u_a @ cov @ u_a)
    cut = min(part * horiz * horiz, 0.99 * var_a)
    return dataclasses.replace(item, cov_b=cov - cut * np.outer(u_a, u_a))


class ModelPart:
    """The variance of the default heading-bias state, from the images' model parts.

    With ``FuseConfig.heading_bias == "model"`` (docs/filter.md §5.7) the Gauss-Markov
    bias (correlation time ``tau_s`` [s]) has the variance ``var``: the median of the
    squared ``model_std`` of the last ``window`` heading items (0 for those without a
    correlated model part). Each heading item raises the state's variance by the growth of ``var`` (a new, independent part)
    and sets its noise density to ``2 var / tau_s``; the item keeps the rest of its sigma
    (:func:`without_bias_part`).
    """

    def __init__(self, tau_s: float, window: int = 256) -> None:
        self.tau_s = float(tau_s)
        self.parts: deque[float] = deque(maxlen=window)  # in arrival order
        self.ordered: list[float] = []  # the same, sorted (a running median per update)
        self.var = 0.0

    def take(self, item: MeasurementItem, P: FloatArray, i: int) -> tuple[MeasurementItem, float]:
        """The item without its carried part, and the bias state's noise density
        [rad^2/s]; ``P[i, i]`` (the bias state's variance) is raised in place."""
        part = item.model_std**2
        if len(self.parts) == self.parts.maxlen:
            del self.ordered[bisect.bisect_left(self.ordered, self.parts[0])]
        self.parts.append(part)
        bisect.insort(self.ordered, part)
        n = len(self.ordered)
        var = (
            self.ordered[n // 2]
            if n % 2
            else 0.5 * (self.ordered[n // 2 - 1] + self.ordered[n // 2])
        )
        if var > self.var:
            P[i, i] += var - self.var
        self.var = var
        return without_bias_part(item, var), 2.0 * var / self.tau_s
