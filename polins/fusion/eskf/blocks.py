"""The error state built from named blocks: each declares its size, dynamics, noise, initial sigma and measurement columns.

A :class:`Block` is one named part of the error state (``att``, ``vel``, ``pos``, ``bg``,
``ba``, with scale factors ``sg``, ``sa``; the optional odometer scale ``so``, mounting
errors ``mount_pitch``, ``mount_yaw``, lever-arm error ``lever_b`` and the sky's states).
It declares

* ``size``: its number of states;
* ``columns(step)``: its columns of the continuous dynamics ``F``, as a mapping from the
  name of a block (the rows) to an ``(S, rows, size)`` array, given the
  :class:`~polins.fusion.eskf.dynamics.StepNominal` of S covariance steps. How the block's
  error drives the others (``bg`` drives ``att`` through ``-C D_g``) and itself (a
  Gauss-Markov state drives its own rows with ``-1/tau``); blocks not named are zero;
* ``noise(model)``: its continuous process-noise density per state (white noise
  entering its own rows; zero by default);
* ``sigma0(model, config)``: its initial 1-sigma per state;
* ``jacobian``: its columns of the measurement Jacobian: a ``slice`` of the columns of the
  shared 15-state model (:func:`~polins.fusion.items.item_model`), or a function
  ``(item, lin) -> (dim, size)`` of the item (:class:`~polins.fusion.items.MeasurementItem`)
  and that model ``lin``; None (the default): zero;
* ``correct(gyro_b, accel_b, estimate)``: for an IMU error, the samples corrected with the
  block's estimate (applied in block order: ``(w - bg) / (1 + sg)``); None otherwise;
* ``offset``: True when the block's estimate enters the measurement linearly through its
  Jacobian columns, ``h = h_shared + J estimate`` (the site error, the heading bias): the
  residual is then taken at the estimate (:meth:`Layout.linearize`).

Navigation blocks (``att``, ``vel``, ``pos``) are injected into the nominal attitude,
velocity and position; the others are *sensor-error* blocks, whose estimates the filter
keeps by name (``ESKF.errors``) and reports in the solution table. :class:`Layout` lays
the blocks out in order and assembles ``F``, ``Qc``, ``P0`` and ``H`` from them, so a
capability adds a block (:func:`error_blocks`) without touching the filter (docs/filter.md,
"Adding a state block").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.fusion.config import ODOMETER_SCALE_STD, SUN_AZIMUTH_RATE_STD, FuseConfig
from polins.fusion.eskf.dynamics import StepNominal
from polins.fusion.items import LEVER_STATE, MOUNT_STATES, MeasurementItem, item_model
from polins.fusion.measurement import (
    BA,
    BG,
    Linearized,
    lever_jacobian,
    mount_jacobian,
    wrap_residual,
)
from polins.fusion.priors import EARTH_RATE_TURN_S, SUN_AZIMUTH_STD0, SUN_RATE_CHANGE_S
from polins.fusion.sky_states import (
    heading_bias_jacobian,
    site_rotation_std,
    sun_attitude_columns,
    sun_azimuth_jacobian,
)
from polins.ins.earth import OMEGA_IE, radii_of_curvature
from polins.models import ImuModel

FloatArray = NDArray[np.float64]
Columns = Callable[[StepNominal], Mapping[str, FloatArray]]
# (gyro_b, accel_b, estimate) -> the IMU samples corrected with the block's estimate
Correction = Callable[[FloatArray, FloatArray, FloatArray], tuple[FloatArray, FloatArray]]


def _no_noise(model: ImuModel) -> float:
    return 0.0


@dataclass(frozen=True)
class Block:
    """One named block of the error state (module docstring)."""

    name: str
    size: int
    columns: Columns
    sigma0: Callable[[ImuModel, FuseConfig], float | Sequence[float]]
    noise: Callable[[ImuModel], float] = _no_noise
    jacobian: slice | Callable[[MeasurementItem, Linearized], FloatArray] | None = None
    navigation: bool = False
    correct: Correction | None = None
    offset: bool = False


def _skew_columns(v: FloatArray) -> FloatArray:
    """``-[v x]`` for ``(S, 3)`` vectors, ``(S, 3, 3)``."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = v[..., 2], -v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = -v[..., 2], v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = v[..., 1], -v[..., 0]
    return out


def _att(step: StepNominal) -> Mapping[str, FloatArray]:
    f = step.f_nav
    return {"att": f[:, 0:3, 0:3], "vel": _skew_columns(step.force_n), "pos": f[:, 6:9, 0:3]}


def _vel(step: StepNominal) -> Mapping[str, FloatArray]:
    f = step.f_nav
    return {"att": f[:, 0:3, 3:6], "vel": f[:, 3:6, 3:6], "pos": f[:, 6:9, 3:6]}


def _pos(step: StepNominal) -> Mapping[str, FloatArray]:
    f = step.f_nav
    return {"att": f[:, 0:3, 6:9], "vel": f[:, 3:6, 6:9], "pos": f[:, 6:9, 6:9]}


def _bg(step: StepNominal) -> Mapping[str, FloatArray]:
    return {"att": -step.mat_nb * step.gyro_divisor}


def _ba(step: StepNominal) -> Mapping[str, FloatArray]:
    return {"vel": -step.mat_nb * step.accel_divisor}


def _sg(step: StepNominal) -> Mapping[str, FloatArray]:
    assert step.mat_omega is not None  # scale-factor runs carry it
    return {"att": -step.mat_omega * step.gyro_divisor}


def _sa(step: StepNominal) -> Mapping[str, FloatArray]:
    assert step.mat_force is not None
    return {"vel": -step.mat_force * step.accel_divisor}


ATT = Block("att", 3, _att, lambda m, c: c.initial.att_std0, lambda m: m.gyro_arw**2,
            slice(0, 3), navigation=True)  # fmt: skip
VEL = Block("vel", 3, _vel, lambda m, c: c.initial.vel_std0, lambda m: m.accel_vrw**2,
            slice(3, 6), navigation=True)  # fmt: skip
POS = Block("pos", 3, _pos, lambda m, c: c.initial.pos_std0, jacobian=slice(6, 9),
            navigation=True)  # fmt: skip
GYRO_BIAS = Block("bg", 3, _bg, lambda m, c: m.gyro_bias, lambda m: m.gyro_bias_rw**2,
                  BG, correct=lambda w, f, e: (w - e, f))  # fmt: skip
ACCEL_BIAS = Block("ba", 3, _ba, lambda m, c: m.accel_bias_turn_on, lambda m: m.accel_bias_rw**2,
                   BA, correct=lambda w, f, e: (w, f - e))  # fmt: skip
GYRO_SCALE = Block("sg", 3, _sg, lambda m, c: m.gyro_scale_factor,
                   correct=lambda w, f, e: (w / (1.0 + e), f))  # fmt: skip
ACCEL_SCALE = Block("sa", 3, _sa, lambda m, c: m.accel_scale_factor,
                    correct=lambda w, f, e: (w, f / (1.0 + e)))  # fmt: skip


def _odometer_scale_jacobian(item: MeasurementItem, lin: Linearized) -> FloatArray:
    """``d h / d k`` of an odometer item: the predicted forward speed [m/s] (the model
    ``speed = (1 + k) v_x``, docs/filter.md "Ground-vehicle aiding"); zero for the others."""
    out = np.zeros((lin.H.shape[0], 1))
    if item.kind == "odo":
        out[0, 0] = item.speed - float(lin.residual[0])
    return out


# the wheel odometer's scale factor k (a constant), with odometer_std
ODOMETER_SCALE = Block("so", 1, lambda step: {}, lambda m, c: ODOMETER_SCALE_STD,
                       jacobian=_odometer_scale_jacobian)  # fmt: skip
# the mounting's pitch and yaw errors (random constants), with mount_std; the NHC and the
# odometer use the mounting turned by their estimate (polins.fusion.items.item_model)
MOUNT_PITCH = Block(MOUNT_STATES[0], 1, lambda step: {}, lambda m, c: c.mount_sigma or 0.0,
                    jacobian=lambda item, lin: mount_jacobian(lin)[:, 0:1])  # fmt: skip
MOUNT_YAW = Block(MOUNT_STATES[1], 1, lambda step: {}, lambda m, c: c.mount_sigma or 0.0,
                  jacobian=lambda item, lin: mount_jacobian(lin)[:, 1:2])  # fmt: skip
# the lever arm's error, IMU axes (random constants), with lever_std
LEVER = Block(LEVER_STATE, 3, lambda step: {}, lambda m, c: c.lever_sigma or 0.0,
              jacobian=lambda item, lin: lever_jacobian(lin, item.mat_vb, item.gyro_b))  # fmt: skip


def _cover_earth_rate(block: Block) -> Block:
    """The gyro-bias block widened to cover the unmechanized Earth rate."""
    return dataclasses.replace(
        block,
        sigma0=lambda m, c: math.hypot(m.gyro_bias, OMEGA_IE),
        noise=lambda m: m.gyro_bias_rw**2 + OMEGA_IE**2 / EARTH_RATE_TURN_S,
    )


def sky_blocks(config: FuseConfig) -> tuple[Block, ...]:
    """The measurement-side blocks ``config`` asks for (:mod:`polins.fusion.sky_states`;
    docs/filter.md, "Approximate site", "No clock", "Heading-measurement bias")."""
    out: tuple[Block, ...] = ()
    if config.site_sigma is not None and config.site is not None:
        std = site_rotation_std(config.site.lat, config.site_sigma)
        out += (Block("site_rot_n", 3, lambda step: {}, lambda m, c: std,
                      jacobian=sun_attitude_columns, offset=True),)  # fmt: skip
    if config.no_clock:
        rate_std = SUN_AZIMUTH_RATE_STD
        out += (
            Block("sun_azimuth_n", 1, lambda step: {}, lambda m, c: SUN_AZIMUTH_STD0,
                  jacobian=sun_azimuth_jacobian),
            Block("sun_azimuth_rate", 1,
                  lambda step: {"sun_azimuth_n": np.ones((step.dt.shape[0], 1, 1))},
                  lambda m, c: SUN_AZIMUTH_RATE_STD,
                  lambda m: rate_std**2 / SUN_RATE_CHANGE_S),
        )  # fmt: skip
    if config.heading_bias_sigma is not None:
        sig, tau = config.heading_bias_sigma, config.sky.heading_bias_tau_s
        out += (Block("heading_bias", 1,
                      lambda step: {"heading_bias": np.full((step.dt.shape[0], 1, 1), -1.0 / tau)},
                      lambda m, c: sig, lambda m: 2.0 * sig**2 / tau, heading_bias_jacobian,
                      offset=True),)  # fmt: skip
    return out


def error_blocks(config: FuseConfig) -> tuple[Block, ...]:
    """The blocks of the error state that ``config`` asks for, in state order."""
    gyro_bias = _cover_earth_rate(GYRO_BIAS) if config.uncovered_earth_rate else GYRO_BIAS
    blocks: tuple[Block, ...] = (ATT, VEL, POS, gyro_bias, ACCEL_BIAS)
    if config.use_scale_factors:
        blocks += (GYRO_SCALE, ACCEL_SCALE)
    if config.odometer_sigma is not None:
        blocks += (ODOMETER_SCALE,)
    if config.mount_sigma is not None:
        blocks += (MOUNT_PITCH, MOUNT_YAW)
    if config.lever_sigma is not None:
        blocks += (LEVER,)
    return blocks + sky_blocks(config)


class Layout:
    """Blocks laid out in order: their slices, and ``F``, ``Qc``, ``P0``, ``H`` assembled.

    The first three blocks must be ``att``, ``vel``, ``pos`` (the nominal navigation state).
    """

    def __init__(self, blocks: Sequence[Block]) -> None:
        if [b.name for b in blocks[:3]] != ["att", "vel", "pos"]:
            raise ValueError("the error state starts with the att, vel, pos blocks")
        self.blocks = tuple(blocks)
        self.index: dict[str, slice] = {}
        start = 0
        for b in self.blocks:
            if b.name in self.index:
                raise ValueError(f"two error-state blocks named {b.name!r}")
            self.index[b.name] = slice(start, start + b.size)
            start += b.size
        self.n = start
        self.sensor = tuple(b for b in self.blocks if not b.navigation)
        # columns taken from the shared 15-state model, and the blocks with own functions
        src = [np.arange(15)[b.jacobian] for b in self.blocks if isinstance(b.jacobian, slice)]
        dst = [np.arange(self.n)[self.index[b.name]] for b in self.blocks
               if isinstance(b.jacobian, slice)]  # fmt: skip
        self._kernel_src = np.concatenate(src) if src else np.zeros(0, dtype=int)
        self._kernel_dst = np.concatenate(dst) if dst else np.zeros(0, dtype=int)
        self._own = tuple(b for b in self.blocks if callable(b.jacobian))
        self._offset = tuple(b for b in self._own if b.offset)
        # the shared model's columns in place (the first k states): copied as one slice
        k = self._kernel_src.size
        same = np.array_equal(self._kernel_src, np.arange(k)) and np.array_equal(
            self._kernel_dst, np.arange(k)
        )
        self._prefix = k if same else -1
        self._plain = self.n == 15 and not self._own and same
        self._own_cols = tuple((self.index[b.name], b.jacobian) for b in self._own)
        self._offset_cols = tuple((self.index[b.name], b.name) for b in self._offset)

    def __getitem__(self, name: str) -> slice:
        return self.index[name]

    def dynamics(self, step: StepNominal) -> FloatArray:
        """Continuous error dynamics ``F`` of the steps, ``(S, n, n)``."""
        F = np.zeros((step.dt.shape[0], self.n, self.n))
        for b in self.blocks:
            col = self.index[b.name]
            for row_name, block in b.columns(step).items():
                F[:, self.index[row_name], col] = block
        return F

    def correct(
        self, gyro_b: ArrayLike, accel_b: ArrayLike, errors: Mapping[str, FloatArray]
    ) -> tuple[FloatArray, FloatArray]:
        """IMU samples corrected with the sensor-error estimates ``errors`` (the blocks'
        ``correct`` in block order: ``(w - bg) / (1 + sg)``, ``(f - ba) / (1 + sa)``)."""
        w, f = np.asarray(gyro_b, dtype=float), np.asarray(accel_b, dtype=float)
        for b in self.sensor:
            if b.correct is not None:
                w, f = b.correct(w, f, errors[b.name])
        return w, f

    def noise_density(self, model: ImuModel) -> FloatArray:
        """Diagonal of the continuous process-noise density ``Qc``, ``(n,)``."""
        return np.concatenate([np.full(b.size, b.noise(model)) for b in self.blocks])

    def step_noise(self, qc: FloatArray, model: ImuModel, step: StepNominal) -> FloatArray:
        """``Qc`` of each step, ``(S, n)``, or ``qc`` itself when it does not vary.

        The gyro's axis misalignment ``m`` (``ImuModel.gyro_misalignment``) turns rotation
        into attitude error: it enters the attitude rows as white noise of density
        ``m^2 |omega_b|^2 tau`` with ``tau = gyro_misalignment_corr_time`` (docs/filter.md,
        "Rotation-proportional attitude noise").
        """
        m2tau = model.gyro_misalignment**2 * model.gyro_misalignment_corr_time
        if m2tau == 0.0 or step.rate_sq is None:
            return qc
        out = np.broadcast_to(qc, (step.dt.shape[0], self.n)).copy()
        out[:, self.index["att"]] += (m2tau * step.rate_sq)[:, None]
        return out

    def initial_covariance(self, model: ImuModel, config: FuseConfig) -> FloatArray:
        """Diagonal initial covariance ``P0`` from the blocks' initial sigmas."""
        sig = [np.broadcast_to(np.asarray(b.sigma0(model, config), float), (b.size,))
               for b in self.blocks]  # fmt: skip
        return np.diag(np.concatenate(sig) ** 2)

    def linearize(
        self,
        item: MeasurementItem,
        mat_nb: FloatArray,
        vel_n: FloatArray,
        tilt_coupling: bool,
        errors: Mapping[str, FloatArray],
    ) -> Linearized:
        """The measurement model of ``item`` over all blocks at the nominal state and the
        sensor-error estimates ``errors``: the shared model (:func:`item_model`), the
        Jacobian over all blocks, the residual taken at the estimates of the ``offset``
        blocks (angles wrapped)."""
        lin = item_model(item, mat_nb, vel_n, tilt_coupling, errors)
        H = self.jacobian(item, lin)
        if not self._offset_cols:
            return Linearized(lin.residual, H, lin.R, lin.name)
        res = lin.residual.copy()
        for cols, name in self._offset_cols:
            res -= H[:, cols] @ errors[name]
        return Linearized(wrap_residual(res, lin.name), H, lin.R, lin.name)

    def jacobian(self, item: MeasurementItem, lin: Linearized) -> FloatArray:
        """The measurement Jacobian ``(dim, n)`` of an item over all blocks."""
        if self._plain:  # the shared model's own layout
            return lin.H
        H = np.zeros((lin.H.shape[0], self.n))
        k = self._prefix
        if k >= 0:
            H[:, :k] = lin.H[:, :k]
        else:
            H[:, self._kernel_dst] = lin.H[:, self._kernel_src]
        for cols, jacobian in self._own_cols:
            H[:, cols] = jacobian(item, lin)  # type: ignore[misc,operator]
        return H


def scale_divisors(errors: Mapping[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
    """``1 / (1 + s)`` of the gyro and accelerometer scale-factor estimates in ``errors``
    (ones without them)."""
    if "sg" in errors:
        return 1.0 / (1.0 + errors["sg"]), 1.0 / (1.0 + errors["sa"])
    return np.ones(3), np.ones(3)


def inject_nav(
    mat_nb: FloatArray,
    vel_n: FloatArray,
    lat: ArrayLike,
    lon: ArrayLike,
    alt_m: ArrayLike,
    dx: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """``nominal (+) dx`` for the navigation blocks (``dx[..., :9]``: attitude, velocity,
    ENU position [m]); single or batched (leading axis)."""
    r_m, r_n = radii_of_curvature(lat)
    lat_a, alt_a = np.asarray(lat, dtype=float), np.asarray(alt_m, dtype=float)
    mat = Rotation.from_rotvec(dx[..., 0:3]).as_matrix() @ mat_nb
    return (
        mat,
        vel_n + dx[..., 3:6],
        lat_a + dx[..., 7] / (r_m + alt_a),
        np.asarray(lon, dtype=float) + dx[..., 6] / ((r_n + alt_a) * np.cos(lat_a)),
        alt_a + dx[..., 8],
    )
