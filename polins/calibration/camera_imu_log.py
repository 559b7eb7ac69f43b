"""Camera-IMU calibration from a polins log: sun vectors from its images, attitude from its gyro or truth.

:func:`camera_imu_from_log` feeds :func:`polins.calibration.camera_imu.calibrate_camera_imu`
from a log folder (``polins.io.read_log``; docs/calibrate.md#camera-imu):

* every image gives the sun in the camera frame, measured with the base camera and no
  ephemeris (``polins.measure`` without ``sun_n``: ``Measurement.sun_b`` turned back
  through the base camera's ``mat_bc``);
* the attitude is either the log's reference trajectory (``truth.csv``, body to ENU: the
  clock mode, with the ephemeris sun at the log's site and times) or the gyro integrated
  from the first sample (:func:`gyro_attitude`: the no-clock mode, which needs no absolute
  attitude and no clock).

The gyro is integrated without removing the Earth rate, so its reference frame does not
turn with the Earth: the sun, fixed among the stars to about 1 deg a day, stays put in it,
and only a vertical gyro bias makes it drift (the no-clock fit's drift term absorbs it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.calibration.camera_imu import CameraImuResult, calibrate_camera_imu
from polins.compass.measure import measure
from polins.errors import UserInputError
from polins.ins.alignment import level_from_accel
from polins.ins.strapdown import rotation_vectors
from polins.io.images import load_raw
from polins.io.log import Log
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

ATTITUDES = ("auto", "truth", "gyro")

__all__ = [
    "ATTITUDES",
    "LogSunVectors",
    "camera_imu_from_log",
    "cumulative_rotation",
    "gyro_attitude",
    "log_sun_vectors",
]


def cumulative_rotation(steps: Rotation) -> Rotation:
    """Running products ``steps[0] * steps[1] * ... * steps[k]`` for every k (a
    Hillis-Steele scan: log2(n) vectorised compositions instead of a loop over samples)."""
    out = steps
    shift = 1
    while shift < len(out):
        out = Rotation.concatenate([out[:shift], out[:-shift] * out[shift:]])
        shift *= 2
    return out


def gyro_attitude(
    t: ArrayLike, gyro_b: ArrayLike, accel_b: ArrayLike | None = None, *, level_s: float = 1.0
) -> Rotation:
    """Body-to-reference attitudes ``(n,)`` integrated from gyro samples.

    The reference frame is the body at ``t[0]``, levelled with the mean specific force of
    the first ``level_s`` seconds when ``accel_b`` is given (yaw 0; ``z`` up). The Earth
    rate is not removed: the frame is fixed among the stars (module docstring).

    Parameters
    ----------
    t : array_like, (n,)
        Sample times [s], increasing.
    gyro_b : array_like, (n, 3)
        Body rates [rad/s], instantaneous at ``t`` (coning-corrected increments between
        samples, ``polins.ins.strapdown.rotation_vectors``).
    accel_b : array_like, (n, 3), optional
        Specific force [m/s^2], for the levelling.
    level_s : float
        Levelling window [s].
    """
    tt = np.asarray(t, dtype=float)
    w = np.asarray(gyro_b, dtype=float)
    if w.shape != (tt.size, 3) or tt.size < 2 or not np.all(np.diff(tt) > 0):
        raise UserInputError(
            f"gyro_attitude: {tt.size} increasing times need gyro_b of shape ({tt.size}, 3), "
            f"got {w.shape}"
        )
    phi, _ = rotation_vectors(w[:-1], w[1:], np.diff(tt))
    start = Rotation.identity()
    if accel_b is not None:
        f = np.asarray(accel_b, dtype=float)
        roll, pitch = level_from_accel(f[tt <= tt[0] + level_s].mean(axis=0))
        start = Rotation.from_euler("ZYX", [0.0, pitch, roll])
    steps = Rotation.concatenate([start, Rotation.from_rotvec(phi)])
    return cumulative_rotation(steps)


@dataclass(frozen=True)
class LogSunVectors:
    """Sun vectors measured in a log's images.

    Attributes
    ----------
    t : (m,)
        Image times on the camera clock [s] (images whose measurement failed left out).
    sun_c : (m, 3)
        Unit sun vectors in the camera frame.
    n_images : int
        Images read (measured or not).
    """

    t: FloatArray
    sun_c: FloatArray
    n_images: int


def log_sun_vectors(
    log: Log, cam: CameraModel, t_att: FloatArray, rot_prior: Rotation, **options: Any
) -> LogSunVectors:
    """The sun in the camera frame in every image of ``log``, measured with ``cam`` and no
    ephemeris; ``rot_prior`` (at ``t_att``) gives each image's tilt prior, the previous
    image's body-frame azimuth chooses the 180 deg branch."""
    times, vectors = [], []
    n = 0
    prior_az = None
    for t, item in log.images:
        n += 1
        k = int(np.clip(np.searchsorted(t_att, t), 0, t_att.size - 1))
        m = measure(load_raw(item, shape=cam.shape), cam, rot_nb_prior=rot_prior[k],
                    sun_azimuth_b_prior=prior_az, **options)  # fmt: skip
        if not m.ok or not np.all(np.isfinite(m.sun_b)):
            continue
        prior_az = m.sun_azimuth_b
        times.append(float(t))
        vectors.append(cam.mat_bc.T @ np.asarray(m.sun_b, dtype=float))
    return LogSunVectors(np.asarray(times), np.asarray(vectors).reshape(-1, 3), n)


def camera_imu_from_log(
    log: Log,
    cam: CameraModel,
    *,
    attitude: str = "auto",
    clock: bool | None = None,
    max_offset_s: float = 0.2,
    **options: Any,
) -> tuple[CameraImuResult, str]:
    """Camera time offset and ``mat_bc`` from a log with turns (module docstring).

    Parameters
    ----------
    log : polins.io.log.Log
    cam : CameraModel
        Base camera (channels, intrinsics; its ``mat_bc`` is the start value and the one
        the measured body vectors are turned back through). Its size must be the images'.
    attitude : {"auto", "truth", "gyro"}
        The log's reference trajectory (absolute: body to ENU), or the integrated gyro
        (relative). ``"auto"``: the truth when the log has one, else the gyro.
    clock : bool, optional
        Use the ephemeris (the log's epoch and site). Default: with an absolute (truth)
        attitude. The gyro's attitude is relative, so it always runs without the clock.
    max_offset_s : float
        Largest time offset searched [s].
    **options
        ``polins.measure`` options.

    Returns
    -------
    result : CameraImuResult
    how : str
        One line: the mode and the attitude used, and why.
    """
    if attitude not in ATTITUDES:
        raise UserInputError(f"attitude={attitude!r}: expected one of {', '.join(ATTITUDES)}")
    has_truth = log.truth is not None and {"qw", "qx", "qy", "qz"} <= set(log.truth.columns)
    if attitude == "truth" and not has_truth:
        raise UserInputError(f"{log.manifest_path}: the log has no truth table with qw..qz")
    use_truth = attitude == "truth" or (attitude == "auto" and has_truth and clock is not False)
    if clock and not use_truth:
        raise UserInputError(
            "camera-imu: the clock mode needs an absolute attitude (the log's truth table); "
            "the gyro's attitude is relative: run without the clock"
        )
    use_clock = use_truth if clock is None else bool(clock)
    imu = log.imu
    if use_truth:
        assert log.truth is not None
        t_att = log.truth["t"].to_numpy(dtype=float)
        rot = Rotation.from_quat(log.truth[["qx", "qy", "qz", "qw"]].to_numpy(dtype=float))
        source = "the log's truth table (body to ENU)"
    else:
        t_att = imu["t"].to_numpy(dtype=float)
        rot = gyro_attitude(
            t_att, imu[["gx", "gy", "gz"]].to_numpy(float), imu[["ax", "ay", "az"]].to_numpy(float)
        )
        source = "the integrated gyro (relative)"
    suns = log_sun_vectors(log, cam, t_att, rot, **options)
    sun_n = log.sun_n(t_att) if use_clock else None
    result = calibrate_camera_imu(suns.t, suns.sun_c, t_att, rot, sun_n,
                                  max_offset_s=max_offset_s, mat_bc_start=cam.mat_bc)  # fmt: skip
    mode = "clock (ephemeris sun at the log's epoch and site)" if use_clock else "no clock"
    how = (
        f"mode: {mode}; attitude: {source}; {suns.t.size} of {suns.n_images} images gave "
        "a sun vector"
    )
    return result, how
