"""Analytic vehicle trajectories: the paper's turntable and a random UGV drive.

Every trajectory is a closed-form function of time, so the body rate relative to the
navigation frame ``omega_nb_b`` and the acceleration ``accel_n = d(vel_n)/dt`` are exact
(no numerical differentiation). Manoeuvres blend with the septic smooth-step
``S(x) = 35 x^4 - 84 x^5 + 70 x^6 - 20 x^7`` (``S' = S'' = S''' = 0`` at both ends), so
attitude rates and accelerations are continuous and so are their first derivatives.

Frames and angles follow docs/conventions.md: ``rot_nb`` maps body FLU to local ENU,
``rot_nb = Rotation.from_euler("ZYX", [yaw, pitch, roll])``, positive pitch is nose down,
positive roll is right side down. The geodetic position integrates the ENU velocity
through the WGS-84 radii of curvature (``polins.ins.earth``):
``lat' = v_N / (R_M + h)``, ``lon' = v_E / ((R_N + h) cos lat)``, ``h' = v_U``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.integrate import cumulative_simpson
from scipy.spatial.transform import Rotation

from polins.frames import heading_deg_from_yaw, wrap_angle
from polins.ins.earth import radii_of_curvature
from polins.site import PAPER_SITE

FloatArray = NDArray[np.float64]


# ----------------------------------------------------------------------------- container
@dataclass(frozen=True, eq=False)
class Trajectory:
    """True motion of the body sampled uniformly in time.

    Attributes
    ----------
    t : ndarray, (N,)
        Sample times [s], uniform at ``rate_hz``, starting at 0.
    rot_nb : Rotation, (N,)
        Body (FLU) to local ENU attitude.
    vel_n : ndarray, (N, 3)
        Velocity relative to the Earth in ENU [m/s].
    lat, lon : ndarray, (N,)
        Geodetic latitude and longitude [rad].
    alt_m : ndarray, (N,)
        Height above the WGS-84 ellipsoid [m].
    omega_nb_b : ndarray, (N, 3)
        Angular rate of the body relative to the local ENU frame, in body axes [rad/s]
        (exact, from the analytic Euler-angle rates).
    accel_n : ndarray, (N, 3)
        ``d(vel_n)/dt`` in ENU [m/s^2] (exact, analytic).
    """

    t: FloatArray
    rot_nb: Rotation
    vel_n: FloatArray
    lat: FloatArray
    lon: FloatArray
    alt_m: FloatArray
    omega_nb_b: FloatArray
    accel_n: FloatArray

    def __post_init__(self) -> None:
        n = len(self.t)
        if n < 2:
            raise ValueError(f"a Trajectory needs at least 2 samples, got {n}")
        expected = {
            "rot_nb": (len(self.rot_nb),),
            "vel_n": self.vel_n.shape,
            "lat": self.lat.shape,
            "lon": self.lon.shape,
            "alt_m": self.alt_m.shape,
            "omega_nb_b": self.omega_nb_b.shape,
            "accel_n": self.accel_n.shape,
        }
        wanted = {
            "rot_nb": (n,),
            "vel_n": (n, 3),
            "lat": (n,),
            "lon": (n,),
            "alt_m": (n,),
            "omega_nb_b": (n, 3),
            "accel_n": (n, 3),
        }
        for name, shape in expected.items():
            if shape != wanted[name]:
                raise ValueError(f"Trajectory.{name} has shape {shape}, expected {wanted[name]}")

    def __len__(self) -> int:
        return len(self.t)

    @property
    def rate_hz(self) -> float:
        """Sample rate [Hz]."""
        return float((len(self.t) - 1) / (self.t[-1] - self.t[0]))

    def truth_frame(self) -> pd.DataFrame:
        """The truth as a table (the ``truth.csv`` of a log).

        Returns
        -------
        DataFrame
            Columns ``t`` [s]; ``roll, pitch, yaw`` [rad] (ZYX Euler, yaw wrapped to
            (-pi, pi]); ``heading_deg``; the quaternion ``qw, qx, qy, qz`` of ``rot_nb``;
            ``ve, vn, vu`` [m/s]; ``lat_deg, lon_deg, alt_m``.
        """
        ypr = self.rot_nb.as_euler("ZYX")
        yaw = wrap_angle(ypr[:, 0])
        quat = self.rot_nb.as_quat()  # scipy order x, y, z, w
        return pd.DataFrame(
            {
                "t": self.t,
                "roll": ypr[:, 2],
                "pitch": ypr[:, 1],
                "yaw": yaw,
                "heading_deg": heading_deg_from_yaw(yaw),
                "qw": quat[:, 3],
                "qx": quat[:, 0],
                "qy": quat[:, 1],
                "qz": quat[:, 2],
                "ve": self.vel_n[:, 0],
                "vn": self.vel_n[:, 1],
                "vu": self.vel_n[:, 2],
                "lat_deg": np.degrees(self.lat),
                "lon_deg": np.degrees(self.lon),
                "alt_m": self.alt_m,
            }
        )


# ----------------------------------------------------------------------------- helpers
def _time_grid(duration_s: float, rate_hz: float) -> FloatArray:
    if not np.isfinite(duration_s) or duration_s <= 0:
        raise ValueError(f"duration_s must be a positive number of seconds, got {duration_s}")
    if not np.isfinite(rate_hz) or rate_hz <= 0:
        raise ValueError(f"rate_hz must be a positive sample rate [Hz], got {rate_hz}")
    n = round(duration_s * rate_hz)
    if n < 1:
        raise ValueError(f"duration_s={duration_s} is shorter than one sample at {rate_hz} Hz")
    return np.arange(n + 1) / rate_hz


def _check_site(lat_deg: float, lon_deg: float) -> None:
    if not -89.0 <= lat_deg <= 89.0:
        raise ValueError(f"lat_deg={lat_deg} outside [-89, 89] (degrees expected)")
    if not -180.0 <= lon_deg <= 360.0:
        raise ValueError(f"lon_deg={lon_deg} outside [-180, 360] (degrees expected)")


def smooth_step(x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Septic smooth-step ``S(x) = 35x^4 - 84x^5 + 70x^6 - 20x^7`` on [0, 1] (clamped).

    Returns ``(S, S', S'')`` with respect to ``x``; ``S'``, ``S''`` and ``S'''`` vanish at
    both ends, so a blend ``a + (b - a) S((t - t0) / T)`` has continuous first, second and
    third time derivatives. The peak slope is ``S'(1/2) = 35/16``.
    """
    x = np.clip(x, 0.0, 1.0)
    s = x**4 * (35.0 + x * (-84.0 + x * (70.0 - 20.0 * x)))
    ds = 140.0 * x**3 * (1.0 - x) ** 3
    dds = 420.0 * x**2 * (1.0 - x) ** 2 * (1.0 - 2.0 * x)
    return s, ds, dds


@dataclass(frozen=True)
class _Channel:
    """A scalar channel of time: ``base + sum_i delta_i S((t - start_i) / length_i)``.

    Transitions of one channel must not overlap (they are evaluated by ``searchsorted``).
    """

    base: float
    start: FloatArray
    length: FloatArray
    delta: FloatArray

    def __call__(self, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Value, first and second time derivative at times ``t``."""
        if len(self.start) == 0:
            zero = np.zeros_like(t)
            return zero + self.base, zero, zero
        before = np.concatenate([[0.0], np.cumsum(self.delta)])
        i = np.clip(np.searchsorted(self.start, t, side="right") - 1, 0, len(self.start) - 1)
        active = t >= self.start[0]
        s, ds, dds = smooth_step((t - self.start[i]) / self.length[i])
        s, ds, dds = (np.where(active, q, 0.0) for q in (s, ds, dds))
        value = self.base + np.where(active, before[i], 0.0) + self.delta[i] * s
        rate = self.delta[i] * ds / self.length[i]
        accel = self.delta[i] * dds / self.length[i] ** 2
        return value, rate, accel


def _channel(base: float, events: list[tuple[float, float, float]]) -> _Channel:
    arr = np.asarray(events, dtype=float).reshape(-1, 3)
    order = np.argsort(arr[:, 0], kind="stable")
    arr = arr[order]
    ends = arr[:, 0] + arr[:, 1]
    if np.any(arr[1:, 0] < ends[:-1] - 1e-9):
        raise ValueError("overlapping transitions in one trajectory channel")
    return _Channel(base=base, start=arr[:, 0], length=arr[:, 1], delta=arr[:, 2])


def body_rate_from_euler_rates(
    roll: FloatArray,
    pitch: FloatArray,
    roll_rate: FloatArray,
    pitch_rate: FloatArray,
    yaw_rate: FloatArray,
) -> FloatArray:
    """Body rate ``omega_nb_b`` [rad/s] from ZYX Euler angles and their rates.

    For ``rot_nb = Rz(yaw) Ry(pitch) Rx(roll)``:
    ``omega_nb_b = (roll' - yaw' sin(pitch),
    pitch' cos(roll) + yaw' sin(roll) cos(pitch),
    -pitch' sin(roll) + yaw' cos(roll) cos(pitch))``.
    """
    sr, cr = np.sin(roll), np.cos(roll)
    sp, cp = np.sin(pitch), np.cos(pitch)
    return np.stack(
        [
            roll_rate - yaw_rate * sp,
            pitch_rate * cr + yaw_rate * sr * cp,
            -pitch_rate * sr + yaw_rate * cr * cp,
        ],
        axis=-1,
    )


def _geodetic_from_velocity(
    t: FloatArray,
    vel_fn: Callable[[FloatArray], FloatArray],
    lat0: float,
    lon0: float,
    h0: float,
    max_step_s: float = 1.0 / 400.0,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Integrate geodetic position from an analytic ENU velocity.

    Cumulative Simpson quadrature on a grid refined to ``max_step_s`` (4th order), and a
    fixed-point iteration for the weak dependence of the radii of curvature on latitude
    (each pass shrinks the error by ~1e-6). Error well below a micrometre over an hour.
    """
    k = max(1, int(np.ceil((t[1] - t[0]) / max_step_s)))
    tf = np.linspace(t[0], t[-1], (len(t) - 1) * k + 1)
    vf = vel_fn(tf)
    h = h0 + cumulative_simpson(vf[:, 2], x=tf, initial=0.0)
    lat = np.full_like(tf, lat0)
    for _ in range(3):
        r_m, _r_n = radii_of_curvature(lat)
        lat = lat0 + cumulative_simpson(vf[:, 1] / (r_m + h), x=tf, initial=0.0)
    _r_m, r_n = radii_of_curvature(lat)
    lon = lon0 + cumulative_simpson(vf[:, 0] / ((r_n + h) * np.cos(lat)), x=tf, initial=0.0)
    return lat[::k], lon[::k], h[::k]


# ----------------------------------------------------------------------------- turntable
def turntable(
    *,
    duration_s: float = 100.0,
    turn_rad: float = 4 * np.pi,
    rate_hz: float = 200.0,
    lat_deg: float = PAPER_SITE.lat_deg,
    lon_deg: float = PAPER_SITE.lon_deg,
    alt_m: float = PAPER_SITE.alt_m,
    yaw0: float = 0.0,
    roll: float = 0.0,
    pitch: float = 0.0,
    ramp_s: float = 0.0,
) -> Trajectory:
    """The paper's turntable (Sec. 4.1): a fixed sensor turning about the local vertical.

    Parameters
    ----------
    duration_s : float
        Length [s]; the trajectory has ``round(duration_s * rate_hz) + 1`` samples from
        ``t = 0`` to ``t = duration_s``.
    turn_rad : float
        Total yaw change [rad] from the first to the last sample (default 720 deg,
        counter-clockwise seen from above, i.e. the heading decreases).
    rate_hz : float
        Sample rate [Hz].
    lat_deg, lon_deg, alt_m : float
        Site (default: the paper's, :data:`polins.site.PAPER_SITE`).
    yaw0 : float
        Initial yaw [rad].
    roll, pitch : float
        Constant tilt of the sensor on the platform [rad] (ZYX Euler angles, so the
        platform turns about the ENU vertical with the tilted sensor on it).
    ramp_s : float
        0 (default, the paper): constant turn rate ``turn_rad / duration_s`` from the
        first sample. > 0: the rate rises from rest over ``ramp_s`` and falls back to rest
        over the last ``ramp_s`` (smooth-step), still turning ``turn_rad`` in total.

    Returns
    -------
    Trajectory
        Zero velocity and acceleration, constant position.
    """
    t = _time_grid(duration_s, rate_hz)
    _check_site(lat_deg, lon_deg)
    if not 0.0 <= ramp_s <= duration_s / 2:
        raise ValueError(f"ramp_s={ramp_s} must be in [0, duration_s/2] seconds")
    if ramp_s == 0.0:
        rate = turn_rad / duration_s
        yaw = yaw0 + rate * t
        yaw_rate = np.full_like(t, rate)
    else:
        # rate(t) = w (S(t/T) - S((t - (D - T))/T)); integral of S over its ramp is T/2.
        w = turn_rad / (duration_s - ramp_s)
        up = _channel(0.0, [(0.0, ramp_s, w)])
        down = _channel(0.0, [(duration_s - ramp_s, ramp_s, -w)])
        yaw_rate = up(t)[0] + down(t)[0]
        yaw = yaw0 + w * (_integral_smooth_step(t, 0.0, ramp_s))
        yaw -= w * _integral_smooth_step(t, duration_s - ramp_s, ramp_s)
    n = len(t)
    zeros = np.zeros(n)
    rot_nb = Rotation.from_euler("ZYX", np.stack([yaw, zeros + pitch, zeros + roll], axis=-1))
    omega_nb_b = body_rate_from_euler_rates(zeros + roll, zeros + pitch, zeros, zeros, yaw_rate)
    return Trajectory(
        t=t,
        rot_nb=rot_nb,
        vel_n=np.zeros((n, 3)),
        lat=np.full(n, np.radians(lat_deg)),
        lon=np.full(n, np.radians(lon_deg)),
        alt_m=np.full(n, float(alt_m)),
        omega_nb_b=omega_nb_b,
        accel_n=np.zeros((n, 3)),
    )


def _integral_smooth_step(t: FloatArray, start: float, length: float) -> FloatArray:
    """``int_0^t S((s - start)/length) ds`` for the septic smooth-step [s]."""
    x = np.clip((t - start) / length, 0.0, 1.0)
    inside = length * x**5 * (7.0 + x * (-14.0 + x * (10.0 - 2.5 * x)))
    after = np.maximum(t - (start + length), 0.0)
    return inside + after


# ----------------------------------------------------------------------------- UGV
@dataclass(frozen=True)
class _UgvPlan:
    """The random manoeuvre plan of a UGV drive, as smooth channels of time."""

    speed: _Channel  # along-track speed [m/s]
    yaw: _Channel  # [rad], ENU yaw of the direction of travel
    pitch: _Channel  # [rad], -atan(road grade)
    crossfall: _Channel  # [rad], roll from the road's cross slope
    roll_per_lateral_accel: float  # [rad per m/s^2], body roll in turns


def _plan_ugv(
    duration_s: float, rng: np.random.Generator, speed_mps: float, yaw0: float, rest_s: float
) -> _UgvPlan:
    """Draw a random sequence of straight runs, turns, slopes, speed changes and stops."""
    a_long = 1.2  # peak longitudinal acceleration [m/s^2]
    a_lat = 2.0  # peak lateral acceleration [m/s^2]
    yaw_rate_max = np.radians(30.0)  # peak yaw rate [rad/s]
    peak = 35.0 / 16.0  # peak slope of the smooth-step

    def new_speed() -> float:
        return float(np.clip(speed_mps * rng.uniform(0.6, 1.4), 1.0, 10.0))

    speed_ev: list[tuple[float, float, float]] = []
    yaw_ev: list[tuple[float, float, float]] = []
    pitch_ev: list[tuple[float, float, float]] = []
    cross_ev: list[tuple[float, float, float]] = []

    def change_speed(t: float, v_from: float, v_to: float) -> float:
        length = max(2.0, peak * abs(v_to - v_from) / a_long)
        speed_ev.append((t, length, v_to - v_from))
        return t + length

    t = rest_s
    v = new_speed()
    t = change_speed(t, 0.0, v)
    pitch = 0.0
    cross = 0.0
    last_stop = 0.0
    while t < duration_s:
        t += rng.uniform(2.0, 8.0)  # straight run at constant speed
        kind = rng.choice(["turn", "turn", "slope", "speed", "stop"])
        if t - last_stop > 60.0:
            kind = "stop"
        if kind == "turn":
            dyaw = rng.choice([-1.0, 1.0]) * np.radians(rng.uniform(20.0, 150.0))
            length = max(3.0, peak * abs(dyaw) * v / a_lat, peak * abs(dyaw) / yaw_rate_max)
            yaw_ev.append((t, length, dyaw))
            t += length
        elif kind == "slope":
            grade = 0.0 if pitch != 0.0 and rng.uniform() < 0.5 else rng.uniform(-0.1, 0.1)
            new_cross = rng.uniform(-0.02, 0.02)
            length = max(2.0, 3.0 * v / 5.0) * rng.uniform(1.0, 2.0)
            new_pitch = -float(np.arctan(grade))  # uphill is nose up: negative pitch
            pitch_ev.append((t, length, new_pitch - pitch))
            cross_ev.append((t, length, new_cross - cross))
            pitch, cross = new_pitch, new_cross
            t += length
        elif kind == "speed":
            v_new = new_speed()
            t = change_speed(t, v, v_new)
            v = v_new
        else:
            t = change_speed(t, v, 0.0)
            t += rng.uniform(3.0, 10.0)  # standing still
            last_stop = t
            v_new = new_speed()
            t = change_speed(t, 0.0, v_new)
            v = v_new
    return _UgvPlan(
        speed=_channel(0.0, speed_ev),
        yaw=_channel(yaw0, yaw_ev),
        pitch=_channel(0.0, pitch_ev),
        crossfall=_channel(0.0, cross_ev),
        roll_per_lateral_accel=np.radians(0.5),
    )


def _ugv_kinematics(plan: _UgvPlan, t: FloatArray) -> dict[str, FloatArray]:
    """Euler angles, their rates, velocity and acceleration of the plan at times ``t``."""
    v, dv, _ = plan.speed(t)
    yaw, dyaw, ddyaw = plan.yaw(t)
    pitch, dpitch, _ = plan.pitch(t)
    cross, dcross, _ = plan.crossfall(t)
    k = plan.roll_per_lateral_accel
    roll = cross + k * v * dyaw  # right side down in a left (positive-yaw-rate) turn
    droll = dcross + k * (dv * dyaw + v * ddyaw)
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    x_n = np.stack([cp * cy, cp * sy, -sp], axis=-1)  # body x axis in ENU
    dx_n = np.stack(
        [-sp * dpitch * cy - cp * sy * dyaw, -sp * dpitch * sy + cp * cy * dyaw, -cp * dpitch],
        axis=-1,
    )
    return {
        "yaw": yaw,
        "pitch": pitch,
        "roll": roll,
        "omega_nb_b": body_rate_from_euler_rates(roll, pitch, droll, dpitch, dyaw),
        "vel_n": v[:, None] * x_n + 0.0,  # + 0.0: no signed zeros at standstill
        "accel_n": dv[:, None] * x_n + v[:, None] * dx_n,
    }


def ugv_drive(
    *,
    duration_s: float = 300.0,
    rate_hz: float = 200.0,
    rng: np.random.Generator,
    lat_deg: float = PAPER_SITE.lat_deg,
    lon_deg: float = PAPER_SITE.lon_deg,
    alt_m: float = PAPER_SITE.alt_m,
    speed_mps: float = 5.0,
    yaw0: float = 0.0,
    rest_s: float = 5.0,
) -> Trajectory:
    """A random ground-vehicle drive: straight runs, turns, slopes, speed changes, stops.

    The vehicle is non-holonomic: its velocity is along the body x axis (no lateral or
    vertical body velocity), its yaw is the direction of travel, its pitch is
    ``-atan(grade)`` of the road, and its roll is the road's cross slope (up to 0.02 rad)
    plus a body roll of 0.5 deg per m/s^2 of lateral acceleration (outwards in turns).
    Turns (20-150 deg, either direction) respect 2 m/s^2 lateral acceleration and
    30 deg/s yaw rate; speed changes 1.2 m/s^2; grades up to 10 %; at most 60 s between
    stops of 3-10 s (zero velocity). All manoeuvres are septic smooth-steps.

    Parameters
    ----------
    duration_s, rate_hz : float
        Length [s] and sample rate [Hz] (samples at ``k / rate_hz``, both ends included).
    rng : numpy.random.Generator
        Draws the manoeuvre plan (the same seed gives the same drive at any rate).
    lat_deg, lon_deg, alt_m : float
        Start position (default: the paper's site, :data:`polins.site.PAPER_SITE`).
    speed_mps : float
        Typical cruise speed [m/s]; each run draws 0.6-1.4 x this, clipped to [1, 10].
    yaw0 : float
        Initial yaw [rad].
    rest_s : float
        Standstill at the start [s] (for alignment).

    Returns
    -------
    Trajectory
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator, e.g. np.random.default_rng(0)")
    if not 0.0 < speed_mps <= 10.0:
        raise ValueError(f"speed_mps={speed_mps} must be in (0, 10] m/s")
    if rest_s < 0.0:
        raise ValueError(f"rest_s={rest_s} must be >= 0 seconds")
    t = _time_grid(duration_s, rate_hz)
    _check_site(lat_deg, lon_deg)
    plan = _plan_ugv(float(t[-1]), rng, speed_mps, yaw0, rest_s)
    kin = _ugv_kinematics(plan, t)
    lat, lon, alt = _geodetic_from_velocity(
        t,
        lambda tf: _ugv_kinematics(plan, tf)["vel_n"],
        np.radians(lat_deg),
        np.radians(lon_deg),
        float(alt_m),
    )
    return Trajectory(
        t=t,
        rot_nb=Rotation.from_euler(
            "ZYX", np.stack([kin["yaw"], kin["pitch"], kin["roll"]], axis=-1)
        ),
        vel_n=kin["vel_n"],
        lat=lat,
        lon=lon,
        alt_m=alt,
        omega_nb_b=kin["omega_nb_b"],
        accel_n=kin["accel_n"],
    )


__all__ = [
    "Trajectory",
    "body_rate_from_euler_rates",
    "smooth_step",
    "turntable",
    "ugv_drive",
]
