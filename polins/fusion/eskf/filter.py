"""The error-state Kalman filter: nominal strapdown state, error state and covariance, measurement queue, resets.

:class:`ESKF` holds the nominal navigation state (attitude as a matrix, ENU velocity,
geodetic position), the sensor-error estimates by block name and the error state ``x``
with its covariance ``P`` (blocks of :mod:`polins.fusion.eskf.blocks`). The reported
estimate is always ``nominal (+) x``. The prediction is ``x = Phi x``, ``P = Phi P Phi^T + Q``
(filterpy's ``predict``), the update filterpy's (Joseph form:
:func:`~polins.fusion.eskf.update.kalman_update`); innovations are gated with a chi-square test
(:func:`~polins.fusion.items.gate_limit`, each rejection logged with its reason) and the
normalised innovation squared (NIS) of every update is recorded.

Streaming use: :meth:`ESKF.propagate` once per IMU sample (the nominal state by
:func:`~polins.ins.strapdown.strapdown_increment`, the covariance every ``cov_step_s`` and
at each measurement time), :meth:`ESKF.add_measurement` for each measurement row (applied
when the IMU reaches its time, with the IMU interpolated linearly to it), :meth:`ESKF.state`
for the current estimate. :mod:`polins.fusion.eskf.propagate` runs the same filter over
runs of samples, through the public methods below (the interface
:class:`polins.fusion.eskf.propagate.Filter` lists).

Reset policy ("closed loop at a reduced rate"): the error estimate is injected into the
nominal state and zeroed after the first processed measurement at least
``reset_interval_s`` after the previous reset, or as soon as the attitude error estimate
exceeds ``reset_angle_rad``. Between resets the updates act on the error state only, so the
nominal state between resets does not depend on them (what the fast path exploits).

Ground-vehicle constraints: ``nhc_std`` applies the non-holonomic constraint (no lateral,
no vertical body velocity) at ``nhc_rate_hz``; measurement rows with ``zupt_std`` a
zero-velocity update. The non-holonomic Jacobian depends on the nominal velocity, so its
sigma must also cover the linearisation error (0.05 m/s is a sound default for a car).

Alignment: ``rot_nb0`` given, or self-alignment (:mod:`polins.fusion.eskf.alignment`): the
vehicle static for ``align_s``, the yaw unknown (NaN) until ``acquire_k`` headings agree;
after ``reacquire_after`` consecutive rejections it is re-acquired, and a ``"gap"`` item
inflates the covariance (:mod:`polins.fusion.eskf.acquisition`, docs/filter.md 7.1-7.2).
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Mapping, Sequence

import numpy as np
from filterpy.kalman import KalmanFilter
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.errors import UserInputError
from polins.fusion.config import (
    COV_STEP_S,
    NHC_RATE_HZ,
    RESET_ANGLE_RAD,
    RESET_INTERVAL_S,
    TIME_TOL_S,
    FuseConfig,
    config_with_site,
)
from polins.fusion.eskf.acquisition import Acquisition, hold_heading
from polins.fusion.eskf.alignment import level
from polins.fusion.eskf.blocks import Block, Layout, error_blocks, inject_nav, scale_divisors
from polins.fusion.eskf.dynamics import StepNominal, StepSums, discretize
from polins.fusion.eskf.propagate import advance, checked_run
from polins.fusion.eskf.update import innovation, kalman_update
from polins.fusion.faults import FusionEvent, skip_in_gaps
from polins.fusion.items import (
    HEADING_KINDS,
    MeasurementItem,
    UpdateRecord,
    gate_limit,
    measurement_items,
)
from polins.fusion.measurement import Linearized
from polins.fusion.sky_states import ModelPart
from polins.fusion.vehicle import VehicleAiding, consider_states, consider_update
from polins.ins.state import NavState
from polins.ins.strapdown import Mechanization, strapdown_increment

FloatArray = NDArray[np.float64]
log = logging.getLogger("polins.fusion")


class ESKF:
    """Error-state Kalman filter holding its state; streaming interface (module docstring).

    Parameters
    ----------
    config : FuseConfig
        The configuration (the site must be set: :func:`polins.fusion.config.config_with_site`).
    t0 : float
        Time of the first IMU sample [s] (the filter starts there).
    dt : float
        IMU sample interval [s]: sets the samples per covariance step (``cov_step_s``) and
        per non-holonomic update (``NHC_RATE_HZ``).
    rot_nb0 : Rotation, optional
        Initial attitude; None for self-alignment.
    blocks : sequence of Block, optional
        The error-state blocks (default :func:`~polins.fusion.eskf.blocks.error_blocks`
        of ``config``; docs/filter.md, "Adding a state block").
    cov_step_s, reset_interval_s : float
        Internal hooks (tests, benchmarks): the longest covariance-propagation step [s]
        and the interval of the error-state resets [s]
        (:data:`polins.fusion.config.COV_STEP_S`, ``RESET_INTERVAL_S``).
    """

    def __init__(
        self,
        config: FuseConfig,
        t0: float,
        dt: float,
        rot_nb0: Rotation | None = None,
        blocks: Sequence[Block] | None = None,
        *,
        cov_step_s: float = COV_STEP_S,
        reset_interval_s: float = RESET_INTERVAL_S,
    ) -> None:
        if not isinstance(config, FuseConfig):
            raise TypeError(f"config must be a FuseConfig, got {type(config).__name__}")
        if not (math.isfinite(dt) and dt > 0):
            raise UserInputError(f"dt must be a positive IMU sample interval [s], got {dt}")
        if rot_nb0 is not None and (not isinstance(rot_nb0, Rotation) or not rot_nb0.single):
            raise UserInputError(
                "rot_nb0 must be a single scipy Rotation (body FLU -> ENU) or None"
            )
        config = config_with_site(config, stacklevel=3)
        assert config.site is not None
        self.config = config
        self.model = config.imu
        earth = config.mechanize_earth_rate
        self.mech = Mechanization(earth_rotation=earth, transport_rate=earth)
        self.layout = Layout(error_blocks(config) if blocks is None else blocks)
        self.n = self.layout.n
        self.qc = self.layout.noise_density(self.model)
        self.cov_every = max(1, int(cov_step_s / dt + 1e-9))
        self.reset_interval_s = float(reset_interval_s)
        self.nhc_every = max(1, round(1.0 / (NHC_RATE_HZ * dt)))
        self.vehicle = VehicleAiding(config, dt)  # NHC, standstill (fusion/vehicle.py)
        self._aid: list[tuple[float, FloatArray, FloatArray]] = []  # samples for the vehicle
        self.tilt_coupling = config.tilt_coupling
        self.t = float(t0)
        self.mat_nb = (rot_nb0 or Rotation.identity()).as_matrix()
        self.vel_n = np.array(config.initial.vel_n0, dtype=float)
        self.lat, self.lon, self.alt_m = config.site.lat, config.site.lon, config.site.alt_m
        self.errors = {b.name: np.zeros(b.size) for b in self.layout.sensor}
        self.x = np.zeros(self.n)
        self.P = self.layout.initial_covariance(self.model, config)
        self._kf = KalmanFilter(dim_x=self.n, dim_z=1)  # lends its arrays to kalman_update
        self.records: list[UpdateRecord] = []
        self.events: list[FusionEvent] = []  # yaw re-acquisitions
        self.yaw_aligned = rot_nb0 is not None
        self.yaw_epoch = 0  # (re-)acquisitions of the yaw: a new smoother chain each
        self.acquisition = Acquisition(
            config.gating.acquire_k, config.gating.acquire_n, config.gating.reacquire_after
        )
        model = config.heading_bias == "model"  # the bias variance from the images
        self.model_part = ModelPart(config.sky.heading_bias_tau_s) if model else None
        self.t_reset = float(t0)
        self.n_resets = 0
        self.count = 0  # real IMU samples consumed
        self.correction = np.zeros(self.n)  # sum of the update corrections (the smoother's)
        self._t0 = float(t0)
        self._pending: list[MeasurementItem] = []
        self._cur: tuple[float, FloatArray, FloatArray] | None = None  # last (virtual) sample
        self._last: tuple[float, FloatArray, FloatArray] | None = None  # last real sample
        self._align_buffer: list[tuple[float, FloatArray, FloatArray]] | None = (
            None if rot_nb0 is not None else []
        )
        self._sums = StepSums()

    # ------------------------------------------------------------------ properties
    @property
    def ready(self) -> bool:
        """True once levelling is done (a state is available)."""
        return self._align_buffer is None

    @property
    def started(self) -> bool:
        """True once the first IMU sample (after levelling) is consumed."""
        return self._cur is not None

    @property
    def last_sample(self) -> tuple[float, FloatArray, FloatArray] | None:
        """The last real IMU sample consumed ``(t, gyro_b, accel_b)`` (raw), or None."""
        return self._last

    @property
    def pending(self) -> tuple[MeasurementItem, ...]:
        """The queued measurement items, in processing order."""
        return tuple(self._pending)

    def skip_in_gap(self, t_a: float, t_b: float) -> list[FusionEvent]:
        """Make the queued items strictly inside the IMU gap ``t_a .. t_b`` [s] invalid, as
        :func:`~polins.fusion.faults.skip_in_gaps` does for a table (a stream learns of a
        gap after it queued them); their ``measurement-in-gap`` events."""
        self._pending, events = skip_in_gaps([(t_a, t_b)], self._pending)
        return events

    def copy(self) -> ESKF:
        """A cheap copy: arrays copied, model/config/layout shared, an empty update log
        and event list."""
        new = copy.copy(self)
        new.mat_nb, new.vel_n = self.mat_nb.copy(), self.vel_n.copy()
        new.errors = {k: v.copy() for k, v in self.errors.items()}
        new.x, new.P, new.correction = self.x.copy(), self.P.copy(), self.correction.copy()
        new.records, new.events = [], []
        new.acquisition, new.vehicle = copy.deepcopy(self.acquisition), self.vehicle.copy()
        new.model_part = copy.deepcopy(self.model_part)
        new._pending = list(self._pending)
        new._aid = list(self._aid)
        if self._align_buffer is not None:
            new._align_buffer = list(self._align_buffer)
        new._sums = copy.deepcopy(self._sums)
        return new

    # ------------------------------------------------------------------ streaming API
    def propagate(self, t: float, gyro_b: ArrayLike, accel_b: ArrayLike) -> list[UpdateRecord]:
        """Consume one IMU sample (instantaneous rate and specific force at ``t``).

        Applies the pending measurements with times up to ``t`` on the way.

        Returns
        -------
        list of UpdateRecord
            Records of the measurements applied during this call.
        """
        t = float(t)
        w = np.array(gyro_b, dtype=float)
        f = np.array(accel_b, dtype=float)
        if (
            w.shape != (3,)
            or f.shape != (3,)
            or not (np.isfinite(w).all() and np.isfinite(f).all() and math.isfinite(t))
        ):
            raise ValueError("gyro_b and accel_b must be finite 3-vectors [rad/s], [m/s^2]")
        n_before = len(self.records)
        tol = TIME_TOL_S
        buffer = self._align_buffer
        if buffer is None:
            self._consume(t, w, f)
            return self.records[n_before:]
        if buffer and t <= buffer[-1][0]:
            raise ValueError(f"IMU time {t} is not after the previous sample {buffer[-1][0]}")
        if not buffer and abs(t - self._t0) > tol:
            raise ValueError(f"the first IMU sample must be at t0={self._t0}, got {t}")
        buffer.append((t, w, f))
        if t - self._t0 >= self.config.initial.align_s - tol:
            self.level(buffer)
            for s in buffer:
                self._consume(*s)
        return self.records[n_before:]

    def propagate_many(
        self, t: ArrayLike, gyro_b: ArrayLike, accel_b: ArrayLike
    ) -> list[UpdateRecord]:
        """Consume a run of IMU samples, vectorised (:func:`polins.fusion.eskf.propagate.advance`).

        The same filter as one :meth:`propagate` per sample, within the discretisation
        error (a covariance step in progress ends at the first sample of the run).

        Parameters
        ----------
        t : (N,) array_like
            Sample times [s], strictly increasing, after the last consumed sample.
        gyro_b, accel_b : (N, 3) array_like
            Raw body rates [rad/s] and specific forces [m/s^2].
        """
        t_a, W, A = checked_run(t, gyro_b, accel_b)
        N = t_a.shape[0]
        n_before = len(self.records)
        k = 0
        while k < N and not (self.ready and self.started):  # levelling, first sample
            self.propagate(t_a[k], W[k], A[k])
            k += 1
        if k < N:
            last = self._last
            assert last is not None
            if t_a[k] <= last[0]:
                raise ValueError(f"IMU time {t_a[k]} is not after the previous sample {last[0]}")
            self.flush()
            T = np.concatenate([[last[0]], t_a[k:]])
            advance(self, T, np.vstack([last[1], W[k:]]), np.vstack([last[2], A[k:]]))
        return self.records[n_before:]

    def add_measurement(
        self,
        t: float,
        *,
        yaw: float | None = None,
        yaw_std: float | None = None,
        sun_b: ArrayLike | None = None,
        sun_n: ArrayLike | None = None,
        sun_std: float | None = None,
        zupt_std: float | None = None,
        rot_nb_prior: Rotation | None = None,
        sky: Mapping[str, float] | None = None,
    ) -> list[UpdateRecord]:
        """Queue (or apply now, if ``t`` is the current time) one measurement row.

        Parameters are the ``measurements`` table's columns (docs/filter.md): a yaw and its
        1-sigma [rad]; and/or a measured body sun vector, its ENU reference and direction
        1-sigma [rad]; and/or a zero-velocity 1-sigma [m/s]; ``rot_nb_prior`` is the prior
        ``polins.measure`` used for the yaw (tilt coupling); ``sky`` the further columns of
        :func:`~polins.fusion.items.measurement_items`. A measurement older than the
        filter time is rejected (logged): the filter does not re-process the past.

        Returns
        -------
        list of UpdateRecord
            Records of the items applied now (empty if queued).
        """
        items = measurement_items(
            t, yaw=yaw, yaw_std=yaw_std, sun_b=sun_b, sun_n=sun_n, sun_std=sun_std,
            zupt_std=zupt_std, use_sun=self.config.gating.use_sun, rot_nb_prior=rot_nb_prior, sky=sky,
            heading_bias=self.config.heading_bias,
        )  # fmt: skip
        return self.add_items(items)

    def add_items(self, items: Sequence[MeasurementItem]) -> list[UpdateRecord]:
        """Queue measurement items (see :meth:`add_measurement`)."""
        n_before = len(self.records)
        tol = TIME_TOL_S
        started = self.started and self.ready
        queued = False
        for item in items:
            if started and item.t < self.t - tol:
                self.reject(item, f"out of sequence: t={item.t} is before the filter time {self.t}")
            elif started and abs(item.t - self.t) <= tol and not self._pending:
                self.apply(item)
            else:
                self._pending.append(item)
                queued = True
        if queued:
            self._pending.sort(key=lambda it: it.order)
        return self.records[n_before:]

    def state(self) -> NavState:
        """Current estimate ``nominal (+) x`` with the sigmas of every block.

        Inside a covariance step, the error state and covariance are propagated over the
        step so far (its own mean dynamics); the filter itself is not changed.
        """
        if not self.ready:
            raise RuntimeError("the filter is still levelling (self-alignment); feed more samples")
        x, P = self.x, self.P
        if self._sums.n:
            Phi, Q = self.step_matrices(self._step_nominal())
            x, P = Phi @ x, Phi @ P @ Phi.T + Q
        lay = self.layout
        sig = np.sqrt(np.clip(np.diag(P), 0.0, None))
        mat, vel, lat, lon, alt = inject_nav(
            self.mat_nb, self.vel_n, self.lat, self.lon, self.alt_m, x[:9]
        )
        return NavState(
            t=self.t,
            rot_nb=Rotation.from_matrix(mat),
            vel_n=vel,
            lat=float(lat),
            lon=float(lon),
            alt_m=float(alt),
            errors={k: v + x[lay[k]] for k, v in self.errors.items()},
            sigma={b.name: sig[lay[b.name]] for b in lay.blocks},
            att_cov=P[lay["att"], lay["att"]].copy(),
            yaw_aligned=self.yaw_aligned,
        )

    # ------------------------------------------------------------------ the filter's steps
    def nominal(self) -> tuple[float, FloatArray, FloatArray, float, float, float]:
        """The nominal state ``(t, mat_nb, vel_n, lat, lon, alt_m)``."""
        return self.t, self.mat_nb, self.vel_n, self.lat, self.lon, self.alt_m

    def set_nominal(
        self, t: float, mat_nb: FloatArray, vel_n: FloatArray, lat: float, lon: float, alt_m: float
    ) -> None:
        """Move the nominal state (the fast path: to a sample of its strapdown run)."""
        self.t, self.mat_nb, self.vel_n = float(t), mat_nb, vel_n
        self.lat, self.lon, self.alt_m = float(lat), float(lon), float(alt_m)

    def step_matrices(self, step: StepNominal) -> tuple[FloatArray, FloatArray]:
        """``(Phi, Q)`` ``(n, n)`` of one covariance step."""
        qc = self.layout.step_noise(self.qc, self.model, step)
        Phi, Q = discretize(self.layout.dynamics(step), step.dt, qc)
        return Phi[0], Q[0]

    def predict(self, Phi: FloatArray, Q: FloatArray) -> None:
        """Propagate the error state and covariance over a step: ``x = Phi x``,
        ``P = Phi P Phi^T + Q`` (filterpy's ``predict`` without its argument handling)."""
        self.x = Phi @ self.x
        self.P = Phi @ self.P @ Phi.T + Q

    def flush(self) -> None:
        """Propagate the covariance over the step in progress (streaming); hand the
        vehicle's detector the samples it has not seen."""
        if self._feed_vehicle():  # pragma: no cover - a bug: epochs are fed as they come
            raise RuntimeError("vehicle items between the vehicle's epochs")
        if self._sums.n:
            self.predict(*self.step_matrices(self._step_nominal()))
            self._sums = StepSums()
            # keep the attitude matrix orthonormal (rounding of the per-sample products)
            self.mat_nb = Rotation.from_matrix(self.mat_nb).as_matrix()

    def take_items(self, t_end: float) -> list[MeasurementItem]:
        """Remove and return the queued items up to ``t_end`` [s] (in processing order)."""
        k = 0
        while k < len(self._pending) and self._pending[k].t <= t_end:
            k += 1
        items, self._pending = self._pending[:k], self._pending[k:]
        return items

    def finish_run(self, t: float, gyro_b: FloatArray, accel_b: FloatArray, count: int) -> None:
        """After a fast-path run: the last real sample and the number of samples consumed."""
        self._cur = self._last = (float(t), gyro_b.copy(), accel_b.copy())
        self.count = count

    def linearize(self, item: MeasurementItem) -> Linearized:
        """The measurement model of ``item`` over all blocks, at the nominal state."""
        return self.layout.linearize(item, self.mat_nb, self.vel_n, self.tilt_coupling,
                                     self.errors)  # fmt: skip

    def reject(self, item: MeasurementItem, reason: str) -> UpdateRecord:
        """Log an item as not used."""
        return self._record(item, 0, math.nan, False, reason)

    def apply(self, item: MeasurementItem) -> UpdateRecord | None:
        """Gate and apply one measurement at the current time; then maybe reset. Headings
        before the yaw is acquired are held for it (:mod:`~polins.fusion.eskf.acquisition`);
        a ``"gap"`` item inflates the covariance (no record)."""
        if self._sums.n:
            self.flush()
        if item.kind == "gap":
            assert item.inflation is not None
            self.P[:9, :9] += np.diag(item.inflation)
            return None
        if not item.valid:
            return self.reject(item, item.reason or "invalid measurement")
        if self.model_part is not None and item.kind in HEADING_KINDS:
            item = self._model_heading_bias(item)
        if not self.yaw_aligned and item.kind in ("yaw", "sun"):
            return hold_heading(self, item, None)
        if item.kind == "odo":  # the lever arm at the current rate, the scale estimate
            item = self.vehicle.odometer(item, self.errors, self._cur)
        rec = self._gate_and_update(item, self.linearize(item))
        x_att = self.x[0:3]
        if (
            self.t - self.t_reset >= self.reset_interval_s
            or float(np.dot(x_att, x_att)) > RESET_ANGLE_RAD**2
        ):
            self.reset()
        return rec

    def _model_heading_bias(self, item: MeasurementItem) -> MeasurementItem:
        """Pass a heading through the heading-bias model; adopt its process-noise density."""
        assert self.model_part is not None
        i = self.layout.index["heading_bias"].start
        item, density = self.model_part.take(item, self.P, i)
        if density != self.qc[i]:
            self.qc = self.qc.copy()  # shared with copies of the filter
            self.qc[i] = density
        return item

    def _gate_and_update(self, item: MeasurementItem, lin: Linearized) -> UpdateRecord:
        """Chi-square gate on the NIS; the Kalman update if it passes, logged either way."""
        nis, nu, S = innovation(lin, self.x, self.P)
        dim = lin.residual.shape[0]
        limit = gate_limit(self.config.gate_probability, dim)
        if nis > limit:
            reason = (f"NIS above the gate: {nis:.3g} > {limit:.3g} (chi2, {dim} dof, "
                      f"p={self.config.gate_probability})")  # fmt: skip
            rec = self._record(item, dim, nis, False, reason, nu, S)
            if item.kind in ("yaw", "sun"):
                self.acquisition.rejections += 1
                rec = hold_heading(self, item, rec)
            return rec
        if item.kind in ("yaw", "sun") and self.acquisition.held:
            self.acquisition.clear()
        x_before = self.x
        if self.yaw_aligned and lin.name != "level":
            self.x, self.P = kalman_update(self._kf, self.x, self.P, lin)
        else:  # yaw unknown, or a levelling: consider states (fusion/vehicle.py)
            held = consider_states(lin.name, self.yaw_aligned, self.layout.index)
            self.x, self.P = consider_update(self.x, self.P, lin.residual, lin.R, lin.H, held)
        self.correction += self.x - x_before
        return self._record(item, dim, nis, True, "", nu, S)

    def reset(self) -> None:
        """Inject the error estimate into the nominal state and zero it (reset Jacobian I)."""
        self.flush()
        x = self.x
        self.mat_nb, self.vel_n, lat, lon, alt = inject_nav(
            self.mat_nb, self.vel_n, self.lat, self.lon, self.alt_m, x[:9]
        )
        self.lat, self.lon, self.alt_m = float(lat), float(lon), float(alt)
        self.errors = {k: v + x[self.layout[k]] for k, v in self.errors.items()}
        self.x = np.zeros(self.n)
        self.t_reset = self.t
        self.n_resets += 1

    def level(self, samples: Sequence[tuple[float, FloatArray, FloatArray]]) -> None:
        """Self-alignment of roll/pitch over the static window (:func:`level`).

        ``samples`` are the raw ``(t, gyro_b, accel_b)`` from ``t0``; those up to
        ``align_s`` are used. Ends the levelling (``ready``).
        """
        tol = TIME_TOL_S
        use = [s for s in samples if s[0] - self._t0 <= self.config.initial.align_s + tol]
        self._align_buffer = None
        self.mat_nb, self.P = level(
            np.array([s[0] for s in use]), np.array([s[1] for s in use]),
            np.array([s[2] for s in use]), self.lat, self.alt_m, self.P, self.layout, self.config,
            self.mech,
        )  # fmt: skip
        self.vel_n = np.zeros(3)
        self.yaw_aligned = self.yaw_aligned or self.config.no_clock  # relative heading

    # ------------------------------------------------------------------ internals
    def _record(
        self,
        item: MeasurementItem,
        dim: int,
        nis: float,
        accepted: bool,
        reason: str,
        innovation: tuple[float, ...] = (),
        innovation_var: tuple[float, ...] = (),
    ) -> UpdateRecord:
        rec = UpdateRecord(
            item.t, item.kind, dim, nis, accepted, reason, innovation, innovation_var
        )
        self.records.append(rec)
        if not accepted:
            log.info("t=%.6f %s rejected: %s", item.t, item.kind, reason)
        return rec

    def _consume(self, t: float, w: FloatArray, f: FloatArray) -> None:
        """One real IMU sample: apply the pending items up to ``t``, step to ``t``."""
        tol = TIME_TOL_S
        if self._cur is None:
            if abs(t - self._t0) > tol:
                raise ValueError(f"the first IMU sample must be at t0={self._t0}, got {t}")
            self._cur = self._last = (t, w, f)
        else:
            t_a, w_a, f_a = self._last  # type: ignore[misc]
            if t <= t_a:
                raise ValueError(f"IMU time {t} is not after the previous sample {t_a}")
            while self._pending and self._pending[0].t <= t + tol:
                item = self._pending.pop(0)
                if item.t < self.t - tol:
                    self.reject(
                        item, f"out of sequence: t={item.t} is before the filter time {self.t}"
                    )
                    continue
                if item.t > self.t + tol:
                    if item.t >= t - tol:
                        self._step(t, w, f)
                    else:  # a virtual sample at the item time
                        frac = (item.t - t_a) / (t - t_a)
                        self._step(item.t, w_a + (w - w_a) * frac, f_a + (f - f_a) * frac)
                self.apply(item)
            if t > self.t + tol:
                self._step(t, w, f)
            self._last = (t, w, f)
        self.count += 1
        if self.vehicle.active:
            self._vehicle_sample(t, w, f)
        while self._pending and abs(self._pending[0].t - self.t) <= tol:
            self.apply(self._pending.pop(0))

    def _vehicle_sample(self, t: float, w: FloatArray, f: FloatArray) -> None:
        """The sample just consumed, for the vehicle's detector; at the vehicle's epochs
        (where its items come) the samples since the last one are handed over and the
        items applied."""
        self._aid.append((t, w, f))
        g = self.count - 1
        if g >= 1 and g % self.vehicle.every == 0:
            for _, item in self._feed_vehicle():
                self.apply(item)

    def _feed_vehicle(self) -> list[tuple[int, MeasurementItem]]:
        """The samples held for the vehicle's detector since its last epoch, handed to it
        at once (:meth:`VehicleAiding.items`: the same items as one call per sample);
        its items."""
        if not self._aid:
            return []
        t, w, f = zip(*self._aid, strict=True)
        index0 = self.count - len(self._aid)
        self._aid = []
        return self.vehicle.items(np.array(t), np.array(w), np.array(f), index0)

    def _step(self, t1: float, w1: FloatArray, f1: FloatArray) -> None:
        """Propagate the nominal state to ``t1``; accumulate the covariance step."""
        t0, w0, f0 = self._cur  # type: ignore[misc]
        (wc0, wc1), (fc0, fc1) = self.layout.correct(
            np.array([w0, w1]), np.array([f0, f1]), self.errors
        )
        dt = t1 - t0
        mat1, v1, lat1, lon1, h1, mat_h, dv_force = strapdown_increment(
            self.mat_nb, self.vel_n, self.lat, self.lon, self.alt_m, wc0, wc1, fc0, fc1, dt,
            self.mech,
        )  # fmt: skip
        self._sums.add((self.vel_n, self.lat, self.alt_m), mat_h, dv_force, (wc0, wc1),
                       (fc0, fc1), dt, scale_factors="sg" in self.errors,
                       rate_noise=bool(self.model.gyro_misalignment))  # fmt: skip
        self.set_nominal(t1, mat1, v1, lat1, lon1, h1)
        self._cur = (t1, w1, f1)
        if self._sums.n >= self.cov_every:
            self.flush()

    def _step_nominal(self) -> StepNominal:
        """The :class:`StepNominal` of the step in progress."""
        return self._sums.nominal(self.mech, scale_divisors(self.errors), "sg" in self.errors)
