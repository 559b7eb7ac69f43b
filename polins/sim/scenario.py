"""Scenario runner: a simulated, synchronized log (IMU, raw sky images, truth) on disk.

A scenario is a trajectory (``polins.sim.trajectory``), the IMU it would produce
(``polins.sim.imu``: ideal physics plus the error model of ``models/imus``), and the raw
DoFP images a zenith-looking polarization camera would record along it
(``polins.sim.render_raw``) under the sun of the log's UTC epoch and site
(``polins.sun_position``, NREL SPA, evaluated at every image time). The result is written
with ``polins.io.log.write_log`` in the format ``polins.io.read_log`` and ``polins fuse``
read back.

The ``"ugv"`` scenario's IMU is mounted on the vehicle with a small mounting rotation and a
lever arm, feels the road's vibration while rolling, and the log carries a wheel-odometer
stream; the manifest's ``[vehicle]`` table says so (:mod:`polins.sim.vehicle`).

Synchronization: every image is taken at an IMU sample time (the one nearest to
``k / image_rate_hz``), so the truth is exact at every image and every stream shares one
clock ``t`` [s] counted from ``epoch_utc``. Randomness comes from one seed split into
independent streams (trajectory, IMU errors, image noise), so e.g. changing the image rate
leaves the drive and the IMU noise unchanged.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from polins.io.log import write_log
from polins.models import CameraModel, ImuModel, load_camera, load_imu
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.realsky import RealSky, random_real_sky, render_real_raw
from polins.sim.render import render_raw
from polins.sim.reproduction import PAPER_EPOCH
from polins.sim.trajectory import Trajectory, turntable, ugv_drive
from polins.sim.vehicle import (
    UGV_LEVER_ARM_B,
    UGV_MOUNT_RPY_DEG,
    UGV_ODOMETER,
    forward_speed,
    mounted_trajectory,
    odometer_speeds,
    road_vibration,
)
from polins.site import PAPER_SITE, to_utc_index
from polins.sky.ephemeris import sun_position, sun_vector_n

FloatArray = NDArray[np.float64]

SCENARIOS = ("turntable", "ugv", "static")
SKIES = ("model", "realistic")
# static: two hours, ten crossover times of a mid-range MEMS gyro's white noise and bias
# random walk (polins.tuning.record_length_needed), at one image a minute
DEFAULT_DURATION_S = {"turntable": 100.0, "ugv": 300.0, "static": 7200.0}
DEFAULT_IMAGE_RATE_HZ = {"turntable": 5.0, "ugv": 5.0, "static": 1.0 / 60.0}
DEFAULT_EPOCH = PAPER_EPOCH  # the paper's Sec. 4.1 simulation (Harbin)
TURNTABLE_RATE = np.radians(7.2)  # [rad/s]: the paper's 720 deg in 100 s


@dataclass(frozen=True, eq=False)
class SimulatedLog:
    """What :func:`simulate_log` wrote, plus the in-memory truth for direct use.

    Attributes
    ----------
    manifest : Path
        ``manifest.toml`` of the log (``polins.io.read_log(manifest)`` loads it).
    scenario : str
    trajectory : Trajectory
        True motion at the IMU rate.
    imu : DataFrame
        The measured IMU as written (``t, gx, gy, gz, ax, ay, az``, SI).
    imu_errors : DataFrame
        True sensor errors per IMU sample (``polins.sim.imu.imu_errors``).
    image_t : ndarray, (M,)
        Image times [s] (IMU sample times).
    sun_n : ndarray, (M, 3)
        ENU sun vector at each image (at the log's site).
    camera : CameraModel
        The (downscaled) camera the images were rendered with.
    imu_model : ImuModel
    epoch_utc : Timestamp
    vehicle : dict or None
        ``"ugv"``: the manifest's ``[vehicle]`` table (kind, mounting, lever arm, odometer).
    odometry : DataFrame or None
        ``"ugv"``: the odometer stream written (``t, speed``, :mod:`polins.sim.vehicle`).
    vehicle_trajectory : Trajectory or None
        ``"ugv"``: the vehicle's motion (``trajectory`` is the IMU's, mounted on it).
    real_sky : RealSky or None
        ``sky="realistic"``: the sky and camera imperfections every image was rendered with.
    """

    manifest: Path
    scenario: str
    trajectory: Trajectory
    imu: pd.DataFrame
    imu_errors: pd.DataFrame
    image_t: FloatArray
    sun_n: FloatArray
    camera: CameraModel
    imu_model: ImuModel
    epoch_utc: pd.Timestamp
    render_options: dict[str, Any] = field(default_factory=dict)
    vehicle: dict[str, Any] | None = None  # the manifest's [vehicle] table (ugv)
    odometry: pd.DataFrame | None = None  # t, speed of the odometer (ugv)
    vehicle_trajectory: Trajectory | None = None  # the vehicle's reference point (ugv)
    real_sky: RealSky | None = None  # sky="realistic"

    @property
    def truth(self) -> pd.DataFrame:
        """Truth table as written: ``truth_frame()`` plus the IMU error states."""
        return truth_table(self.trajectory, self.imu_errors)


def scenario_trajectory(
    scenario: str,
    *,
    duration_s: float | None = None,
    rate_hz: float = 200.0,
    rng: np.random.Generator,
    lat_deg: float = PAPER_SITE.lat_deg,
    lon_deg: float = PAPER_SITE.lon_deg,
    alt_m: float = PAPER_SITE.alt_m,
) -> Trajectory:
    """The trajectory of a named scenario.

    ``"turntable"``: the paper's turntable, level, 7.2 deg/s about the vertical (720 deg in
    the default 100 s). ``"ugv"``: :func:`polins.sim.trajectory.ugv_drive` (default 300 s)
    with an initial yaw drawn from ``rng``. ``"static"``: the IMU at rest, level, at a yaw
    drawn from ``rng`` (default 7200 s): a record for ``polins imu-model``
    (docs/imu-model.md).
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}: expected one of {', '.join(SCENARIOS)}")
    duration = DEFAULT_DURATION_S[scenario] if duration_s is None else float(duration_s)
    site = {"lat_deg": lat_deg, "lon_deg": lon_deg, "alt_m": alt_m}
    if scenario == "turntable":
        return turntable(
            duration_s=duration, turn_rad=TURNTABLE_RATE * duration, rate_hz=rate_hz, **site
        )
    if scenario == "static":
        yaw = float(rng.uniform(-np.pi, np.pi))
        return turntable(duration_s=duration, turn_rad=0.0, rate_hz=rate_hz, yaw0=yaw, **site)
    yaw0 = float(rng.uniform(-np.pi, np.pi))
    return ugv_drive(duration_s=duration, rate_hz=rate_hz, rng=rng, yaw0=yaw0, **site)


def image_indices(t: FloatArray, image_rate_hz: float) -> NDArray[np.int_]:
    """Indices of the samples ``t`` nearest to ``k / image_rate_hz`` (unique, in order)."""
    if not np.isfinite(image_rate_hz) or image_rate_hz <= 0:
        raise ValueError(f"image_rate_hz must be a positive rate [Hz], got {image_rate_hz}")
    rate_hz = (len(t) - 1) / (t[-1] - t[0])
    if image_rate_hz > rate_hz:
        raise ValueError(
            f"image_rate_hz={image_rate_hz} is above the IMU rate {rate_hz:g} Hz: images are "
            "taken at IMU sample times"
        )
    wanted = np.arange(t[0], t[-1] + 0.5 / rate_hz, 1.0 / image_rate_hz)
    idx = np.clip(np.rint((wanted - t[0]) * rate_hz).astype(int), 0, len(t) - 1)
    return np.unique(idx)


def truth_table(traj: Trajectory, errors: pd.DataFrame | None = None) -> pd.DataFrame:
    """``traj.truth_frame()`` with the IMU error states (``bgx .. saz``) appended."""
    truth = traj.truth_frame()
    if errors is None:
        return truth
    if len(errors) != len(truth) or not np.allclose(errors["t"], truth["t"], atol=1e-9):
        raise ValueError("the IMU error table does not share the trajectory's sample times")
    return pd.concat([truth, errors.drop(columns="t").reset_index(drop=True)], axis=1)


def simulate_log(
    out: str | Path,
    *,
    scenario: str = "turntable",
    duration_s: float | None = None,
    image_rate_hz: float | None = None,
    downscale: int = 8,
    imu: str | Path | ImuModel = "fins-paper",
    camera: str | Path | CameraModel = "paper-table1",
    seed: int = 0,
    epoch_utc: Any = DEFAULT_EPOCH,
    lat_deg: float = PAPER_SITE.lat_deg,
    lon_deg: float = PAPER_SITE.lon_deg,
    alt_m: float = PAPER_SITE.alt_m,
    imu_rate_hz: float | None = None,
    render_options: Mapping[str, Any] | None = None,
    sky: str = "model",
    imu_format: str = "csv",
    progress: bool = True,
) -> SimulatedLog:
    """Simulate a scenario and write it as a log folder.

    Parameters
    ----------
    out : str or Path
        Output folder (created; an existing log there is replaced).
    scenario : {"turntable", "ugv", "static"}
        See :func:`scenario_trajectory`.
    duration_s : float, optional
        Length [s]; default ``DEFAULT_DURATION_S`` (turntable 100 s, ugv 300 s, static 7200 s).
    image_rate_hz : float, optional
        Camera rate [Hz] (e.g. 5-22); images are taken at the nearest IMU sample times.
        Default ``DEFAULT_IMAGE_RATE_HZ``: 5 Hz, for the static record one image a minute.
    downscale : int
        Render the camera at ``1/downscale`` resolution (``CameraModel.downscaled``), for
        small, quick logs; 1 = full resolution (2048 x 2448, ~6 MB per PNG). The default
        (8, 256 x 306, as ``polins simulate``) takes a few ms and ~0.07 MB per image; 4
        (512 x 612) ~25 ms and ~0.25 MB.
    imu : str, Path or ImuModel
        IMU error model: shipped name (``fins-paper``, ``mems-typical``), TOML path or model.
    camera : str, Path or CameraModel
        Camera model (default the paper's Table 1 camera).
    seed : int
        Seed of every random draw (drive, IMU errors, image noise).
    epoch_utc : str, datetime or Timestamp
        Timezone-aware time of ``t = 0`` (default the paper's 2023-09-05 15:06 +08:00).
    lat_deg, lon_deg, alt_m : float
        Site and start position (default the paper's, :data:`polins.site.PAPER_SITE`).
    imu_rate_hz : float, optional
        IMU rate [Hz]; default the model's ``sample_rate_hz``.
    render_options : mapping, optional
        Keyword arguments for ``polins.sim.render_raw`` (``dop_max``, ``radiance``,
        ``epsilon``, ``noise_std``, ``sky``, ``clouds``, ``occluders``, ...); only with
        ``sky="model"``.
    sky : {"model", "realistic"}
        ``"model"``: the estimator's own sky (``polins.sim.render_raw``) and a camera file
        whose calibration is exact (``instrumental_dop_std = 0``). ``"realistic"``: one
        random realistic sky for the whole log (``polins.sim.random_real_sky``: CIE
        radiance, Berry neutral points, two thin clouds fixed in the sky, vignetting, a
        channel-gain residual of the camera that its file does not know), rendered by the
        independent ``polins.sim.render_real_raw``; the log's camera file keeps its
        ``instrumental_dop_std`` (docs/measurement.md §12).
    imu_format : {"csv", "parquet"}
    progress : bool
        Show a tqdm progress bar while rendering images.

    Returns
    -------
    SimulatedLog
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}: expected one of {', '.join(SCENARIOS)}")
    if image_rate_hz is None:
        image_rate_hz = DEFAULT_IMAGE_RATE_HZ[scenario]
    if isinstance(downscale, bool) or not isinstance(downscale, int | np.integer):
        raise ValueError(f"downscale must be a positive integer, got {downscale!r}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    if Path(out).exists() and not Path(out).is_dir():
        raise ValueError(f"output {out} exists and is not a folder")
    epoch = to_utc_index(epoch_utc)[0]
    imu_model = imu if isinstance(imu, ImuModel) else load_imu(imu)
    cam_full = camera if isinstance(camera, CameraModel) else load_camera(camera)
    try:
        cam = cam_full if downscale == 1 else cam_full.downscaled(int(downscale))
    except ValueError as exc:
        raise ValueError(f"downscale={downscale}: {exc}") from None
    if sky not in SKIES:
        raise ValueError(f"sky={sky!r}: expected one of {SKIES}")
    if sky == "model":
        # the images are rendered with the camera file's own calibration: it is exact, and
        # the log's camera file says so (its sigma then has no camera-fixed part,
        # docs/measurement.md)
        cam = dataclasses.replace(cam, instrumental_dop_std=0.0)
    rate_hz = imu_model.sample_rate_hz if imu_rate_hz is None else float(imu_rate_hz)
    options = dict(render_options or {})
    if "rng" in options:
        raise ValueError("render_options must not contain 'rng': the seed drives the noise")
    if options and sky != "model":
        raise ValueError(f"render_options apply to sky='model' only, not sky={sky!r}")

    rng_traj, rng_imu, rng_img, rng_vib, rng_odo, rng_sky = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(6)
    )
    traj = scenario_trajectory(
        scenario,
        duration_s=duration_s,
        rate_hz=rate_hz,
        rng=rng_traj,
        lat_deg=lat_deg,
        lon_deg=lon_deg,
        alt_m=alt_m,
    )
    vehicle_traj, vehicle, odometry = None, None, None
    ideal = None
    if scenario == "ugv":  # the IMU mounted off the vehicle's axes, road vibration, odometer
        vehicle_traj = traj
        traj = mounted_trajectory(traj, np.radians(UGV_MOUNT_RPY_DEG), UGV_LEVER_ARM_B)
        ideal = ideal_imu(traj)
        gyro_vib, accel_vib = road_vibration(traj.t, forward_speed(vehicle_traj), rng_vib)
        ideal[["gx", "gy", "gz"]] += gyro_vib
        ideal[["ax", "ay", "az"]] += accel_vib
        odometry = odometer_speeds(vehicle_traj, rng_odo, **UGV_ODOMETER)
        vehicle = {"kind": "ground", "mount_rpy_deg": list(UGV_MOUNT_RPY_DEG),
                   "lever_arm_b": list(UGV_LEVER_ARM_B), "odometer": "odometer.csv",
                   "odometer_std": UGV_ODOMETER["noise_std"]}  # fmt: skip
    measured, errors = imu_errors(ideal_imu(traj) if ideal is None else ideal, imu_model, rng_imu)
    idx = image_indices(traj.t, image_rate_hz)
    image_t = traj.t[idx]
    times = pd.DatetimeIndex(epoch + pd.to_timedelta(image_t, unit="s"))
    sun = sun_position(times, lat_deg, lon_deg, alt_m)
    sun_n = sun_vector_n(sun.azimuth, sun.zenith)
    rot_nb = traj.rot_nb
    real_sky = random_real_sky(rng_sky, sun_n[0]) if sky == "realistic" else None

    def images() -> Iterator[tuple[float, NDArray]]:
        bar = tqdm(
            idx, desc=f"rendering {cam.shape[1]}x{cam.shape[0]} images", disable=not progress
        )
        for j, k in enumerate(bar):
            if real_sky is None:
                raw = render_raw(cam, sun_n[j], rot_nb[int(k)], rng=rng_img, **options)
            else:
                raw = render_real_raw(cam, sun_n[j], rot_nb[int(k)], real_sky, rng_img)
            yield float(traj.t[k]), raw

    # Shipped models are named in the manifest; objects and paths are copied into the log.
    manifest = write_log(
        out,
        epoch_utc=epoch,
        camera=cam,
        imu_model=imu,
        lat_deg=lat_deg,
        lon_deg=lon_deg,
        alt_m=alt_m,
        imu=measured,
        images=images(),
        truth=truth_table(traj, errors),
        imu_format=imu_format,
        vehicle=vehicle,
        odometry=odometry,
        description=(
            f"polins simulate: scenario={scenario} duration_s={traj.t[-1]:g} "
            f"image_rate_hz={image_rate_hz:g} downscale={downscale} imu={imu_model.name} "
            f"sky={sky} seed={seed}"
        ),
    )
    return SimulatedLog(
        manifest=Path(manifest),
        scenario=scenario,
        trajectory=traj,
        imu=measured,
        imu_errors=errors,
        image_t=image_t,
        sun_n=sun_n,
        camera=cam,
        imu_model=imu_model,
        epoch_utc=epoch,
        render_options=options,
        real_sky=real_sky,
        vehicle=vehicle,
        odometry=odometry,
        vehicle_trajectory=vehicle_traj,
    )


def rot_nb_at(traj: Trajectory, t: FloatArray) -> Rotation:
    """True attitude at sample times ``t`` [s] of the trajectory (exact sample lookup)."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    idx = np.rint((t - traj.t[0]) * traj.rate_hz).astype(int)
    if np.any(idx < 0) or np.any(idx >= len(traj)) or not np.allclose(traj.t[idx], t, atol=1e-9):
        raise ValueError("times are not sample times of the trajectory")
    return traj.rot_nb[idx]


__all__ = [
    "DEFAULT_DURATION_S",
    "DEFAULT_EPOCH",
    "DEFAULT_IMAGE_RATE_HZ",
    "SCENARIOS",
    "SimulatedLog",
    "image_indices",
    "rot_nb_at",
    "scenario_trajectory",
    "simulate_log",
    "truth_table",
]
