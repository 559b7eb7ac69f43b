"""The batch solver's vectorized factors: the errors and Jacobians of every Python factor of one type at once, per linearization point.

GTSAM evaluates a ``CustomFactor`` through its Python callback, one factor at a time; the
shared measurement models of :mod:`polins.fusion.measurement` then run on 3-vectors, and
numpy's per-call overhead dominates (about 50-200 us a factor, a few thousand factors of
each type per log). A :class:`FactorBatch` holds the parameters of all factors of one type;
:meth:`FactorBatch.prepare` evaluates the same model for all of them in numpy at given
values, and each factor's callback returns its row (:meth:`FactorBatch.lookup`). The rows
are served only for that very ``gtsam.Values`` object and only while GTSAM linearizes the
graph at it (:func:`linearize`: evaluate, linearize, forget), during which GTSAM holds it
as a constant reference: a callback given any other values (another solver, a cost
evaluation, a retracted copy) evaluates itself, so no factor ever sees a row of other
values. The vectorized models are checked against the per-factor callbacks in
tests/test_graph_batched.py:

* :class:`NonHolonomicBatch`: :func:`~polins.fusion.measurement.non_holonomic_kernel`;
* :class:`OdometerBatch`: :func:`~polins.fusion.measurement.odometer_kernel` with the
  odometer scale ``so`` (:func:`~polins.fusion.vehicle.scaled_odometer`), whitened by its
  ``R`` (:func:`polins.fusion.graph.states.item_factor`);
* :class:`YawBatch`: :func:`~polins.fusion.measurement.yaw_kernel`, with and without the
  tilt coupling;
* :class:`ScaleImuBatch`: :func:`polins.fusion.graph.imu.scale_factor_imu_factor` (GTSAM's
  ``CombinedImuFactor`` linearized in one C++ call for all intervals, the scale-factor
  terms in numpy).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from polins.frames import skew, wrap_angle

FloatArray = NDArray[np.float64]

POSE, VECTOR, BIAS = "pose", "vector", "bias"  # the value type of a key


class ValueReader:
    """The values of one linearization point, each key read once (shared by the batches)."""

    def __init__(self, values: gtsam.Values) -> None:
        self.values = values
        self._rot: dict[int, FloatArray] = {}
        self._vec: dict[int, list[float]] = {}

    def rotation(self, key: int) -> FloatArray:
        """``mat_nb`` (3, 3) of a ``Pose3`` key."""
        if key not in self._rot:
            self._rot[key] = self.values.atPose3(key).rotation().matrix()
        return self._rot[key]

    def vector(self, key: int) -> list[float]:
        """A ``Vector`` key's value."""
        if key not in self._vec:
            self._vec[key] = self.values.atVector(key).tolist()
        return self._vec[key]


class FactorBatch:
    """The factors of one type: their keys, parameters and, after :meth:`prepare`, their
    errors and Jacobians at one linearization point.

    Subclasses set :attr:`kinds` (the value type of each key position) and implement
    :meth:`evaluate`.
    """

    kinds: tuple[str, ...] = ()

    def __init__(self) -> None:
        self.keys: list[tuple[int, ...]] = []
        self.params: list[tuple[Any, ...]] = []
        self._stacked: tuple[Any, ...] | None = None
        self._err: FloatArray | None = None
        self._jac: list[FloatArray] = []
        self._ok: NDArray[np.bool_] | None = None
        self._values: gtsam.Values | None = None

    def add(self, keys: Sequence[int], *params: Any) -> int:
        """Register a factor on ``keys`` with its parameters; returns its slot."""
        self.keys.append(tuple(int(k) for k in keys))
        self.params.append(params)
        self._stacked = None
        return len(self.keys) - 1

    def stack(self) -> tuple[Any, ...]:
        """The parameters as arrays over the slots (default: one array per parameter)."""
        return tuple(np.array(column, dtype=float) for column in zip(*self.params, strict=True))

    def evaluate(
        self, reader: ValueReader, params: tuple[Any, ...], keys: list[tuple[int, ...]]
    ) -> tuple[FloatArray, list[FloatArray], NDArray[np.bool_]]:
        """Errors ``(N, m)``, Jacobians (one ``(N, m, d_j)`` array per key) and the slots
        whose model is defined, at the reader's values, of the slots with ``keys`` and
        parameters ``params`` (:meth:`stack`'s, selected)."""
        raise NotImplementedError

    def prepare(self, reader: ValueReader) -> None:
        """Evaluate every factor whose keys the reader's values hold (a window's: those of
        its keyframes)."""
        self.clear()
        if not self.keys:
            return
        if self._stacked is None:
            self._stacked = self.stack()
        live = np.array([reader.values.exists(k[0]) for k in self.keys])
        if live.all():
            err, jac, ok = self.evaluate(reader, self._stacked, self.keys)
        else:
            keys = [k for k, on in zip(self.keys, live, strict=True) if on]
            params = tuple(p if isinstance(p, gtsam.NonlinearFactorGraph) else p[live]
                           for p in self._stacked)  # fmt: skip
            part = self.evaluate(reader, params, keys)
            err = np.zeros((len(self.keys), *part[0].shape[1:]))
            err[live] = part[0]
            jac = [np.zeros((len(self.keys), *j.shape[1:])) for j in part[1]]
            for full, j in zip(jac, part[1], strict=True):
                full[live] = j
            ok = np.zeros(len(self.keys), bool)
            ok[live] = part[2]
        self._err = np.ascontiguousarray(err)
        self._jac = [np.ascontiguousarray(j) for j in jac]
        self._ok = ok
        self._values = reader.values

    def clear(self) -> None:
        """Forget the last evaluation."""
        self._err, self._jac, self._ok, self._values = None, [], None, None

    def lookup(self, slot: int, values: gtsam.Values, jacobians: Any) -> FloatArray | None:
        """The error of factor ``slot`` (and its Jacobians into ``jacobians``) if ``values``
        is the object the batch was last evaluated at (module docstring); else None (the
        factor evaluates itself)."""
        if values is not self._values or self._ok is None or not self._ok[slot]:
            return None
        assert self._err is not None
        if jacobians is not None:
            for j, block in enumerate(self._jac):
                jacobians[j] = block[slot]
        return self._err[slot]


def rotations(reader: ValueReader, keys: Sequence[tuple[int, ...]], pos: int) -> FloatArray:
    """``mat_nb`` ``(N, 3, 3)`` of key position ``pos`` of every slot."""
    return np.array([reader.rotation(k[pos]) for k in keys])


def vectors(reader: ValueReader, keys: Sequence[tuple[int, ...]], pos: int) -> FloatArray:
    """The vectors ``(N, d)`` of key position ``pos`` of every slot."""
    return np.array([reader.vector(k[pos]) for k in keys], dtype=float)


def body_columns(h_att_n: FloatArray, mat_nb: FloatArray) -> FloatArray:
    """:func:`polins.fusion.graph.factors.body_jacobian` over a batch: ``(N, m, 6)`` from
    ``(N, m, 3)``."""
    out = np.zeros((*h_att_n.shape[:2], 6))
    out[..., :3] = h_att_n @ mat_nb
    return out


def vehicle_velocity(
    mat_nb: FloatArray, vel_n: FloatArray, mat_vb: FloatArray, lever_vel_b: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``vel_v`` ``(N, 3)`` and ``mat_vn`` ``(N, 3, 3)`` of the vehicle's reference point
    (``polins.fusion.measurement``'s, over a batch; identity mounting and zero lever
    velocity where none is configured)."""
    mat_vn = mat_vb @ np.swapaxes(mat_nb, 1, 2)
    vel_v = np.einsum("nij,nj->ni", mat_vn, vel_n) + np.einsum("nij,nj->ni", mat_vb, lever_vel_b)
    return vel_v, mat_vn


class NonHolonomicBatch(FactorBatch):
    """:func:`polins.fusion.graph.factors.non_holonomic_factor` (keys ``X``, ``V``;
    parameters ``mat_vb`` and ``lever_vel_b``, identity and zero when not configured)."""

    kinds = (POSE, VECTOR)

    def evaluate(
        self, reader: ValueReader, params: tuple[Any, ...], keys: list[tuple[int, ...]]
    ) -> tuple[FloatArray, list[FloatArray], NDArray[np.bool_]]:
        mat_vb, lever = params
        mat_nb = rotations(reader, keys, 0)
        vel_n = vectors(reader, keys, 1)
        vel_v, mat_vn = vehicle_velocity(mat_nb, vel_n, mat_vb, lever)
        h_att = (mat_vn @ skew(vel_n))[:, 1:3]
        jac = [body_columns(h_att, mat_nb), mat_vn[:, 1:3]]
        return vel_v[:, 1:3], jac, np.ones(len(keys), bool)


class OdometerBatch(FactorBatch):
    """An odometer speed's :func:`polins.fusion.graph.states.item_factor` with the odometer
    scale ``so`` as its only variable (keys ``X``, ``V``, ``o0``; parameters the speed
    [m/s], its sigma [m/s], ``mat_vb`` and ``lever_vel_b``): the speed and sigma divided by
    ``1 + k``, whitened by that sigma."""

    kinds = (POSE, VECTOR, VECTOR)

    def evaluate(
        self, reader: ValueReader, params: tuple[Any, ...], keys: list[tuple[int, ...]]
    ) -> tuple[FloatArray, list[FloatArray], NDArray[np.bool_]]:
        speed, std, mat_vb, lever = params
        mat_nb = rotations(reader, keys, 0)
        vel_n = vectors(reader, keys, 1)
        div = 1.0 + vectors(reader, keys, 2)[:, 0]
        speed, std = speed / div, std / div
        vel_v, mat_vn = vehicle_velocity(mat_nb, vel_n, mat_vb, lever)
        residual = speed - vel_v[:, 0]
        white = (1.0 / std)[:, None, None]
        h_att = (mat_vn @ skew(vel_n))[:, 0:1]
        h_so = ((speed - residual) / div)[:, None, None]
        jac = [white * body_columns(h_att, mat_nb), white * mat_vn[:, 0:1], white * h_so]
        return (-residual / std)[:, None], jac, np.ones(len(keys), bool)


class YawBatch(FactorBatch):
    """:func:`polins.fusion.graph.factors.yaw_factor` (key ``X``; parameters the yaw [rad],
    and with ``tilt`` the unit ``sun_n`` and the prior's ``mat_nb``)."""

    kinds = (POSE,)

    def __init__(self, tilt: bool) -> None:
        super().__init__()
        self.tilt = tilt

    def evaluate(
        self, reader: ValueReader, params: tuple[Any, ...], keys: list[tuple[int, ...]]
    ) -> tuple[FloatArray, list[FloatArray], NDArray[np.bool_]]:
        mat_nb = rotations(reader, keys, 0)
        if not self.tilt:
            (yaw,) = params
            ax, ay, az = mat_nb[:, 0, 0], mat_nb[:, 1, 0], mat_nb[:, 2, 0]
            horiz2 = ax * ax + ay * ay
            safe = np.maximum(horiz2, 1e-300)
            h_att = np.stack([-ax * az / safe, -ay * az / safe, np.ones_like(ax)], -1)
            predicted = np.arctan2(ay, ax)
        else:
            yaw, sun_n, prior = params
            m = prior @ np.swapaxes(mat_nb, 1, 2)
            b = np.einsum("nij,nj->ni", m, sun_n)
            horiz2 = b[:, 0] ** 2 + b[:, 1] ** 2
            safe = np.maximum(horiz2, 1e-300)
            grad = np.stack([-b[:, 1], b[:, 0], np.zeros_like(safe)], -1) / safe[:, None]
            h_att = -np.einsum("ni,nij,njk->nk", grad, m, skew(sun_n))
            predicted = (np.arctan2(sun_n[:, 1], sun_n[:, 0])
                         + np.arctan2(prior[:, 1, 0], prior[:, 0, 0])
                         - np.arctan2(b[:, 1], b[:, 0]))  # fmt: skip
        residual = wrap_angle(yaw - predicted)
        jac = [body_columns(h_att[:, None, :], mat_nb)]
        return -residual[:, None], jac, horiz2 >= 1e-12


# The columns of the CombinedImuFactor's keys X_i, V_i, X_j, V_j, B_i, B_j in its Jacobian.
IMU_COLUMNS = ((0, 6), (6, 9), (9, 15), (15, 18), (18, 24), (24, 30))


class ScaleImuBatch(FactorBatch):
    """:func:`polins.fusion.graph.imu.scale_factor_imu_factor` (keys ``X_i, V_i, X_j,
    V_j, B_i, B_j, sg, sa``; parameters the wrapped ``CombinedImuFactor``, ``W_R J_R``
    (15, 6), ``W_pv`` (15, 6) and ``J_pv`` (2, 3, 6), the names of that function)."""

    kinds = (POSE, VECTOR, POSE, VECTOR, BIAS, BIAS, VECTOR, VECTOR)

    def stack(self) -> tuple[Any, ...]:
        graph = gtsam.NonlinearFactorGraph()
        for p in self.params:
            graph.add(p[0])
        h_rot, w_pv, jac_pv = (np.array([p[i] for p in self.params]) for i in (1, 2, 3))
        return graph, h_rot, w_pv, jac_pv

    def evaluate(
        self, reader: ValueReader, params: tuple[Any, ...], keys: list[tuple[int, ...]]
    ) -> tuple[FloatArray, list[FloatArray], NDArray[np.bool_]]:
        graph, h_rot, w_pv, jac_pv = params
        n = len(keys)
        linear = graph.linearize(reader.values)
        a_mat = np.empty((n, 15, 30))
        b_vec = np.empty((n, 15))
        for i in range(n):
            a_mat[i], b_vec[i] = linear.at(i).jacobian()
        mat_i = rotations(reader, keys, 0)
        mat_j = rotations(reader, keys, 2)
        mat_ji = np.swapaxes(mat_j, 1, 2) @ mat_i
        turned = (mat_ji[:, None] @ jac_pv).reshape(n, 6, 6)
        h_s = h_rot + w_pv @ turned
        s = np.concatenate([vectors(reader, keys, 6), vectors(reader, keys, 7)], 1)
        u = np.einsum("npij,nj->npi", jac_pv, s)  # (N, 2, 3): J_p s, J_v s
        a_mat[:, :, 0:3] -= w_pv @ (mat_ji[:, None] @ skew(u)).reshape(n, 6, 3)
        u_j = np.einsum("npj,nkj->npk", u, mat_ji)  # u @ mat_ji.T
        a_mat[:, :, 9:12] += w_pv @ skew(u_j).reshape(n, 6, 3)
        jac = [a_mat[:, :, lo:hi] for lo, hi in IMU_COLUMNS]
        jac += [h_s[:, :, :3], h_s[:, :, 3:]]
        err = -b_vec + np.einsum("nij,nj->ni", h_s, s)
        return err, jac, np.ones(n, bool)


def prepare_all(batches: Sequence[FactorBatch], values: gtsam.Values) -> None:
    """Evaluate every batch at ``values`` (each key read once)."""
    reader = ValueReader(values)
    for batch in batches:
        batch.prepare(reader)


def linearize(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, batches: Sequence[FactorBatch]
) -> gtsam.GaussianFactorGraph:
    """``graph.linearize(values)`` with the batches' factors evaluated together: the batches
    are evaluated at ``values``, serve its linearization, and are cleared."""
    try:
        prepare_all(batches, values)
        return graph.linearize(values)
    finally:
        for batch in batches:
            batch.clear()


__all__ = [
    "FactorBatch",
    "NonHolonomicBatch",
    "OdometerBatch",
    "ScaleImuBatch",
    "ValueReader",
    "YawBatch",
    "linearize",
    "prepare_all",
]
