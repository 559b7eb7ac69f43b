"""The graph's sensor-error variables (odometer scale, mounting, lever arm, site, no-clock sun azimuth, heading bias) and their factors.

Each is a block of the ESKF (:mod:`polins.fusion.eskf.blocks`, docs/filter.md §5.6, §5.7)
and becomes GTSAM variables here (docs/filter.md §9):

* ``so`` (odometer scale ``k``, a constant): one ``Vector1`` ``o0`` with the prior
  ``odometer_scale_std``;
* ``mount_pitch``, ``mount_yaw`` (the mounting's errors, constants seen by the
  non-holonomic and odometer factors at nearly every keyframe): a ``Vector2`` ``m<k>`` per
  keyframe with the prior ``mount_std``, linked as constants the way the scale factors are
  (``BetweenFactorVector`` of ``mount_std sqrt(dt / CONSTANT_S)``): one key for the whole
  log made ISAM2 3x slower on a 60 s drive (it sits in every clique's separator);
* ``lever_b`` (the lever arm's error, constants): a ``Vector3`` ``r<k>`` per keyframe with
  the prior ``lever_std``, linked the same way;
* ``site_rot_n`` (the ENU frame rotation of an approximate site, three constants): one
  ``Vector3`` ``l0`` with the ESKF's independent 1-sigmas
  (:func:`~polins.fusion.sky_states.site_rotation_std`);
* ``sun_azimuth_n`` and ``sun_azimuth_rate`` (no clock): a ``Vector2`` ``z<k>`` of the
  sun's ENU azimuth and its rate per keyframe, linked by the integrated random walk of the
  ESKF (``F = [[1, dt], [0, 1]]``, rate density ``sun_azimuth_rate_std^2 /
  SUN_RATE_CHANGE_S``, :func:`sun_azimuth_factor`);
* ``heading_bias`` (first-order Gauss-Markov): a ``Vector1`` ``h<k>`` per keyframe, linked
  by ``b_j - exp(-dt/tau) b_i`` with the variance ``sigma^2 (1 - exp(-2 dt/tau))``
  (:func:`gauss_markov_factor`; GTSAM has no such factor).

A measurement that sees one of them (or a sun vector with a 2x2 covariance: the fit's
azimuth / elevation sigmas, docs/filter.md §5.3) becomes an :func:`item_factor`: a ``CustomFactor`` on the shared model
(:func:`polins.fusion.items.item_model`) extended by the columns of
:mod:`polins.fusion.sky_states`, the odometer's scale, the mounting and the lever arm
(:func:`GraphStates.model`), the same linearization the solvers gate with.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X
from numpy.typing import NDArray

from polins.fusion.config import ODOMETER_SCALE_STD, SUN_AZIMUTH_RATE_STD, FuseConfig
from polins.fusion.graph.batched import OdometerBatch
from polins.fusion.graph.factors import body_jacobian
from polins.fusion.graph.imu import CONSTANT_S
from polins.fusion.items import (
    HEADING_KINDS,
    LEVER_STATE,
    MOUNT_STATES,
    SUN_AZIMUTH_STATE,
    MeasurementItem,
    item_model,
)
from polins.fusion.measurement import (
    ATT,
    N_ERROR,
    VEL,
    Linearized,
    lever_jacobian,
    mount_jacobian,
    sun_basis_b,
    sun_kernel,
    wrap_residual,
)
from polins.fusion.priors import SUN_AZIMUTH_STD0, SUN_RATE_CHANGE_S
from polins.fusion.sky_states import (
    heading_bias_jacobian,
    site_rotation_std,
    sun_attitude_columns,
    sun_azimuth_jacobian,
    without_bias_part,
)
from polins.fusion.vehicle import VehicleAiding, scaled_odometer

FloatArray = NDArray[np.float64]

# A floor on the variance of the sun azimuth's change between keyframes [rad^2]: the
# integrated random walk alone gives a nearly singular 2 x 2 covariance between keyframes
# microseconds apart; 1e-12 rad^2 per interval adds at most 0.03 mrad over 1000 keyframes.
AZIMUTH_VAR_FLOOR = 1e-12


@dataclass(frozen=True)
class Variable:
    """One kind of graph variable: its GTSAM symbol letter, size, whether each keyframe
    has its own (else one constant), and the ESKF blocks (name, size) of its components."""

    letter: str
    size: int
    per_keyframe: bool
    blocks: tuple[tuple[str, int], ...]
    kinds: tuple[str, ...]  # the measurement kinds that see it


ODOMETER_SCALE = Variable("o", 1, False, (("so", 1),), ("odo",))
MOUNT = Variable("m", 2, True, tuple((name, 1) for name in MOUNT_STATES), ("nhc", "odo"))
LEVER = Variable("r", 3, True, ((LEVER_STATE, 3),), ("nhc", "odo"))
# ISAM2 relinearization thresholds other than 1e-3: the mounting 1e-2 rad, the attitude's
# (the NHC is linear in it to ``v e^2 / 2``, 2.5 mm/s at 5 m/s: relinearizing at every
# 1e-3 rad of its settling re-eliminated every keyframe that sees it, ISAM2 3x slower on a
# 60 s drive); the lever arm never (the models are linear in it)
RELINEARIZE = {MOUNT: 1e-2, LEVER: 1e6}
SITE_ROTATION = Variable("l", 3, False, (("site_rot_n", 3),), ("yaw", "sun"))
SUN_AZIMUTH = Variable(
    "z", 2, True, (("sun_azimuth_n", 1), ("sun_azimuth_rate", 1)), ("sun_azimuth",)
)
HEADING_BIAS = Variable("h", 1, True, (("heading_bias", 1),), HEADING_KINDS)


def gauss_markov_factor(
    key_i: int, key_j: int, dt: float, sigma: float, tau_s: float
) -> gtsam.CustomFactor:
    """First-order Gauss-Markov link of a ``Vector1`` from one keyframe to the next:
    error ``b_j - exp(-dt/tau) b_i`` with variance ``sigma^2 (1 - exp(-2 dt/tau))``
    (``sigma`` the stationary 1-sigma, ``tau_s`` [s] the correlation time, ``dt`` [s])."""
    phi = math.exp(-dt / tau_s)
    std = sigma * math.sqrt(max(-math.expm1(-2.0 * dt / tau_s), 1e-24))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        ki, kj = this.keys()
        if jacobians is not None:
            jacobians[0] = np.array([[-phi]])
            jacobians[1] = np.array([[1.0]])
        return values.atVector(kj) - phi * values.atVector(ki)

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, std), [key_i, key_j], error)


def sun_azimuth_factor(key_i: int, key_j: int, dt: float, rate_std: float) -> gtsam.CustomFactor:
    """The no-clock azimuth ``(a, a_dot)`` from one keyframe to the next: error ``x_j - F
    x_i``, ``F = [[1, dt], [0, 1]]``, covariance ``q [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` with
    ``q = rate_std^2 / SUN_RATE_CHANGE_S`` (the ESKF's ``sun_azimuth_rate`` block), plus
    :data:`AZIMUTH_VAR_FLOOR` on the azimuth."""
    q = rate_std**2 / SUN_RATE_CHANGE_S
    cov = q * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
    cov[0, 0] += AZIMUTH_VAR_FLOOR
    cov[1, 1] += 1e-30
    F = np.array([[1.0, dt], [0.0, 1.0]])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        ki, kj = this.keys()
        if jacobians is not None:
            jacobians[0] = -F
            jacobians[1] = np.eye(2)
        return values.atVector(kj) - F @ values.atVector(ki)

    return gtsam.CustomFactor(gtsam.noiseModel.Gaussian.Covariance(cov), [key_i, key_j], error)


def heading_bias_std(config: FuseConfig, headings: Sequence[MeasurementItem]) -> float | None:
    """The 1-sigma [rad] of the graph's heading-bias variable, or None (no variable):
    ``heading_bias_std`` when given (``FuseConfig.heading_bias == "fixed"``); by default
    (``"model"``) the root of the median ``model_std^2`` of the heading items (0 for those
    without a model part: the ESKF's :class:`~polins.fusion.sky_states.ModelPart` over the
    whole log, as a batch sees it); 0 leaves the variable out and its columns zero, as the
    ESKF's state stays at zero. None: off."""
    mode = config.heading_bias
    if mode == "fixed":
        return config.heading_bias_sigma
    if mode != "model":
        return None
    parts = [it.model_std**2 for it in headings if it.kind in HEADING_KINDS]
    return math.sqrt(float(np.median(parts))) if parts else 0.0


def whitener(cov: FloatArray) -> Callable[[FloatArray], FloatArray]:
    """``a -> L^-1 a`` for ``cov = L L^T`` of a 1x1 or 2x2 covariance (closed form: LAPACK
    calls cost milliseconds each in the factors' Python callbacks), else by Cholesky."""
    if cov.shape == (1, 1):
        scale = 1.0 / math.sqrt(float(cov[0, 0]))
        return lambda a: scale * a
    if cov.shape == (2, 2):
        l00 = math.sqrt(float(cov[0, 0]))
        l10 = float(cov[1, 0]) / l00
        l11 = math.sqrt(float(cov[1, 1]) - l10 * l10)
        inv = np.array([[1.0 / l00, 0.0], [-l10 / (l00 * l11), 1.0 / l11]])
    else:
        inv = np.linalg.inv(np.linalg.cholesky(cov))
    return lambda a: inv @ a


class GraphStates:
    """The sensor-error variables a configuration asks for (module docstring).

    Their estimates form one vector ``extra`` (the ESKF's block order: ``so``,
    ``mount_pitch``, ``mount_yaw``, ``lever_b``, ``site_rot_n``, ``sun_azimuth_n``,
    ``sun_azimuth_rate``, ``heading_bias``) that follows
    the 15 navigation and bias errors in :class:`~polins.fusion.graph.estimates.Estimates`.

    Parameters
    ----------
    config : FuseConfig
        ``odometer_std`` (an odometer: ``so``), ``mount_std`` (the mounting), ``lever_std``,
        ``site_std`` with ``site``, ``no_clock``,
        ``heading_bias_sigma`` (``heading_bias_std``, docs/filter.md §5.7).
    t_key : (K,) ndarray
        Keyframe times [s].
    """

    def __init__(
        self, config: FuseConfig, t_key: FloatArray, headings: Sequence[MeasurementItem] = ()
    ) -> None:
        self.config = config
        self.t_key = np.asarray(t_key, dtype=float)
        self.bias_std = heading_bias_std(config, headings)
        variables: list[Variable] = []
        if config.odometer_sigma is not None:
            variables.append(ODOMETER_SCALE)
        if config.mount_sigma is not None:
            variables.append(MOUNT)
        if config.lever_sigma is not None:
            variables.append(LEVER)
        if config.site_sigma is not None and config.site is not None:
            variables.append(SITE_ROTATION)
        if config.no_clock:
            variables.append(SUN_AZIMUTH)
        if self.bias_std is not None and self.bias_std > 0.0:
            variables.append(HEADING_BIAS)
        self.variables = tuple(variables)
        self.slices: dict[Variable, slice] = {}
        self.index: dict[str, slice] = {}  # ESKF block name -> slice of ``extra``
        start = 0
        for var in self.variables:
            self.slices[var] = slice(start, start + var.size)
            for name, size in var.blocks:
                self.index[name] = slice(start, start + size)
                start += size
        if self.bias_std == 0.0:  # the ESKF's state at zero: a column of the table only
            self.index["heading_bias"] = slice(start, start + 1)
            start += 1
        self.n = start
        self.guess = np.zeros(self.n)  # the initial values of the first keyframe
        # the odometer factors, evaluated together when the scale is their only variable
        only_scale = ODOMETER_SCALE in variables and set(self.index) <= {"so", "heading_bias"}
        self.odometer_batch = OdometerBatch() if only_scale else None

    def start(self, meas: Sequence[Any], mat_nb0: FloatArray) -> None:
        """Set the first keyframe's values (:attr:`guess`): the sun's ENU azimuth seen in the
        first ``"sun_azimuth"`` item of ``meas`` (``MeasFactor``, with ``k`` and ``item``)
        at the first attitude ``mat_nb0`` (the body elevation taken as 0 when NaN)."""
        if SUN_AZIMUTH not in self.slices:
            return
        first = [mf.item for mf in sorted(meas, key=lambda mf: mf.k)
                 if mf.item.kind == "sun_azimuth"]  # fmt: skip
        if first:
            az, el = first[0].yaw, first[0].elevation_b
            el = 0.0 if math.isnan(el) else el
            s_n = mat_nb0 @ np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                      math.sin(el)])  # fmt: skip
            self.guess[self.slices[SUN_AZIMUTH].start] = math.atan2(s_n[1], s_n[0])

    def prepare(self, item: MeasurementItem) -> MeasurementItem:
        """A heading item without the part of its sigma the heading-bias variable carries
        (``heading_bias == "model"``: :func:`~polins.fusion.sky_states.without_bias_part`
        with the variable's variance); unchanged otherwise."""
        if self.bias_std is None or self.config.heading_bias != "model":
            return item
        return without_bias_part(item, self.bias_std**2)

    def odometer(
        self,
        items: Sequence[MeasurementItem],
        keys: Sequence[int | None],
        t_imu: FloatArray,
        gyro_b: FloatArray,
    ) -> list[tuple[int, MeasurementItem, gtsam.NonlinearFactor]]:
        """``(k, item, factor)`` of the odometer speeds ``items`` at their keyframes ``keys``
        (None: outside the log, dropped): each item with the mounting and ``omega_b x
        lever_arm_b`` at the gyro rate interpolated to its time, as the ESKF's
        ``VehicleAiding.odometer``; its factor on ``X(k)``, ``V(k)`` and ``so``."""
        aiding = VehicleAiding(self.config, float(np.median(np.diff(t_imu))))
        t_items = np.array([it.t for it in items], dtype=float)
        rates = np.column_stack([np.interp(t_items, t_imu, gyro_b[:, i]) for i in range(3)])
        out: list[tuple[int, MeasurementItem, gtsam.NonlinearFactor]] = []
        for it, k, rate in zip(items, keys, rates.reshape(-1, 3), strict=True):
            if k is None:
                continue
            item = aiding.attach(it, rate)
            out.append((k, item, self.factor(item, k, X(k), V(k), False)))
        return out

    def key(self, var: Variable, k: int) -> int:
        """The GTSAM key of ``var`` at keyframe ``k`` (a constant's is ``<letter>0``)."""
        return int(gtsam.symbol(var.letter, k if var.per_keyframe else 0))

    def new_at(self, k: int) -> list[Variable]:
        """The variables whose keys are created at keyframe ``k``."""
        return [v for v in self.variables if k == 0 or v.per_keyframe]

    def sees(self, item: MeasurementItem) -> bool:
        """Whether ``item`` depends on one of the variables (then: :meth:`factor`)."""
        return any(item.kind in v.kinds for v in self.variables)

    def priors(self) -> list[gtsam.NonlinearFactor]:
        """Priors of the variables at the first keyframe (zero mean, the ESKF's sigmas;
        the sun azimuth: its first guess, sigma ``SUN_AZIMUTH_STD0``)."""
        c = self.config
        out: list[gtsam.NonlinearFactor] = []
        for var in self.variables:
            if var is ODOMETER_SCALE:
                sig = np.array([ODOMETER_SCALE_STD])
            elif var is MOUNT:
                sig = np.full(2, c.mount_sigma)
            elif var is LEVER:
                sig = np.full(3, c.lever_sigma)
            elif var is SITE_ROTATION:
                assert c.site is not None and c.site_sigma is not None
                sig = np.array(site_rotation_std(c.site.lat, c.site_sigma))
            elif var is SUN_AZIMUTH:
                sig = np.array([SUN_AZIMUTH_STD0, SUN_AZIMUTH_RATE_STD])
            else:
                assert self.bias_std is not None
                sig = np.array([self.bias_std])
            mean = self.guess[self.slices[var]]
            noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
            out.append(gtsam.PriorFactorVector(self.key(var, 0), mean, noise))
        return out

    def between(self, k: int) -> list[gtsam.NonlinearFactor]:
        """The links of the per-keyframe variables from keyframe ``k - 1`` to ``k``."""
        c = self.config
        out: list[gtsam.NonlinearFactor] = []
        dt = float(self.t_key[k] - self.t_key[k - 1])
        for var in self.variables:
            ki, kj = self.key(var, k - 1), self.key(var, k)
            if var is SUN_AZIMUTH:
                out.append(sun_azimuth_factor(ki, kj, dt, SUN_AZIMUTH_RATE_STD))
            elif var in (MOUNT, LEVER):  # constants (module docstring)
                sigma = c.mount_sigma if var is MOUNT else c.lever_sigma
                std = max(float(sigma) * math.sqrt(dt / CONSTANT_S), 1e-12)  # type: ignore[arg-type]
                noise = gtsam.noiseModel.Isotropic.Sigma(var.size, std)
                out.append(gtsam.BetweenFactorVector(ki, kj, np.zeros(var.size), noise))
            elif var is HEADING_BIAS:
                assert self.bias_std is not None
                out.append(gauss_markov_factor(ki, kj, dt, self.bias_std,
                                               c.sky.heading_bias_tau_s))  # fmt: skip
        return out

    def predict(self, extra: FloatArray, k: int) -> FloatArray:
        """The estimates ``extra`` of keyframe ``k`` carried to keyframe ``k + 1``."""
        out = np.array(extra, dtype=float)
        dt = float(self.t_key[k + 1] - self.t_key[k])
        if SUN_AZIMUTH in self.slices:
            s = self.slices[SUN_AZIMUTH]
            out[s.start] += dt * out[s.start + 1]
        if HEADING_BIAS in self.slices:
            out[self.slices[HEADING_BIAS]] *= math.exp(-dt / self.config.sky.heading_bias_tau_s)
        return out

    def initial(self, k: int, extra: FloatArray) -> gtsam.Values:
        """Initial values of the keys created at keyframe ``k`` from the estimates ``extra``."""
        values = gtsam.Values()
        for var in self.new_at(k):
            values.insert(self.key(var, k), np.array(extra[self.slices[var]], dtype=float))
        return values

    def read(
        self,
        k: int,
        value: Callable[[int], FloatArray],
        marginal: Callable[[int], FloatArray] | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """The estimates ``(n,)`` and their covariance ``(n, n)`` (block diagonal over the
        variables; NaN without ``marginal``) at keyframe ``k``, from a solver's
        ``value(key)`` and ``marginal(key)``."""
        x = np.zeros(self.n)
        cov = np.full((self.n, self.n), np.nan if marginal is None else 0.0)
        for var, s in self.slices.items():
            key = self.key(var, k)
            x[s] = value(key)
            if marginal is not None:
                cov[s, s] = marginal(key)
        return x, cov

    def timestamps(self, k: int, t: float) -> dict[int, float]:
        """Fixed-lag smoother timestamps [s] at keyframe ``k``: the constants are renewed at
        every keyframe (they stay in the window), the others have their keyframe's."""
        return {self.key(v, k): t for v in self.variables}

    def thresholds(self) -> list[tuple[str, FloatArray]]:
        """ISAM2 relinearization thresholds per symbol letter: 1e-3 of the variable's units,
        except :data:`RELINEARIZE`'s."""
        return [(v.letter, np.full(v.size, RELINEARIZE.get(v, 1e-3))) for v in self.variables]

    def model(
        self,
        item: MeasurementItem,
        mat_nb: FloatArray,
        vel_n: FloatArray | None,
        tilt_coupling: bool,
        extra: FloatArray,
        bias_g: FloatArray | None = None,
    ) -> Linearized:
        """The shared model of ``item`` (:func:`~polins.fusion.items.item_model`) at the
        nominal state, the gyro bias ``bias_g`` [rad/s] (a zero-rate item's; zero when
        None) and the estimates ``extra``, over ``15 + n`` columns: ``H[:, 15:]`` the
        columns of the variables, the residual taken at their estimates (the ESKF's
        ``Layout.linearize``). A sun vector uses the shared kernel
        (:func:`~polins.fusion.measurement.sun_kernel`) in the tangent basis of the measured
        direction, not of the prediction: its ``R`` is then constant and its Jacobian exact
        for Gauss-Newton (the same first-order model). An odometer speed is divided by
        ``1 + k`` (:func:`~polins.fusion.vehicle.scaled_odometer`), its ``k`` column is the
        predicted speed over ``1 + k`` (the derivative of the scaled residual). With the
        mounting variable, a non-holonomic or odometer item uses the mounting turned by its
        estimate and its columns :func:`~polins.fusion.measurement.mount_jacobian`; with the
        lever-arm variable, the lever arm plus its estimate and
        :func:`~polins.fusion.measurement.lever_jacobian`."""
        it, lin = self._base_model(item, mat_nb, vel_n, tilt_coupling, extra, bias_g)
        if self.n == 0:
            return lin
        H, res = self._variable_columns(item, it, lin, extra)
        return Linearized(wrap_residual(res, lin.name), H, lin.R, lin.name)

    def _base_model(
        self,
        item: MeasurementItem,
        mat_nb: FloatArray,
        vel_n: FloatArray | None,
        tilt_coupling: bool,
        extra: FloatArray,
        bias_g: FloatArray | None = None,
    ) -> tuple[MeasurementItem, Linearized]:
        """The item as modelled (an odometer speed scaled by ``1 + k``) and its shared model
        over the 15 navigation errors, with the variables' estimates ``extra`` as states."""
        idx = self.index
        states: dict[str, FloatArray] = {}
        if bias_g is not None:
            states["bg"] = np.asarray(bias_g, dtype=float)
        if "sun_azimuth_n" in idx:
            states[SUN_AZIMUTH_STATE] = extra[idx["sun_azimuth_n"]]
        for name in (*MOUNT_STATES, LEVER_STATE):
            if name in idx:
                states[name] = extra[idx[name]]
        it = item
        if item.kind == "odo" and "so" in idx:
            it = scaled_odometer(item, {"so": extra[idx["so"]]})
        if item.kind == "sun":  # the tangent basis of the measured direction (docstring)
            assert item.sun_b is not None and item.sun_n is not None
            lin = sun_kernel(mat_nb, item.sun_b, item.sun_n, item.std**2,
                             sun_basis_b(item.sun_b), item.cov_b)  # fmt: skip
        else:
            lin = item_model(it, mat_nb, vel_n, tilt_coupling, states)
        return it, lin

    def _variable_columns(
        self, item: MeasurementItem, it: MeasurementItem, lin: Linearized, extra: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """``H`` over ``15 + n`` columns (the variables' columns appended to ``lin.H``) and
        the residual taken at the variables' estimates ``extra``; ``it`` is ``item`` as
        modelled (:meth:`_base_model`)."""
        idx = self.index
        H = np.zeros((lin.dim, N_ERROR + self.n))
        H[:, :N_ERROR] = lin.H
        res = lin.residual.copy()
        if "so" in idx and item.kind == "odo":
            scale = 1.0 + float(extra[idx["so"]][0])
            H[0, N_ERROR + idx["so"].start] = (it.speed - float(lin.residual[0])) / scale
        if MOUNT_STATES[0] in idx:
            start = N_ERROR + idx[MOUNT_STATES[0]].start
            H[:, start : start + 2] = mount_jacobian(lin)
        if LEVER_STATE in idx:
            cols = lever_jacobian(lin, item.mat_vb, item.gyro_b)
            H[:, N_ERROR + idx[LEVER_STATE].start : N_ERROR + idx[LEVER_STATE].stop] = cols
        if "site_rot_n" in idx:
            cols = sun_attitude_columns(item, lin)
            H[:, N_ERROR + idx["site_rot_n"].start : N_ERROR + idx["site_rot_n"].stop] = cols
            res -= cols @ extra[idx["site_rot_n"]]
        if "sun_azimuth_n" in idx:
            H[:, N_ERROR + idx["sun_azimuth_n"].start] = sun_azimuth_jacobian(item, lin)[:, 0]
        if "heading_bias" in idx:
            col = heading_bias_jacobian(item, lin)
            H[:, N_ERROR + idx["heading_bias"].start] = col[:, 0]
            res -= col[:, 0] * float(extra[idx["heading_bias"]][0])
        return H, res

    def factor(
        self, item: MeasurementItem, k: int, pose_key: int, vel_key: int | None, tilt: bool
    ) -> gtsam.CustomFactor:
        """The factor of ``item`` at keyframe ``k`` (:func:`item_factor` over the variables
        that the item's kind sees)."""
        used = {v: self.key(v, k) for v in self.variables if item.kind in v.kinds}
        batch = self.odometer_batch if item.kind == "odo" and vel_key is not None else None
        return item_factor(self, item, pose_key, vel_key, used, tilt, batch)


def item_factor(
    states: GraphStates,
    item: MeasurementItem,
    pose_key: int,
    vel_key: int | None,
    used: Mapping[Variable, int],
    tilt_coupling: bool,
    batch: OdometerBatch | None = None,
) -> gtsam.CustomFactor:
    """A measurement factor on the shared model with the variables ``used`` (variable ->
    key): ``GraphStates.model`` whitened by its own ``R`` (``R = L L^T``; error ``L^-1 (h -
    z) = -L^-1 residual``, Jacobians ``L^-1 H``, unit noise), so that an ``R`` that depends
    on the state (the sun's 2x2 covariance in the basis of the prediction, an odometer
    speed divided by ``1 + k``) is exact. Attitude columns are mapped to GTSAM's body tangent
    (:func:`~polins.fusion.graph.factors.body_jacobian`); velocity and the variables'
    columns are used as they are (``Vector`` tangents). ``batch``: an odometer factor
    whose only variable is the odometer scale, evaluated with the others
    (:mod:`polins.fusion.graph.batched`)."""
    keys = [pose_key] + ([] if vel_key is None else [vel_key]) + list(used.values())
    cols = [states.slices[v] for v in used]
    dim = 2 if item.kind in ("sun", "nhc") else 1
    slot = -1
    if batch is not None:
        if item.kind != "odo" or list(used) != [ODOMETER_SCALE]:
            raise ValueError("the odometer batch takes odometer factors on X, V and so only")
        slot = batch.add(keys, item.speed, item.std,
                         np.eye(3) if item.mat_vb is None else item.mat_vb,
                         np.zeros(3) if item.lever_vel_b is None else item.lever_vel_b)  # fmt: skip

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        if batch is not None:
            hit = batch.lookup(slot, values, jacobians)
            if hit is not None:
                return hit
        mat_nb = values.atPose3(pose_key).rotation().matrix()
        vel = None if vel_key is None else values.atVector(vel_key)
        extra = states.guess.copy()
        for s, key in zip(cols, used.values(), strict=True):
            extra[s] = values.atVector(key)
        lin = states.model(item, mat_nb, vel, tilt_coupling, extra)
        white = whitener(lin.R)

        if jacobians is not None:
            jacobians[0] = white(body_jacobian(lin.H[:, ATT], mat_nb))
            i = 1
            if vel_key is not None:
                jacobians[1] = white(np.ascontiguousarray(lin.H[:, VEL]))
                i = 2
            for j, s in enumerate(cols, i):
                jacobians[j] = white(np.ascontiguousarray(lin.H[:, N_ERROR + s.start :
                                                                N_ERROR + s.stop]))  # fmt: skip
        return white(-lin.residual)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(dim), keys, error)


__all__ = [
    "AZIMUTH_VAR_FLOOR",
    "GraphStates",
    "Variable",
    "gauss_markov_factor",
    "item_factor",
    "sun_azimuth_factor",
]
