"""The fusion's entry points: ``fuse`` (a solution table), ``run_fusion`` (the full result) and ``build_filter`` (streaming)."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from polins.errors import UserInputError
from polins.fusion.acquisition import gap_variance, skip_in_gaps
from polins.fusion.config import (
    TIME_TOL_S,
    FuseConfig,
    config_with_site,
    scaled_measurement_noise,
)
from polins.fusion.eskf.filter import ESKF
from polins.fusion.eskf.propagate import advance, interpolate
from polins.fusion.eskf.smoother import rts_smooth
from polins.fusion.inputs import (
    PRIOR_COLUMNS,
    ImuArrays,
    check_gyro_against_headings,
    output_mask,
    validate_imu,
    validate_measurements,
)
from polins.fusion.items import (
    MeasurementItem,
    items_from_table,
    no_clock_table,
    records_table,
)
from polins.fusion.result import FusionEvent, FusionResult, events_table
from polins.fusion.vehicle import odometer_items
from polins.ins.state import solution_table


def build_filter(
    t0: float,
    dt: float,
    rot_nb0: Rotation | None = None,
    config: FuseConfig | None = None,
    **options: Any,
) -> ESKF:
    """The :class:`~polins.fusion.eskf.ESKF` that :func:`fuse` runs, for streaming use.

    Feeding it the IMU samples (``propagate``) with the measurement rows queued
    (``add_measurement``) gives ``fuse``'s results within the discretisation error
    (``state().row()`` is a row of the solution table).

    Parameters
    ----------
    t0 : float
        Time of the first IMU sample [s].
    dt : float
        IMU sample interval [s] (sets the covariance-step and non-holonomic cadence).
    rot_nb0 : Rotation, optional
        Initial attitude; None for self-alignment.
    config : FuseConfig, optional
        The configuration; ``options`` (:class:`FuseConfig` field names, ``lat_deg/lon_deg/
        alt_m`` for ``site``) replace its values. No site: one ``UserWarning``.
    """
    cfg = config_with_site(FuseConfig.from_options(config, **options), stacklevel=3)
    cfg.check_backend("eskf")
    return ESKF(cfg, float(t0), float(dt), rot_nb0)


def run_fusion(
    imu: pd.DataFrame,
    measurements: pd.DataFrame | None = None,
    backend: str = "eskf",
    rot_nb0: Rotation | None = None,
    config: FuseConfig | None = None,
    odometry: pd.DataFrame | None = None,
) -> FusionResult:
    """Fuse an IMU log with measurements: the solution, the update log and the run's facts.

    The arguments are those of :func:`fuse`, with the options in ``config``. The GTSAM
    backend (``polins.fusion.graph.fuse_graph``) is imported only when asked for.
    """
    cfg = config or FuseConfig()
    cfg.check_backend(backend)
    meas = scaled_measurement_noise(validate_measurements(measurements), cfg)
    check_gyro_against_headings(imu, meas)
    cfg = config_with_site(cfg, stacklevel=4)
    if no_clock_table(meas):
        cfg = announce_no_clock(cfg)
    cfg = cfg.resolve(priors=all(c in meas.columns for c in PRIOR_COLUMNS),
                      odometry=odometry is not None)  # fmt: skip
    if backend == "graph":
        from polins.fusion.graph import fuse_graph  # gtsam: only when asked for

        return fuse_graph(imu, meas, rot_nb0, cfg, odometry)
    arrays = validate_imu(imu, max_gap_s=cfg.gap_s, model=cfg.imu)
    t, W, A = arrays.t, arrays.gyro_b, arrays.accel_b
    filt = ESKF(cfg, float(t[0]), arrays.dt, rot_nb0)
    items = items_from_table(meas, use_sun=cfg.gating.use_sun, heading_bias=cfg.heading_bias)
    if odometry is not None and cfg.odometer_sigma is not None:  # "off": ignored
        items += odometer_items(odometry, cfg.odometer_sigma)
    items, events = bridge_gaps(arrays, items)
    filt.add_items(items)
    if not filt.ready:
        k_end = int(np.searchsorted(t - t[0], cfg.initial.align_s - TIME_TOL_S, side="left"))
        if k_end >= len(t):
            raise UserInputError(
                f"the IMU log ({t[-1] - t[0]:.3f} s) is shorter than the alignment window "
                f"align_s={cfg.initial.align_s} s; give rot_nb0 or a longer log"
            )
        filt.level([(float(t[k]), W[k], A[k]) for k in range(k_end + 1)])
    run = advance(filt, t, W, A, output_mask(t, cfg.output_rate), full=cfg.output.smooth)
    assert run is not None
    nodes, rows = run
    slices = filt.layout.index
    filtered = solution_table(interpolate(nodes, rows, slices))
    solution = filtered
    if cfg.output.smooth:
        assert nodes.P_pre is not None and nodes.P_post is not None and nodes.Phi is not None
        delta, P_s = rts_smooth(nodes.P_pre, nodes.P_post, nodes.Phi, nodes.dx, nodes.linked)
        solution = solution_table(interpolate(nodes, rows, slices, delta, P_s))
    info = {"imu_model": cfg.imu.name, "n_resets": filt.n_resets, "options": cfg.changes()}
    return FusionResult(
        solution, records_table(filt.records), filtered if cfg.output.smooth else None, "eskf", info,
        events_table([*arrays.events, *events, *filt.events]),
    )  # fmt: skip


def announce_no_clock(config: FuseConfig) -> FuseConfig:
    """The config of a measurements table in the no-clock mode (sun_azimuth_b without yaw
    or sun_n), with the one warning that says so (both backends)."""
    config = config.resolve(sun_azimuth_only=True)  # no_clock=off: a one-line error
    warnings.warn(
        "no-clock mode: the measurements carry sun_azimuth_b without yaw or sun_n; the sun's "
        "ENU azimuth is a filter state and the heading is relative to the initial yaw "
        "(absolute heading is not observable without a clock; docs/filter.md, 'No clock')",
        UserWarning,
        stacklevel=4,
    )
    return config


def bridge_gaps(
    arrays: ImuArrays, items: list[MeasurementItem]
) -> tuple[list[MeasurementItem], list[FusionEvent]]:
    """The measurement items with the IMU gaps longer than ``max_gap_s`` handled
    (docs/faults.md): the measurements inside a gap are rejected (invalid items with a
    reason), and a ``"gap"`` item at the sample after it inflates the covariance
    (:func:`~polins.fusion.acquisition.gap_variance`); an event for each. The graph skips
    the same measurements (:func:`~polins.fusion.acquisition.skip_in_gaps`).

    Returns
    -------
    items : list of MeasurementItem
        In the input order, the ``"gap"`` items after them.
    events : list of FusionEvent
    """
    t, gaps = arrays.t, arrays.gaps
    out, events = skip_in_gaps(t, gaps, items)
    for i in gaps.tolist():
        t_a, t_b = float(t[i]), float(t[i + 1])
        inflation = gap_variance(t_b - t_a, (arrays.gyro_b[i], arrays.gyro_b[i + 1]),
                                 (arrays.accel_b[i], arrays.accel_b[i + 1]))  # fmt: skip
        events.append(FusionEvent(t_a, "imu-gap", f"IMU gap of {t_b - t_a:.3g} s until "
                                  f"t={t_b:.6g}: propagated across, covariance inflated"))  # fmt: skip
        out.append(MeasurementItem(t_b, "gap", t_b - t_a, inflation=inflation))
    return out, events


def fuse(
    imu: pd.DataFrame,
    measurements: pd.DataFrame | None = None,
    backend: str = "eskf",
    rot_nb0: Rotation | None = None,
    *,
    config: FuseConfig | None = None,
    odometry: pd.DataFrame | None = None,
    **options: Any,
) -> pd.DataFrame:
    """Fuse an IMU log with polarization yaw / sun-vector measurements.

    Parameters
    ----------
    imu : DataFrame
        Columns ``t`` [s], ``gx, gy, gz`` [rad/s], ``ax, ay, az`` [m/s^2]: body (FLU)
        angular rate and specific force, instantaneous at ``t``.
    measurements : DataFrame, optional
        Columns ``t`` and ``yaw, yaw_std`` [rad] and/or ``sun_bx, sun_by, sun_bz``
        (measured, body), ``sun_nx, sun_ny, sun_nz`` (reference, ENU), ``sun_std`` [rad];
        optionally ``zupt_std`` [m/s] and the prior ``prior_roll/pitch/yaw`` [rad]. NaN
        values are skipped (logged). None: no aiding.
    backend : {"eskf", "graph"}
        Error-state Kalman filter (:mod:`polins.fusion.eskf`) or the GTSAM factor graph
        (``polins.fusion.graph``, needs ``gtsam``).
    rot_nb0 : Rotation, optional
        Initial attitude (body FLU -> ENU). None: self-alignment (roll/pitch from the
        accelerometer over ``align_s`` at rest, yaw from the first valid measurement).
    config : FuseConfig, optional
        The configuration (``polins.fusion.config.option_table()`` lists the options).
    odometry : DataFrame, optional
        Wheel-odometer speeds: columns ``t`` [s] and ``speed`` [m/s] (forward, vehicle
        frame), fused with ``odometer_std`` (default 0.05 m/s) and an odometer scale-factor
        state (a variable in the graph; docs/filter.md, "Ground-vehicle aiding").
    **options
        :class:`FuseConfig` field names replacing the values of ``config``;
        ``lat_deg, lon_deg, alt_m`` are a shorthand for ``site``. An unknown name is a
        ``TypeError``; no site: one ``UserWarning`` naming the site assumed.

    Returns
    -------
    DataFrame
        The solution table (:func:`polins.ins.state.solution_table`; docs/filter.md
        lists its columns), smoothed with ``smooth=True``. ``attrs`` carries ``updates``,
        ``events``, ``backend``, ``imu_model`` and (smoothed) ``filtered`` for compatibility; pandas
        operations drop them: :func:`run_fusion` returns them in a ``FusionResult``.
    """
    result = run_fusion(
        imu, measurements, backend, rot_nb0, FuseConfig.from_options(config, **options), odometry
    )
    sol = result.solution
    sol.attrs["updates"] = result.updates
    sol.attrs["backend"] = result.backend
    sol.attrs["imu_model"] = result.info.get("imu_model")
    sol.attrs["events"] = result.events
    if result.filtered is not None:
        sol.attrs["filtered"] = result.filtered
    return sol
