"""Fusion of IMU with polarization measurements: measurement models, ESKF and GTSAM backends.

Entry point: :func:`fuse` (also ``polins.fuse``). Modules: :mod:`polins.fusion.measurement`
(the shared ``(z, H, R)`` models), :mod:`polins.fusion.eskf` (error-state Kalman filter with
a streaming interface and an RTS smoother), :mod:`polins.fusion.inputs` (validation of the
input tables), ``polins.fusion.graph`` (GTSAM factor graph, imported lazily).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from polins.fusion.batch import run_batch
from polins.fusion.eskf import (
    ESKF,
    EskfOptions,
    FilterState,
    solution_columns,
)
from polins.fusion.inputs import (
    PRIOR_COLUMNS,
    validate_imu,
    validate_measurements,
)
from polins.fusion.items import (
    MeasurementItem,
    items_from_table,
    records_table,
)
from polins.ins.strapdown import Mechanization
from polins.models.loader import ImuModel, load_imu

DEFAULT_SITE = (45.6234, 126.7264, 148.74)  # the paper's site (Harbin), as in polins.sim

_FUSE_OPTIONS = {
    "imu_model": "IMU error model: shipped name or TOML path or ImuModel (default 'mems-typical')",
    "lat_deg": "start latitude [deg] (default: the paper's site, with a warning)",
    "lon_deg": "start longitude [deg]",
    "alt_m": "start height above the WGS-84 ellipsoid [m]",
    "vel_n0": "initial ENU velocity [m/s] (default 0)",
    "earth_rate": "mechanize Earth and transport rate (default: imu_model.earth_rate)",
    "scale_factors": (
        "estimate gyro/accel scale factors (21 states; default False). Turn it on for "
        "IMUs with ~1000 ppm scale factors: without it the yaw sigma of 'mems-typical' is "
        "optimistic in turns (yaw RMS(err/sigma) 1.36 in 50 runs of 120 s; with it 1.04 in "
        "50 runs of 300 s, tests/test_eskf.py)"
    ),
    "gate_prob": "chi-square gate probability, None = no gate (default 0.9973)",
    "reset_interval_s": "error-state reset interval [s] (default 20.0)",
    "reset_angle_rad": "reset as soon as |dtheta| exceeds this [rad] (default 0.005)",
    "align_s": "static levelling window for self-alignment [s] (default 1.0)",
    "att_std0": "initial attitude 1-sigma when rot_nb0 is given [rad] (default 1 deg)",
    "vel_std0": "initial velocity 1-sigma [m/s] (default 0.1)",
    "pos_std0": "initial position 1-sigma [m] (default 1.0)",
    "use_sun": "use a row's sun vector instead of its yaw (default True)",
    "tilt_coupling": "tilt-coupled yaw model (default: True if the table has prior_* columns)",
    "nhc_std": "non-holonomic constraint 1-sigma [m/s], None = off (default)",
    "nhc_rate_hz": "rate of the non-holonomic constraint [Hz] (default 10)",
    "zupt_std": "zero-velocity 1-sigma [m/s] at the `stationary` times",
    "stationary": "times [s] at which the vehicle is known to stand still",
    "output_rate_hz": "output rows per second (default None: every IMU sample)",
    "smooth": "run the Rauch-Tung-Striebel smoother (default False)",
    "max_gap_s": "longest allowed IMU gap [s] (default 5 median intervals)",
    "fast": "vectorised batch path (default True) or the per-sample streaming path",
    "time_tol": "measurement times this close to an IMU sample use it [s] (default 1e-6)",
    "cov_step_s": "longest covariance-propagation step [s] (default 0.1)",
}


def _resolve_model(model: Any) -> ImuModel:
    if isinstance(model, ImuModel):
        return model
    if isinstance(model, str | Path):
        return load_imu(model)
    raise ValueError(f"imu_model must be a model name, a TOML path or an ImuModel, got {model!r}")


def output_mask(t: np.ndarray, rate_hz: float | None) -> np.ndarray:
    """IMU samples reported at ``rate_hz``: the first sample at or after each grid time
    ``t[0] + k / rate_hz``, and the last sample (all samples for None)."""
    if rate_hz is None:
        return np.ones(len(t), dtype=bool)
    if not rate_hz > 0:
        raise ValueError(f"output_rate_hz must be > 0 or None, got {rate_hz}")
    cell = np.floor((t - t[0]) * rate_hz + 1e-9)
    mask = np.concatenate([[True], np.diff(cell) > 0])
    mask[-1] = True
    return mask


_OUTPUT_OPTIONS = {"output_rate_hz", "smooth", "max_gap_s", "fast", "zupt_std", "stationary"}


# options of fuse that configure the filter itself (the others are the site and outputs)
FILTER_OPTIONS = (
    "earth_rate", "scale_factors", "gate_prob", "reset_interval_s", "reset_angle_rad",
    "align_s", "att_std0", "vel_std0", "pos_std0", "use_sun", "tilt_coupling", "nhc_std",
    "nhc_rate_hz", "cov_step_s", "time_tol",
)  # fmt: skip


def check_filter_options(options: Any) -> None:
    """Raise TypeError naming the option names that are not :data:`FILTER_OPTIONS`."""
    unknown = sorted(set(options) - set(FILTER_OPTIONS))
    if unknown:
        raise TypeError(f"unknown filter option(s) {unknown}; valid: {', '.join(FILTER_OPTIONS)}")


def eskf_options(imu_model: ImuModel, dt: float, **options: Any) -> EskfOptions:
    """The :class:`~polins.fusion.eskf.EskfOptions` that :func:`fuse` builds.

    Parameters
    ----------
    imu_model : ImuModel
        Its ``earth_rate`` is the default of ``earth_rate``.
    dt : float
        IMU sample interval [s]: turns ``nhc_rate_hz`` and ``cov_step_s`` into sample strides.
    **options
        :data:`FILTER_OPTIONS` by their :func:`fuse` names (an unknown name is a TypeError).
    """
    check_filter_options(options)
    if not dt > 0:
        raise ValueError(f"dt must be a positive IMU sample interval [s], got {dt}")
    opts = dict(options)
    earth = opts.pop("earth_rate", None)
    earth = imu_model.earth_rate if earth is None else bool(earth)
    nhc_rate = float(opts.pop("nhc_rate_hz", 10.0))
    if not nhc_rate > 0:
        raise ValueError(f"nhc_rate_hz must be > 0, got {nhc_rate}")
    cov_step = float(opts.pop("cov_step_s", 0.1))
    if not cov_step > 0:
        raise ValueError(f"cov_step_s must be > 0 [s], got {cov_step}")
    if "att_std0" in opts:
        att = np.broadcast_to(np.asarray(opts["att_std0"], dtype=float), (3,))
        opts["att_std0"] = tuple(float(a) for a in att)
    return EskfOptions(
        mech=Mechanization(earth_rotation=earth, transport_rate=earth),
        nhc_every=max(1, round(1.0 / (nhc_rate * dt))),
        cov_every=max(1, int(cov_step / dt + 1e-9)),
        **opts,
    )


def build_filter(t0: float, dt: float, rot_nb0: Rotation | None = None, **options: Any) -> ESKF:
    """The :class:`~polins.fusion.eskf.ESKF` that :func:`fuse` runs, for streaming use.

    Feeding this filter the IMU samples one by one (``propagate``) with the measurement
    rows queued (``add_measurement``) reproduces ``fuse`` with the same options (to 1e-9
    rad; ``state().row()`` is a row of the solution table).

    Parameters
    ----------
    t0 : float
        Time of the first IMU sample [s].
    dt : float
        IMU sample interval [s] (sets the non-holonomic and covariance-step cadence).
    rot_nb0 : Rotation, optional
        Initial attitude; None for self-alignment.
    **options
        ``imu_model``, ``lat_deg``, ``lon_deg``, ``alt_m``, ``vel_n0`` and the filter options
        (:data:`FILTER_OPTIONS`) of :func:`fuse`.
    """
    site = {"imu_model", "lat_deg", "lon_deg", "alt_m", "vel_n0"}
    unknown = sorted(set(options) - site - set(FILTER_OPTIONS))
    if unknown:
        raise TypeError(f"unknown filter option(s) {unknown}")
    model = _resolve_model(options.get("imu_model", "mems-typical"))
    default_site = "lat_deg" not in options
    lat_deg = float(options.get("lat_deg", DEFAULT_SITE[0]))
    lon_deg = float(options.get("lon_deg", DEFAULT_SITE[1] if default_site else 0.0))
    alt_m = float(options.get("alt_m", DEFAULT_SITE[2] if default_site else 0.0))
    if not -90.0 <= lat_deg <= 90.0:
        raise ValueError(f"lat_deg={lat_deg} outside [-90, 90] (degrees expected)")
    filter_opts = {k: v for k, v in options.items() if k in FILTER_OPTIONS}
    return ESKF(
        model,
        float(t0),
        np.radians(lat_deg),
        np.radians(lon_deg),
        alt_m,
        rot_nb0=rot_nb0,
        vel_n0=options.get("vel_n0", (0.0, 0.0, 0.0)),
        options=eskf_options(model, dt, **filter_opts),
    )


def fuse(
    imu: pd.DataFrame,
    measurements: pd.DataFrame | None = None,
    backend: str = "eskf",
    rot_nb0: Rotation | None = None,
    **options: Any,
) -> pd.DataFrame:
    """Fuse an IMU log with polarization yaw / sun-vector measurements.

    Parameters
    ----------
    imu : DataFrame
        Columns ``t`` [s], ``gx, gy, gz`` [rad/s], ``ax, ay, az`` [m/s^2]: body (FLU)
        angular rate and specific force, instantaneous at ``t`` (validated by
        :func:`polins.fusion.inputs.validate_imu`).
    measurements : DataFrame, optional
        Columns ``t`` and ``yaw, yaw_std`` [rad] and/or ``sun_bx, sun_by, sun_bz``
        (measured, body), ``sun_nx, sun_ny, sun_nz`` (reference, ENU), ``sun_std`` [rad];
        optionally ``zupt_std`` [m/s]. NaN values are skipped (logged). None: no aiding.
    backend : {"eskf", "graph"}
        Error-state Kalman filter (:mod:`polins.fusion.eskf`) or the GTSAM factor graph
        (``polins.fusion.graph``, needs ``gtsam``).
    rot_nb0 : Rotation, optional
        Initial attitude (body FLU -> ENU) at the first IMU sample. None: self-alignment
        (roll/pitch from the accelerometer averaged over ``align_s`` at rest, yaw from the
        first valid measurement).
    **options
        See ``polins.fusion._FUSE_OPTIONS`` (an unknown name raises ``TypeError`` listing
        them). The main ones: ``imu_model`` (default ``"mems-typical"``), ``lat_deg``,
        ``lon_deg``, ``alt_m``, ``nhc_std``, ``output_rate_hz``, ``smooth``,
        ``scale_factors``. The graph backend takes its own options (``fuse_graph``).

    Returns
    -------
    DataFrame
        One row per reported IMU sample. Columns ``t, roll, pitch, yaw, heading_deg,
        roll_std, pitch_std, yaw_std, bgx, bgy, bgz, bax, bay, baz`` (CONVENTIONS.md), then
        the bias sigmas, ``ve, vn, vu`` and sigmas, ``lat_deg, lon_deg, height_m`` and
        position sigmas ``pe_std, pn_std, pu_std`` [m], the quaternion ``qw, qx, qy, qz`` and,
        with ``scale_factors``, ``sgx .. saz`` and sigmas. Angles in radians, yaw NaN before
        the yaw alignment. ``attrs["updates"]``: one row per measurement with ``t, name,
        dim, nis, accepted, reason``; with ``smooth=True`` the table is the smoothed
        solution and ``attrs["filtered"]`` the filtered one.
    """
    if backend == "graph":
        from polins.fusion import graph

        graph_opts = dict(options)
        graph_opts["imu_model"] = _resolve_model(graph_opts.get("imu_model", "mems-typical"))
        if "lat_deg" not in graph_opts:
            warnings.warn(
                f"fuse: no lat_deg/lon_deg/alt_m given; using the paper's site {DEFAULT_SITE}",
                UserWarning,
                stacklevel=2,
            )
            graph_opts["lat_deg"], graph_opts["lon_deg"], graph_opts["alt_m"] = DEFAULT_SITE
        meas = validate_measurements(measurements)
        graph_opts.setdefault("tilt_coupling", _has_priors(meas))
        return graph.fuse_graph(imu, meas, rot_nb0, **graph_opts)
    if backend != "eskf":
        raise ValueError(f"backend={backend!r}: expected 'eskf' or 'graph'")
    unknown = sorted(set(options) - set(_FUSE_OPTIONS))
    if unknown:
        valid = "\n".join(f"  {k}: {v}" for k, v in _FUSE_OPTIONS.items())
        raise TypeError(f"unknown fuse option(s) {unknown}; valid options:\n{valid}")
    arrays = validate_imu(imu, max_gap_s=options.get("max_gap_s"))
    meas = validate_measurements(measurements)
    if "lat_deg" not in options:
        warnings.warn(
            "fuse: no lat_deg/lon_deg/alt_m given; using the paper's site (Harbin, "
            f"{DEFAULT_SITE}) for gravity and Earth rate",
            UserWarning,
            stacklevel=2,
        )
    filt_opts = {k: v for k, v in options.items() if k not in _OUTPUT_OPTIONS}
    filt_opts.setdefault("tilt_coupling", _has_priors(meas))
    filt = build_filter(float(arrays.t[0]), arrays.dt, rot_nb0, **filt_opts)
    model = filt.model
    items = items_from_table(meas, use_sun=filt.options.use_sun)
    zupt_std = options.get("zupt_std")
    stationary = options.get("stationary")
    if stationary is not None:
        if zupt_std is None:
            raise ValueError("stationary times need zupt_std [m/s]")
        items += [
            MeasurementItem(float(ts), "zupt", float(zupt_std)) for ts in np.ravel(stationary)
        ]
    mask = output_mask(arrays.t, options.get("output_rate_hz"))
    smooth = bool(options.get("smooth", False))
    if options.get("fast", True):
        result = run_batch(
            filt, arrays.t, arrays.gyro_b, arrays.accel_b, items, output_mask=mask, smooth=smooth
        )
        sol = pd.DataFrame(result.columns())
        if smooth and result.smoothed is not None:
            filtered = sol
            sol = pd.DataFrame(result.smoothed.columns())
            sol.attrs["filtered"] = filtered
    else:
        if smooth:
            raise ValueError("smooth=True needs the batch path (fast=True)")
        sol = _fuse_streaming(filt, arrays.t, arrays.gyro_b, arrays.accel_b, items, mask)
    sol.attrs["updates"] = records_table(filt.records)
    sol.attrs["backend"] = "eskf"
    sol.attrs["imu_model"] = model.name
    return sol


def _fuse_streaming(
    filt: ESKF,
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    items: list[MeasurementItem],
    mask: np.ndarray,
) -> pd.DataFrame:
    """The straightforward per-sample filter: one ``propagate`` per IMU sample."""
    states: list[FilterState] = []

    def collect(f: ESKF, k: int) -> None:
        if mask[k]:
            states.append(f.state())

    filt.sample_hook = collect
    filt.add_items(items)
    for k in range(len(t)):
        filt.propagate(t[k], gyro[k], accel[k])
    filt.sample_hook = None
    from polins.fusion.eskf import _state_arrays

    return pd.DataFrame(solution_columns(**_state_arrays(states)))


def _has_priors(measurements: pd.DataFrame) -> bool:
    """The table carries the priors ``polins.measure`` used (``polins fuse`` writes them)."""
    return all(c in measurements.columns for c in PRIOR_COLUMNS)


__all__ = [
    "ESKF",
    "FILTER_OPTIONS",
    "EskfOptions",
    "build_filter",
    "check_filter_options",
    "eskf_options",
    "fuse",
    "output_mask",
    "records_table",
]
