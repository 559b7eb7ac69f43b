"""The graph's problem: keyframes, IMU integration steps, factors per keyframe, keyframe estimates.

:class:`Problem` holds what the solvers (:mod:`polins.fusion.graph.solvers`) need: the
keyframe times, the preintegration parameters, the measurement factors per keyframe, the
priors of the first state (the keyframe results:
:class:`~polins.fusion.graph.estimates.Estimates`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.fusion.acquisition import consensus, yaw_offset
from polins.fusion.config import (
    INTEGRATION_STD,
    MAX_KEYFRAME_DT_S,
    TIME_TOL_S,
    FuseConfig,
)
from polins.fusion.faults import FusionEvent
from polins.fusion.graph.batched import (
    FactorBatch,
    NonHolonomicBatch,
    ScaleImuBatch,
    YawBatch,
)
from polins.fusion.graph.factors import (
    gyro_noise_density,
    levelling_factor,
    non_holonomic_factor,
    pose_cov_body_from_nav,
    preintegration_params,
    sun_factor,
    yaw_factor,
    zero_rate_factor,
    zero_velocity_factor,
)
from polins.fusion.graph.imu import (
    imu_segments,
    increment_jacobians,
    scale_factor_imu_factor,
    scale_factor_links,
    scale_factor_priors,
    scale_keys,
)
from polins.fusion.graph.states import GraphStates
from polins.fusion.items import HEADING_KINDS, MeasurementItem, UpdateRecord
from polins.fusion.priors import EARTH_RATE_TURN_S
from polins.fusion.vehicle import vehicle_items
from polins.ins.alignment import level_from_accel
from polins.ins.earth import (
    OMEGA_IE,
    earth_rate_n,
    normal_gravity,
    radii_of_curvature,
    transport_rate_n,
)
from polins.site import Site

FloatArray = NDArray[np.float64]

HELD = "held for the yaw acquisition"  # the ESKF's wording (polins.fusion.eskf.acquisition)


def keyframe_times(
    t_start: float, t_end: float, t_events: ArrayLike, max_keyframe_dt_s: float
) -> FloatArray:
    """Keyframe times [s]: start, end, every event time inside, and evenly spaced fill-ins
    so that no interval exceeds ``max_keyframe_dt_s``. Events closer than 1 us merge."""
    ev = np.asarray(t_events, dtype=float)
    base = np.union1d([t_start, t_end], ev[(ev >= t_start) & (ev <= t_end)])
    base = base[np.concatenate([[True], np.diff(base) > 1e-6])]
    if base[-1] < t_end:  # the merge may have dropped t_end
        base[-1] = t_end
    out = [base[:1]]
    for a, b in itertools.pairwise(base):
        n = int(np.ceil((b - a) / max_keyframe_dt_s - 1e-9))
        out.append(a + (b - a) * np.arange(1, n + 1) / n)
    return np.concatenate(out)


def snap_times(t: ArrayLike, t_imu: FloatArray, tol_s: float) -> FloatArray:
    """Times [s] within ``tol_s`` of an IMU sample moved onto that sample."""
    t = np.asarray(t, dtype=float)
    k = np.clip(np.searchsorted(t_imu, t - tol_s), 0, len(t_imu) - 1)
    return np.where(np.abs(t_imu[k] - t) <= tol_s, t_imu[k], t)


@dataclass(frozen=True, eq=False)
class MeasFactor:
    """A yaw, sun or zero-velocity factor at keyframe ``k`` with the item it came from (to
    gate and log it)."""

    k: int
    item: MeasurementItem
    factor: gtsam.NonlinearFactor


class Problem:
    """One fusion problem: keyframes, IMU steps, GTSAM parameters, factors per keyframe.

    Parameters
    ----------
    config : FuseConfig
        The run's options (``config.site`` set: :func:`polins.fusion.graph.fuse_graph`
        substitutes the assumed site).
    tilt_coupling : bool
        The resolved ``config.tilt_coupling``.
    t_imu, gyro, accel : ndarray
        Validated IMU samples [s], [rad/s], [m/s^2].
    items : list of MeasurementItem
        The measurement items (:func:`polins.fusion.items.items_from_table`).
    rot_nb0 : Rotation or None
        Initial attitude, or None for self-alignment.
    gaps : sequence of (t_a, t_b, variance)
        The IMU gaps longer than ``max_gap_s`` [s] and the variances their ``"gap"`` items
        add to the 9 navigation errors (``ImuArrays.gap_spans``, ``ImuArrays.gaps``,
        :func:`polins.fusion.faults.gap_item`): keyframes at their ends, and the IMU noise
        of the intervals inside raised by the attitude and velocity variances, the ESKF's
        inflation (docs/faults.md).
    """

    def __init__(
        self,
        config: FuseConfig,
        tilt_coupling: bool,
        t_imu: FloatArray,
        gyro: FloatArray,
        accel: FloatArray,
        items: list[MeasurementItem],
        rot_nb0: Rotation | None,
        gaps: Sequence[tuple[float, float, FloatArray]] = (),
    ) -> None:
        assert isinstance(config.site, Site)  # fuse_graph substitutes the assumed site
        self.config = config
        self.tilt_coupling = tilt_coupling
        self.earth_rate = config.mechanize_earth_rate
        self.lat = float(np.radians(config.site.lat_deg))
        self.lon = float(np.radians(config.site.lon_deg))
        self.alt_m = float(config.site.alt_m)
        self.gravity = float(normal_gravity(self.lat, self.alt_m))
        self.params = self._params()
        t0, t1 = float(t_imu[0]), float(t_imu[-1])
        aiding = [it for it in items if it.valid and it.kind in HEADING_KINDS]
        zupts = [it for it in items if it.valid and it.kind == "zupt"]
        odos = [it for it in items if it.valid and it.kind == "odo"]  # (graph/states.py)
        # The vehicle's NHC and standstill pseudo-measurements, at the ESKF's epochs.
        ground = vehicle_items(config, t_imu, gyro, accel)
        n_given = len(zupts)
        zupts += [it for it in ground if it.kind == "zupt"]
        nhcs = [it for it in ground if it.kind == "nhc"]
        zarus = [it for it in ground if it.kind == "zaru"]
        # Times within TIME_TOL_S of an IMU sample are moved onto it (as the ESKF does).
        t_aid = snap_times([it.t for it in aiding], t_imu, TIME_TOL_S).tolist()
        t_zupt = snap_times([it.t for it in zupts], t_imu, TIME_TOL_S).tolist()
        nhc_t = np.array([it.t for it in nhcs], dtype=float)
        # (start, end, variances of the attitude and velocity errors) of each IMU gap
        self.gaps = [(t_a, t_b, np.asarray(var)[[0, 3]]) for t_a, t_b, var in gaps]
        t_gaps = [t for a, b, _ in self.gaps for t in (a, b)]
        t_odo = snap_times([it.t for it in odos], t_imu, TIME_TOL_S).tolist()
        zaru_t = np.array([it.t for it in zarus], dtype=float)
        events = np.concatenate([t_aid, t_zupt, nhc_t, zaru_t, t_gaps, t_odo])
        self.t_key = keyframe_times(t0, t1, events, MAX_KEYFRAME_DT_S)
        self.segments = imu_segments(t_imu, gyro, accel, self.t_key)
        n_key = len(self.t_key)
        self.interval_params = self._interval_params()
        # the increments' Jacobians on the scale factors (graph/imu.py), None without them
        seg = self.segments
        self.scale_jac = (increment_jacobians(seg.gyro, seg.accel, seg.dt, seg.bounds)
                          if config.use_scale_factors else None)  # fmt: skip
        self.states = GraphStates(config, self.t_key, aiding)  # odometer scale, sky variables
        # the Python factors evaluated by type in the batch solver (graph/batched.py)
        self.nhc_batch, self.yaw_batches = NonHolonomicBatch(), (YawBatch(False), YawBatch(True))
        aiding = [self.states.prepare(it) for it in aiding]

        self.meas: list[MeasFactor] = []
        self.outside: list[MeasurementItem] = []
        self._place_headings(aiding, t_aid)
        self.aux = self._nhc_factors(nhcs, n_key)
        # else unknown until the first yaw / sun; no clock: relative to the first yaw
        self.yaw_given = rot_nb0 is not None or config.no_clock
        self.held: list[UpdateRecord] = []  # headings rejected by the yaw acquisition
        self.events: list[FusionEvent] = []
        self.state0, self.bias0, self.priors = self._first_state(t_imu, accel, rot_nb0)
        self.states.start(self.meas, self.state0.attitude().matrix())
        self.priors += self.states.priors()
        # the variables' links from keyframe k - 1 to k
        self.links: list[list[gtsam.NonlinearFactor]] = [[]]
        self.links += [self.states.between(k) for k in range(1, n_key)]
        self.n_headings = len(self.meas)  # the yaw / sun factors kept by the acquisition
        # Zero velocity: gated like the headings (the standstill detector also fires at
        # a constant speed; the ESKF's gate rejects those updates too).
        self.detected: set[int] = set()  # those of the standstill detector
        self._place_zupts(zupts, t_zupt, n_given)
        self._place_zero_rates(zarus)
        keys = [self.key_of(t) for t in t_odo]
        self.meas += [MeasFactor(*m) for m in self.states.odometer(odos, keys, t_imu, gyro)]
        self.meas_at: list[list[int]] = [[] for _ in range(n_key)]
        for i, mf in enumerate(self.meas):
            self.meas_at[mf.k].append(i)

    def _place_headings(self, aiding: list[MeasurementItem], t_aid: list[float]) -> None:
        """The yaw / sun factors at their keyframes; items outside the keyframes kept aside."""
        for it, t in zip(aiding, t_aid, strict=True):
            k = self.key_of(t)
            if k is None:
                self.outside.append(it)
            else:
                self.meas.append(MeasFactor(k, it, self._aiding_factor(X(k), it)))

    def _nhc_factors(
        self, nhcs: list[MeasurementItem], n_key: int
    ) -> list[list[gtsam.NonlinearFactor]]:
        """The non-holonomic constraints of each keyframe (through the mounting variable
        when the run estimates it)."""
        aux: list[list[gtsam.NonlinearFactor]] = [[] for _ in range(n_key)]
        for it in nhcs:
            k = self.key_of(it.t)
            if k is not None and self.states.sees(it):  # the mounting variable
                aux[k].append(self.states.factor(it, k, X(k), V(k), False))
            elif k is not None:
                aux[k].append(non_holonomic_factor(X(k), V(k), it.std, it.mat_vb, it.lever_vel_b,
                                                   self.nhc_batch))  # fmt: skip
        return aux

    def _place_zupts(self, zupts: list[MeasurementItem], t_zupt: list[float], n_given: int) -> None:
        """The zero-velocity factors at their keyframes; those after the first ``n_given``
        (the standstill detector's) are marked in ``self.detected``."""
        for j, (it, t) in enumerate(zip(zupts, t_zupt, strict=True)):
            k = self.key_of(t)
            if k is not None:
                if j >= n_given:
                    self.detected.add(len(self.meas))
                self.meas.append(MeasFactor(k, it, zero_velocity_factor(V(k), it.std)))

    def _place_zero_rates(self, zarus: list[MeasurementItem]) -> None:
        """The zero-rate factors at their keyframes, gated as the detector's zero-velocity
        factors (``self.detected``; docs/filter.md §12.1). Under self-alignment, from the
        first heading on: before it the yaw is unknown, and the Earth rate's projection
        would tie the bias to it (the ESKF holds the yaw as a consider state there)."""
        if not self.yaw_given:
            first = min((mf.item.t for mf in self.meas), default=math.inf)
            zarus = [it for it in zarus if it.t >= first]
        for it in zarus:
            key = self.key_of(it.t)
            if key is not None and it.gyro_b is not None:
                self.detected.add(len(self.meas))
                factor = zero_rate_factor(X(key), B(key), it.gyro_b, it.std, it.rate_n)
                self.meas.append(MeasFactor(key, it, factor))

    def _params(self, **densities: Any) -> gtsam.PreintegrationCombinedParams:
        """Preintegration parameters of the run with the densities ``densities`` replaced
        (:func:`~polins.fusion.graph.factors.preintegration_params`); without a site the
        gyro bias random walk covers the unmechanized Earth rate, as the ESKF's
        (docs/filter.md, "Without a site")."""
        c = self.config
        if c.uncovered_earth_rate:
            densities.setdefault(
                "gyro_bias_density", c.imu.gyro_bias_rw**2 + OMEGA_IE**2 / EARTH_RATE_TURN_S
            )
        return preintegration_params(
            c.imu,
            gravity_mps2=self.gravity,
            omega_ie_n=earth_rate_n(self.lat) if self.earth_rate else None,
            integration_std=INTEGRATION_STD,
            **densities,
        )

    def _interval_params(self) -> list[gtsam.PreintegrationCombinedParams]:
        """Preintegration parameters of each keyframe interval: the gyro noise density with
        the rotation-proportional term of the interval's mean ``|omega_b|^2``
        (:func:`~polins.fusion.graph.factors.gyro_noise_density`, docs/filter.md §9); inside
        an IMU gap the gyro and accelerometer densities raised so that the interval adds
        the gap's variances (``self.gaps``)."""
        c, seg = self.config, self.segments
        energy = np.concatenate(
            [[0.0], np.cumsum(np.einsum("ij,ij->i", seg.gyro, seg.gyro) * seg.dt)]
        )
        rate_sq = np.diff(energy[seg.bounds]) / np.diff(seg.t[seg.bounds])
        mid = 0.5 * (self.t_key[1:] + self.t_key[:-1])
        gyro = gyro_noise_density(c.imu, rate_sq)
        accel = np.full(gyro.shape[0], c.imu.accel_vrw**2)
        for t_a, t_b, (att_var, vel_var) in self.gaps:  # spread over the gap's intervals
            inside = (mid > t_a) & (mid < t_b)
            gyro[inside] += att_var / (t_b - t_a)
            accel[inside] += vel_var / (t_b - t_a)
        if np.all(gyro == c.imu.gyro_arw**2) and np.all(accel == c.imu.accel_vrw**2):
            return [self.params] * len(rate_sq)
        return [
            self._params(gyro_density=float(g), accel_density=float(a))
            for g, a in zip(gyro, accel, strict=True)
        ]

    def key_of(self, t: float) -> int | None:
        """The keyframe at time ``t`` [s] (within 1 us), or None."""
        n_key = len(self.t_key)
        k = int(np.clip(np.searchsorted(self.t_key, t), 1, n_key - 1))
        k = k if abs(self.t_key[k] - t) < abs(self.t_key[k - 1] - t) else k - 1
        return k if abs(self.t_key[k] - t) < 1e-6 else None

    def _aiding_factor(self, key: int, it: MeasurementItem) -> gtsam.NonlinearFactor:
        prior = it.sun_n is not None and it.mat_nb_prior is not None
        if it.kind == "yaw" and self.tilt_coupling and not prior:
            raise ValueError(
                f"tilt_coupling: the yaw row at t={it.t} needs sun_nx/ny/nz and the "
                "prior_roll/prior_pitch/prior_yaw of the image (the graph "
                "re-linearizes away from the prior polins.measure used)"
            )
        if self.states.sees(it) or it.cov_b is not None:  # graph/states.py: shared model
            k = int(gtsam.Symbol(key).index())
            return self.states.factor(it, k, key, None, self.tilt_coupling)
        if it.kind == "sun":
            return sun_factor(key, it.sun_n, it.sun_b, it.std)  # type: ignore[arg-type]
        if not self.tilt_coupling:
            return yaw_factor(key, it.yaw, it.std, batch=self.yaw_batches[0])
        return yaw_factor(key, it.yaw, it.std, sun_n=it.sun_n, rot_nb_prior=it.mat_nb_prior,
                          batch=self.yaw_batches[1])  # fmt: skip

    def _first_state(
        self, t_imu: FloatArray, accel: FloatArray, rot_nb0: Rotation | None
    ) -> tuple[gtsam.NavState, gtsam.imuBias.ConstantBias, list[gtsam.NonlinearFactor]]:
        """First keyframe's initial values and priors (module docstring of the package)."""
        c, m = self.config, self.config.imu
        bias0 = gtsam.imuBias.ConstantBias()
        gyro_bias = np.hypot(m.gyro_bias, OMEGA_IE) if c.uncovered_earth_rate else m.gyro_bias
        bias_sigmas = np.concatenate([np.full(3, m.accel_bias_turn_on), np.full(3, gyro_bias)])
        priors: list[gtsam.NonlinearFactor] = [
            gtsam.PriorFactorConstantBias(
                B(0), bias0, gtsam.noiseModel.Diagonal.Sigmas(np.maximum(bias_sigmas, 1e-12))
            )
        ]
        vel_n0 = np.asarray(c.initial.vel_n0, dtype=float)
        if rot_nb0 is not None:
            att_var = np.asarray(c.initial.att_std0, dtype=float) ** 2
            turn = self._acquire(rot_nb0, vel_n0, float(np.sqrt(att_var[2])), att_var[:2])
            rot = Rotation.from_rotvec([0.0, 0.0, turn]) * rot_nb0
            if turn != 0.0:
                att_var[2] = 1.0  # re-acquired: the prior's yaw is released
        else:
            window = t_imu <= t_imu[0] + c.initial.align_s
            f_mean = accel[window].mean(axis=0)
            duration = max(float(t_imu[window][-1] - t_imu[0]), 1.0 / m.sample_rate_hz)
            roll, pitch = level_from_accel(f_mean)
            vel_n0 = np.zeros(3)
            level = Rotation.from_euler("ZYX", [0.0, pitch, roll])
            if not self.meas:
                raise ValueError(
                    "self-alignment (rot_nb0=None) needs a valid yaw or sun-vector "
                    "measurement; give rot_nb0 or measurements"
                )
            std = max(m.accel_vrw / np.sqrt(duration), 1e-9)
            tilt_var = np.full(2, (std**2 + m.accel_bias_turn_on**2) / self.gravity**2)
            rot = Rotation.from_rotvec([0.0, 0.0, self._acquire(level, vel_n0, None, tilt_var)])
            rot = rot * level
            priors.append(levelling_factor(X(0), B(0), f_mean, std))
            # Tilt from the levelling factor only (1e4 rad is no information); yaw 1 rad
            # until the first yaw / sun measurement (the ESKF's P[2, 2] = 1).
            att_var = np.array([1e8, 1e8, 1.0])
            if c.no_clock:  # the heading is relative to the levelled yaw (docs/filter.md §5.7)
                att_var[2] = 1e-12
        mat_nb = rot.as_matrix()
        cov_n = np.diag(np.concatenate([att_var, np.full(3, c.initial.pos_std0**2)]))
        state0 = gtsam.NavState(gtsam.Rot3(mat_nb), np.zeros(3), vel_n0)
        priors.append(
            gtsam.PriorFactorPose3(
                X(0),
                state0.pose(),
                gtsam.noiseModel.Gaussian.Covariance(pose_cov_body_from_nav(mat_nb, cov_n)),
            )
        )
        priors.append(
            gtsam.PriorFactorVector(
                V(0), vel_n0, gtsam.noiseModel.Isotropic.Sigma(3, c.initial.vel_std0)
            )
        )
        return state0, bias0, priors

    def _acquire(
        self, rot0: Rotation, vel_n0: FloatArray, yaw_std0: float | None, tilt_var: FloatArray
    ) -> float:
        """The yaw acquisition of the graph (docs/filter.md §7.1, §9): the turn [rad] of the
        first keyframe's yaw.

        The keyframes are dead-reckoned from ``rot0`` (zero bias); each heading gives its
        :func:`~polins.fusion.acquisition.yaw_offset` there (with the first keyframe's
        tilt variances ``tilt_var`` [rad^2], East and North), and the headings are taken in
        time order until ``acquire_k`` of the last ``acquire_n`` agree
        (:func:`~polins.fusion.acquisition.consensus`), as the ESKF does online.

        * Self-alignment (``yaw_std0`` None): the consensus sets the yaw; the headings held
          before it that disagree leave the graph (``held for the yaw acquisition:
          disagrees``, or ``no consensus`` when they left the window). No consensus at
          all: every heading leaves the graph and the yaw stays unknown (NaN).
        * A given ``rot_nb0`` (yaw 1-sigma ``yaw_std0``): if the consensus differs from its
          yaw by more than ``3 sqrt(yaw_std0^2 + std^2)``, the yaw is re-acquired from the
          consensus (its prior released, a ``yaw-reacquired`` event); else nothing changes.
        """
        c = self.config
        if c.no_clock:  # a relative heading: nothing to acquire (docs/filter.md §5.7)
            return 0.0
        order = sorted(range(len(self.meas)), key=lambda i: self.meas[i].k)
        state = gtsam.NavState(gtsam.Rot3(rot0.as_matrix()), np.zeros(3), vel_n0)
        bias, k_state = gtsam.imuBias.ConstantBias(), 0
        offsets: list[float] = []
        stds: list[float] = []
        found = None
        for i in order:
            mf = self.meas[i]
            for k in range(k_state, mf.k):
                state = self.preintegrate(k, bias, np.zeros(6)).predict(state, bias)
            k_state = max(k_state, mf.k)
            mat = state.attitude().matrix()
            offset, std, _ = yaw_offset(mf.item, mat, None, self.tilt_coupling, np.diag(tilt_var))
            offsets.append(offset)
            stds.append(std)
            lo = max(0, len(offsets) - c.gating.acquire_n)
            res = consensus(np.array(offsets[lo:]), np.array(stds[lo:]), c.gating.acquire_k)
            if res is not None:
                found = (res[0], res[1], res[2] + lo, len(offsets) - 1)
                break
        if yaw_std0 is not None:
            if found is None or abs(found[0]) <= 3.0 * math.hypot(yaw_std0, found[1]):
                return 0.0
            mean, _std, members, last = found
            t_last = self.meas[order[last]].item.t
            detail = (
                f"re-acquired: {members.size} of {min(last + 1, c.gating.acquire_n)} headings "
                f"agree on a yaw {math.degrees(mean):.1f} deg from the initial attitude's"
            )
            self.events.append(FusionEvent(t_last, "yaw-reacquired", detail))
            return mean
        last = len(order) - 1 if found is None else found[3]
        used = set() if found is None else {order[j] for j in found[2].tolist()}
        for pos, i in enumerate(order[: last + 1]):
            if i in used:
                continue
            it = self.meas[i].item
            agreed = found is not None and pos > last - c.gating.acquire_n
            why = (
                "disagrees"
                if agreed
                else f"no consensus of {c.gating.acquire_k} in {c.gating.acquire_n}"
            )
            self.held.append(UpdateRecord(it.t, it.kind, 0, math.nan, False, f"{HELD}: {why}"))
        drop = set(order[: last + 1]) - used
        self.meas = [mf for i, mf in enumerate(self.meas) if i not in drop]
        return 0.0 if found is None else found[0]

    def imu_correction(self, state: gtsam.NavState) -> FloatArray:
        """What to subtract from the (gyro, accelerometer) samples of the next interval (6,).

        Gyro: the transport rate in body axes, ``C_bn omega_en_n`` [rad/s] (with Earth rate
        only, like the ESKF's mechanization). Accelerometer: ``C_bn (0, 0, g(lat, h) - g0)``
        [m/s^2], the change of normal gravity since the start, since GTSAM's gravity is
        constant. Both at the current estimate ``state`` of the keyframe.
        """
        lat, _lon, alt_m = self.geodetic(state.position())
        mat_bn = state.attitude().matrix().T
        corr = np.zeros(6)
        corr[3:] = mat_bn @ np.array([0.0, 0.0, float(normal_gravity(lat, alt_m)) - self.gravity])
        if self.earth_rate:
            corr[:3] = mat_bn @ transport_rate_n(lat, alt_m, state.velocity())
        return corr

    def geodetic(self, pos_n: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Latitude, longitude [rad] and height [m] of local ENU positions ``(..., 3)`` [m]."""
        p = np.asarray(pos_n, dtype=float)
        r_m, r_n = radii_of_curvature(self.lat)
        lat = self.lat + p[..., 1] / (r_m + self.alt_m)
        lon = self.lon + p[..., 0] / ((r_n + self.alt_m) * np.cos(self.lat))
        return lat, lon, self.alt_m + p[..., 2]

    def local_position(self, lat: FloatArray, lon: FloatArray, alt_m: FloatArray) -> FloatArray:
        """Local ENU positions ``(N, 3)`` [m] of geodetic ones [rad], [m]: the inverse of
        :meth:`geodetic`."""
        r_m, r_n = radii_of_curvature(self.lat)
        east = (lon - self.lon) * (r_n + self.alt_m) * np.cos(self.lat)
        north = (lat - self.lat) * (r_m + self.alt_m)
        return np.stack([east, north, alt_m - self.alt_m], axis=-1)

    def preintegrate(
        self, k: int, bias: gtsam.imuBias.ConstantBias, correction: FloatArray
    ) -> gtsam.PreintegratedCombinedMeasurements:
        """Preintegrated IMU from keyframe ``k`` to ``k + 1`` (``correction``: see
        :meth:`imu_correction`)."""
        seg = self.segments
        pim = gtsam.PreintegratedCombinedMeasurements(self.interval_params[k], bias)
        lo, hi = seg.bounds[k], seg.bounds[k + 1]
        gyro = seg.gyro[lo:hi] - correction[:3]
        accel = seg.accel[lo:hi] - correction[3:]
        for a, w, dt in zip(accel, gyro, seg.dt[lo:hi], strict=True):
            pim.integrateMeasurement(a, w, dt)
        return pim

    def imu_factor(
        self,
        k: int,
        pim: gtsam.PreintegratedCombinedMeasurements,
        scale: bool = True,
        batch: ScaleImuBatch | None = None,
    ) -> Any:
        """``CombinedImuFactor`` between keyframes ``k`` and ``k + 1``; with scale factors
        (and ``scale``) wrapped to depend on them
        (:func:`~polins.fusion.graph.imu.scale_factor_imu_factor`, evaluated in ``batch``)."""
        factor = gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim)
        if self.scale_jac is None or not scale:
            return factor
        return scale_factor_imu_factor(factor, self.scale_jac[k], *scale_keys(k), batch)

    def batches(self) -> list[FactorBatch]:
        """The batches of the factors built here (the IMU factors' are the graph's)."""
        odometer = self.states.odometer_batch
        return [self.nhc_batch, *self.yaw_batches, *([odometer] if odometer else [])]

    def scale_factors_at(self, k: int) -> list[gtsam.NonlinearFactor]:
        """The scale factors' priors (``k = 0``) or their link from keyframe ``k - 1``
        (:func:`~polins.fusion.graph.imu.scale_factor_links`); empty without them."""
        if self.scale_jac is None:
            return []
        std = (self.config.imu.gyro_scale_factor, self.config.imu.accel_scale_factor)
        if k == 0:
            return scale_factor_priors(*std)
        return scale_factor_links(k, float(self.t_key[k] - self.t_key[k - 1]), *std)

    def keys_at(self, k: int, constants: bool) -> list[int]:
        """The keys of keyframe ``k`` (and, with ``constants``, of the run's constants)."""
        keys = [X(k), V(k), B(k), *self.scale_values(k).keys()]
        keys += [self.states.key(v, k) for v in self.states.variables if v.per_keyframe]
        if constants:
            keys += [self.states.key(v, 0) for v in self.states.variables if not v.per_keyframe]
        return keys

    def scale_values(self, k: int) -> gtsam.Values:
        """Initial values of keyframe ``k``'s scale factors ``sg, sa`` (zero: the factors
        are linear in them; empty without them)."""
        values = gtsam.Values()
        if self.scale_jac is not None:
            for key in scale_keys(k):
                values.insert(key, np.zeros(3))
        return values
