"""The fusion's entry points: ``fuse`` (the solution table), ``run_fusion`` (the full result) and ``build_filter`` (streaming)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from polins.fusion.config import FuseConfig, config_with_site
from polins.fusion.eskf.batch import fuse_eskf
from polins.fusion.eskf.filter import ESKF
from polins.fusion.faults import ImplausibleRunError, nis_verdict
from polins.fusion.inputs import prepare
from polins.fusion.items import HEADING_KINDS
from polins.fusion.result import FusionResult


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
    progress: bool = False,
) -> FusionResult:
    """Fuse an IMU log with measurements: the solution, the update log and the run's facts.

    The arguments are those of :func:`fuse`, with the options in ``config``; ``progress``
    shows a tqdm line while the graph solves. One
    preparation (:func:`polins.fusion.inputs.prepare`: validation, the fault policy of
    docs/faults.md, the resolved configuration), then the backend solves. The GTSAM
    backend (``polins.fusion.graph.fuse_graph``) is imported only when asked for.

    Raises
    ------
    ImuUnitsError
        The IMU data look like other units than declared (a ``UserInputError``).
    ImplausibleRunError
        The run's NIS is far outside any plausible band
        (:func:`polins.fusion.faults.nis_verdict`); its ``result`` holds the run.
    """
    prep = prepare(imu, measurements, backend, rot_nb0, config, odometry)
    if backend == "graph":
        from polins.fusion.graph import fuse_graph  # gtsam: only when asked for

        result = fuse_graph(prep, progress)
    else:
        result = fuse_eskf(prep)
    check_plausible(result)
    return result


def check_plausible(result: FusionResult) -> None:
    """Raise :class:`~polins.fusion.faults.ImplausibleRunError` when the NIS of the
    heading updates is far outside any plausible band (:func:`~polins.fusion.faults.nis_verdict`)."""
    upd = result.updates
    heading = upd["name"].isin(HEADING_KINDS).to_numpy() if len(upd) else np.zeros(0, bool)
    verdict = nis_verdict(upd["nis"].to_numpy()[heading], upd["dim"].to_numpy()[heading])
    if verdict:
        raise ImplausibleRunError(verdict, result)


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
        lists its columns), smoothed with ``smooth=True``: the ``solution`` of
        :func:`run_fusion`, whose :class:`~polins.fusion.result.FusionResult` also holds the
        update log, the events, the filtered solution and the resolved configuration.

    Raises
    ------
    ImuUnitsError, ImplausibleRunError
        As :func:`run_fusion`.
    """
    config = FuseConfig.from_options(config, **options)
    return run_fusion(imu, measurements, backend, rot_nb0, config, odometry).solution
