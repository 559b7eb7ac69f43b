"""The navigation state: one type for one time or many, and the one writer of the solution table.

Every backend (the ESKF, its smoother, the GTSAM graph) and the streaming loop report
:class:`NavState`; :func:`solution_table` turns it into the solution ``DataFrame`` whose
columns docs/filter.md lists. Sensor-error estimates travel as named blocks (``bg``,
``ba``, ``sg``, ``sa``, and whatever block a capability adds), each with its sigma, so a
new block reaches the table without touching this module.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.frames import euler_from_rot_nb, heading_deg_from_yaw

FloatArray = NDArray[np.float64]

NAV_BLOCKS = ("att", "vel", "pos")  # the error blocks with dynamics, in state order
_NAV_COLUMNS = {"vel": ("ve", "vn", "vu"), "pos": ("pe", "pn", "pu")}


def block_columns(name: str, size: int) -> tuple[str, ...]:
    """Solution-table columns of a sensor-error block: ``bg`` -> ``bgx, bgy, bgz``;
    a 1-element block keeps its name; other sizes get ``_0 .. _k``."""
    if size == 3:
        return tuple(f"{name}{ax}" for ax in "xyz")
    if size == 1:
        return (name,)
    return tuple(f"{name}_{i}" for i in range(size))


@dataclass(frozen=True, eq=False)
class NavState:
    """Navigation state and its uncertainty at one time (scalars) or N times (leading axis).

    Attributes
    ----------
    t : float or (N,) ndarray
        Time [s].
    rot_nb : Rotation
        Attitude, body FLU -> ENU (single, or N stacked).
    vel_n : (..., 3) ndarray
        ENU velocity relative to the Earth [m/s].
    lat, lon : float or (N,) ndarray
        Geodetic latitude and longitude [rad].
    alt_m : float or (N,) ndarray
        Height above the WGS-84 ellipsoid [m].
    errors : mapping of str to (..., k) ndarray
        Sensor-error estimates by block name (``bg`` [rad/s], ``ba`` [m/s^2], ``sg``,
        ``sa`` [-], ...), in state order.
    sigma : mapping of str to (..., k) ndarray
        1-sigma of every error block by name: ``att`` [rad] (attitude-error vector),
        ``vel`` [m/s], ``pos`` [m] (ENU), then the blocks of ``errors``. Empty when the
        state carries no uncertainty (a nominal state).
    att_cov : (..., 3, 3) ndarray or None
        Covariance of the attitude-error vector [rad^2] (gives the Euler-angle sigmas).
    yaw_aligned : bool or (N,) ndarray
        False while self-alignment still waits for its first heading (yaw columns NaN).
    """

    t: Any
    rot_nb: Rotation
    vel_n: FloatArray
    lat: Any
    lon: Any
    alt_m: Any
    errors: Mapping[str, FloatArray] = field(default_factory=dict)
    sigma: Mapping[str, FloatArray] = field(default_factory=dict)
    att_cov: FloatArray | None = None
    yaw_aligned: Any = True

    def __len__(self) -> int:
        return 1 if self.rot_nb.single else len(self.rot_nb)

    def at(self, i: int) -> NavState:
        """The i-th state of a batched state."""
        if self.rot_nb.single:
            raise TypeError("at() needs a batched NavState")
        return NavState(
            t=float(np.asarray(self.t)[i]),
            rot_nb=self.rot_nb[i],
            vel_n=np.asarray(self.vel_n)[i],
            lat=float(np.asarray(self.lat)[i]),
            lon=float(np.asarray(self.lon)[i]),
            alt_m=float(np.asarray(self.alt_m)[i]),
            errors={k: np.asarray(v)[i] for k, v in self.errors.items()},
            sigma={k: np.asarray(v)[i] for k, v in self.sigma.items()},
            att_cov=None if self.att_cov is None else np.asarray(self.att_cov)[i],
            yaw_aligned=bool(np.broadcast_to(self.yaw_aligned, (len(self),))[i]),
        )

    def take(self, index: ArrayLike) -> NavState:
        """The states ``index`` (integer positions) of a batched state, batched."""
        if self.rot_nb.single:
            raise TypeError("take() needs a batched NavState")
        idx = np.asarray(index, dtype=np.intp)
        return NavState(
            t=np.asarray(self.t)[idx],
            rot_nb=self.rot_nb[idx],
            vel_n=np.asarray(self.vel_n)[idx],
            lat=np.asarray(self.lat)[idx],
            lon=np.asarray(self.lon)[idx],
            alt_m=np.asarray(self.alt_m)[idx],
            errors={k: np.asarray(v)[idx] for k, v in self.errors.items()},
            sigma={k: np.asarray(v)[idx] for k, v in self.sigma.items()},
            att_cov=None if self.att_cov is None else np.asarray(self.att_cov)[idx],
            yaw_aligned=np.broadcast_to(self.yaw_aligned, (len(self),))[idx],
        )

    def batched(self) -> NavState:
        """The same state(s) with a leading axis (length 1 for a single state)."""
        if not self.rot_nb.single:
            return self
        return concatenate([self])

    def euler_std(self) -> FloatArray:
        """1-sigma of (yaw, pitch, roll) [rad], ``(..., 3)``, from ``att_cov``."""
        if self.att_cov is None:
            raise ValueError("this NavState carries no attitude covariance")
        yaw, pitch, _ = euler_from_rot_nb(self.rot_nb)
        return _euler_std(yaw, pitch, np.asarray(self.att_cov))

    def row(self) -> dict[str, float]:
        """A single state as one row of the solution table."""
        table = solution_table(self.batched())
        return {str(k): float(v) for k, v in table.iloc[0].items()}


def concatenate(states: Sequence[NavState]) -> NavState:
    """Stack single (or batched) states along a leading time axis."""
    if not states:
        raise ValueError("concatenate needs at least one NavState")

    def stack(values: Sequence[Any]) -> FloatArray:
        return np.concatenate([np.atleast_1d(np.asarray(v, dtype=float)) for v in values])

    def stack_rows(values: Sequence[Any], k: int) -> FloatArray:
        return np.concatenate([np.asarray(v, dtype=float).reshape(-1, k) for v in values])

    first = states[0]
    cov = None
    if all(s.att_cov is not None for s in states):
        cov = np.concatenate([np.asarray(s.att_cov).reshape(-1, 3, 3) for s in states])
    return NavState(
        t=stack([s.t for s in states]),
        rot_nb=Rotation.concatenate([s.rot_nb for s in states]),
        vel_n=stack_rows([s.vel_n for s in states], 3),
        lat=stack([s.lat for s in states]),
        lon=stack([s.lon for s in states]),
        alt_m=stack([s.alt_m for s in states]),
        errors={
            k: stack_rows(
                [s.errors[k] for s in states],
                np.size(v) if first.rot_nb.single else np.shape(v)[-1],
            )
            for k, v in first.errors.items()
        },
        sigma={
            k: stack_rows(
                [s.sigma[k] for s in states], np.size(v) if first.rot_nb.single else np.shape(v)[-1]
            )
            for k, v in first.sigma.items()
        },
        att_cov=cov,
        yaw_aligned=np.concatenate(
            [np.broadcast_to(np.asarray(s.yaw_aligned, dtype=bool), (len(s),)) for s in states]
        ),
    )


def _euler_std(yaw: FloatArray, pitch: FloatArray, att_cov: FloatArray) -> FloatArray:
    """1-sigma of (yaw, pitch, roll) from the attitude-error covariance: sqrt diag(J P J^T),
    ``(..., 3)``, with ``J`` of :func:`euler_jacobian` row by row (no batched 3x3 products:
    this runs for every output row)."""
    p = np.asarray(att_cov)
    p00, p11, p22 = p[..., 0, 0], p[..., 1, 1], p[..., 2, 2]
    p01, p02, p12 = p[..., 0, 1], p[..., 0, 2], p[..., 1, 2]
    var = [
        a * a * p00 + b * b * p11 + c * c * p22 + 2.0 * (a * b * p01 + a * c * p02 + b * c * p12)
        for a, b, c in _euler_jacobian_rows(yaw, pitch)
    ]
    return np.sqrt(np.clip(np.stack(var, axis=-1), 0.0, None))


def _euler_jacobian_rows(yaw: ArrayLike, pitch: ArrayLike) -> list[tuple[Any, Any, Any]]:
    """The rows (yaw, pitch, roll) of :func:`euler_jacobian`, each as three arrays."""
    yaw = np.asarray(yaw, dtype=float)
    pitch = np.asarray(pitch, dtype=float)
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, tp = np.cos(pitch), np.tan(pitch)
    return [(cy * tp, sy * tp, 1.0), (-sy, cy, 0.0), (cy / cp, sy / cp, 0.0)]


def euler_jacobian(yaw: ArrayLike, pitch: ArrayLike) -> FloatArray:
    """``d(yaw, pitch, roll) / d(dtheta)`` for ``rot_true = exp(dtheta) rot_nb`` (ENU,
    ZYX Euler angles), ``(..., 3, 3)``; singular at pitch = +-90 deg."""
    rows = _euler_jacobian_rows(yaw, pitch)
    shape = np.shape(yaw)
    return np.stack([np.stack(np.broadcast_arrays(*r, np.zeros(shape))[:3], axis=-1)
                     for r in rows], axis=-2)  # fmt: skip


def solution_table(state: NavState) -> pd.DataFrame:
    """The solution table of a batched :class:`NavState` (docs/filter.md lists the columns).

    Columns: ``t, roll, pitch, yaw, heading_deg, roll_std, pitch_std, yaw_std``, the
    sensor-error blocks (``bgx .. baz`` first), their ``_std``, ``ve, vn, vu`` and sigmas,
    ``lat_deg, lon_deg, alt_m``, ``pe_std, pn_std, pu_std`` [m] and the quaternion
    ``qw, qx, qy, qz``. Angles in radians; the yaw columns are NaN before the yaw alignment.
    """
    state = state.batched()
    n = len(state)
    yaw, pitch, roll = euler_from_rot_nb(state.rot_nb)
    nan_yaw = ~np.broadcast_to(np.asarray(state.yaw_aligned, dtype=bool), (n,))
    std = (
        np.full((n, 3), np.nan)
        if state.att_cov is None
        else _euler_std(yaw, pitch, np.asarray(state.att_cov).reshape(n, 3, 3))
    )
    yaw = np.where(nan_yaw, np.nan, yaw)
    cols: dict[str, Any] = {
        "t": np.asarray(state.t, dtype=float),
        "roll": roll,
        "pitch": pitch,
        "yaw": yaw,
        "heading_deg": heading_deg_from_yaw(yaw),
        "roll_std": std[:, 2],
        "pitch_std": std[:, 1],
        "yaw_std": np.where(nan_yaw, np.nan, std[:, 0]),
    }
    for name, values in state.errors.items():
        values = np.asarray(values).reshape(n, -1)
        cols.update(zip(block_columns(name, values.shape[1]), values.T, strict=True))
    for name in state.errors:
        if name in state.sigma:
            sig = np.asarray(state.sigma[name]).reshape(n, -1)
            names = block_columns(name, sig.shape[1])
            cols.update(zip((f"{c}_std" for c in names), sig.T, strict=True))
    vel = np.asarray(state.vel_n).reshape(n, 3)
    cols.update(zip(_NAV_COLUMNS["vel"], vel.T, strict=True))
    if "vel" in state.sigma:
        sig = np.asarray(state.sigma["vel"]).reshape(n, 3)
        cols.update(zip((f"{c}_std" for c in _NAV_COLUMNS["vel"]), sig.T, strict=True))
    cols["lat_deg"] = np.degrees(np.asarray(state.lat, dtype=float))
    cols["lon_deg"] = np.degrees(np.asarray(state.lon, dtype=float))
    cols["alt_m"] = np.asarray(state.alt_m, dtype=float)
    if "pos" in state.sigma:
        sig = np.asarray(state.sigma["pos"]).reshape(n, 3)
        cols.update(zip((f"{c}_std" for c in _NAV_COLUMNS["pos"]), sig.T, strict=True))
    quat = state.rot_nb.as_quat()
    cols["qw"], cols["qx"], cols["qy"], cols["qz"] = quat[:, 3], quat[:, 0], quat[:, 1], quat[:, 2]
    # the columns are arrays made for this table or the state built for it: no second copy
    return pd.DataFrame(cols, copy=False)
