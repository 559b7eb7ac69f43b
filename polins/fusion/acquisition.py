"""Backend-neutral robust start: the yaw offsets of the headings and their consensus.

Both backends acquire the yaw by consensus (docs/filter.md §7.1): each yaw / sun
measurement gives the yaw rotation that zeroes its residual at the estimate of its time
(:func:`yaw_offset`), and the yaw is set only when enough of them agree
(:func:`consensus`). The ESKF runs this online (:mod:`polins.fusion.eskf.acquisition`),
the graph on its dead-reckoned keyframes before the solve
(:mod:`polins.fusion.graph.problem`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from polins.frames import wrap_angle, yaw_from_rot_nb
from polins.fusion.items import MeasurementItem, item_model
from polins.fusion.measurement import yaw_from_sun

FloatArray = NDArray[np.float64]


def yaw_offset(
    item: MeasurementItem,
    mat_nb: FloatArray,
    vel_n: FloatArray | None,
    tilt_coupling: bool,
    tilt_cov: FloatArray | None = None,
) -> tuple[float, float, FloatArray]:
    """The yaw rotation [rad] that zeroes the residual of a yaw / sun ``item`` at the
    attitude ``mat_nb``, its 1-sigma [rad] and its tilt gain ``a`` (2,) [-].

    The sigma is the item's (for a sun vector divided by the cosine of the sun elevation).
    A tilt-coupled yaw (docs/measurement.md, tilt coupling) also implies a yaw that moves
    by ``-(H_tilt / H_yaw) dtheta`` with the estimate's tilt error ``dtheta``: with
    ``tilt_cov`` (the 2 x 2 covariance [rad^2] of the navigation-frame tilt errors about
    East and North) that part is added in quadrature (docs/filter.md §7.1). The yaw set by
    the offset is then in error by ``-a . dtheta`` plus the item's noise (``a`` zero for a
    sun vector, whose tilt part is not modelled here).
    """
    gain = np.zeros(2)
    if item.kind == "yaw":
        # one step for the yaw of body x (exact), three Newton steps with the tilt
        # coupling (the model depends on the prior's tilt)
        delta, std = 0.0, item.std
        coupled = tilt_coupling and item.sun_n is not None
        for _ in range(3 if coupled else 1):
            mat = Rotation.from_rotvec([0.0, 0.0, delta]).as_matrix() @ mat_nb
            lin = item_model(item, mat, vel_n, tilt_coupling)
            delta += float(lin.residual[0] / lin.H[0, 2])
        if coupled:
            gain = lin.H[0, 0:2] / lin.H[0, 2]  # the last step's, at the converged yaw
        if coupled and tilt_cov is not None:
            std = math.hypot(std, math.sqrt(max(float(gain @ tilt_cov @ gain), 0.0)))
        return float(wrap_angle(delta)), std, gain
    s_n = np.asarray(item.sun_n, dtype=float)
    s_n = s_n / np.linalg.norm(s_n)
    rot0 = Rotation.from_matrix(mat_nb)
    yaw_meas = yaw_from_sun(rot0, item.sun_b, s_n)  # type: ignore[arg-type]
    std = item.std / max(float(np.hypot(s_n[0], s_n[1])), 1e-3)
    return float(wrap_angle(yaw_meas - yaw_from_rot_nb(rot0))), std, gain


def consensus(
    offsets: FloatArray, stds: FloatArray, k: int
) -> tuple[float, float, NDArray[np.int_]] | None:
    """The largest group of yaw offsets that agree, if it has at least ``k`` members.

    Parameters
    ----------
    offsets, stds : (M,) ndarray
        Yaw offsets and their 1-sigmas [rad].
    k : int
        Least group size.

    Returns
    -------
    (mean, std, members) or None
        The inverse-variance weighted mean offset [rad] (wrapped) and its 1-sigma [rad],
        and the indices of the group: the offsets within ``3 sqrt(s_i^2 + s_j^2)`` of the
        group's seed ``i`` (the seed giving the largest group, the earliest on a tie).
    """
    if offsets.size < k:
        return None
    diff = wrap_angle(offsets[None, :] - offsets[:, None])  # [i, j]: o_j - o_i
    agree = np.abs(diff) <= 3.0 * np.hypot(stds[:, None], stds[None, :])
    sizes = agree.sum(axis=1)
    seed = int(np.argmax(sizes))
    if sizes[seed] < k:
        return None
    members = np.flatnonzero(agree[seed])
    w = 1.0 / stds[members] ** 2
    mean = offsets[seed] + float(np.sum(w * diff[seed, members]) / np.sum(w))
    return float(wrap_angle(mean)), float(1.0 / math.sqrt(np.sum(w))), members
