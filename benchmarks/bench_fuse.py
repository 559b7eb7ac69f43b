"""Speed of ``polins.fuse`` (the ESKF, 10 Hz polarization yaw) beside GTSAM's C++ EKF.

Prints IMU samples per second of, in the same run and over the same IMU samples, with the
machine's core count and load average (the machine may be shared: the ratios to the
reference carry over, the wall times do not):

* GTSAM's ``gtsam.NavStateImuEKF.predict`` (9-state navigation EKF in C++, propagation
  only) driven sample by sample from Python: the reference;
* ``polins.fuse`` of the default configuration (a free vehicle, 22 states) with its default
  output, 10 rows per second, and with a row per IMU sample (``output_rate_hz="imu"``; each
  row also carries the sigmas of all states, Euler angles and a quaternion);
* the same for the ground configuration (``vehicle="ground"``: non-holonomic constraint,
  zero-velocity and zero-rate updates at rest, a 10 Hz wheel odometer);
* GTSAM's predict with its state and covariance read after every sample (what a row per
  sample of a solution table needs);
* the streaming filter: ``ESKF.propagate`` once per sample, and ``ESKF.propagate_many`` on
  runs of 0.1 s (how ``polins.loop.stream`` feeds it between images) and on the whole log;
* the cost of one Kalman update of the 22-state filter through filterpy (a scalar yaw and a
  2-dof update), and the floor of filterpy's ``predict`` + ``update`` alone at the 10 Hz
  epochs;
* in a fresh process: the time to import ``polins.fusion`` and the first ``polins.fuse``
  after it on a 10 s log;

then the largest differences of ``polins.fuse`` and of the streaming filter to a fine-step
reference (one covariance step per IMU interval: the ESKF's internal ``cov_step_s`` set to
the sample interval): the discretisation error of the default step
(``polins.fusion.config.COV_STEP_S``).

With ``--graph``, also the time of the graph backend (batch solver) on the same inputs; with
``--sections``, where the CPU time of one ``polins.fuse`` of each configuration goes (the
filter's steps timed one by one: each timer adds about a microsecond per call).

Run: ``python benchmarks/bench_fuse.py [--duration 120] [--imu mems-typical] [--repeat 5]
[--graph]``.
Every figure is the best of ``--repeat`` runs, interleaved round by round.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from unittest import mock

import numpy as np
import pandas as pd

import polins
from polins.frames import wrap_angle
from polins.fusion import build_filter
from polins.fusion.eskf import ESKF
from polins.fusion.items import items_from_table
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import ugv_drive

SITE = {"lat_deg": 45.6234, "lon_deg": 126.7264, "alt_m": 148.74}


def simulate(duration: float, model: polins.ImuModel, seed: int = 0):
    rng = np.random.default_rng(seed)
    traj = ugv_drive(duration_s=duration, rate_hz=model.sample_rate_hz, rng=rng)
    imu, _ = imu_errors(ideal_imu(traj), model, rng)
    truth = traj.truth_frame()
    t_meas = np.arange(0.05, duration, 0.1)  # 10 Hz
    yaw = np.interp(t_meas, truth.t, np.unwrap(truth.yaw))
    std = np.radians(0.3)
    meas = pd.DataFrame(
        {"t": t_meas, "yaw": wrap_angle(yaw + rng.normal(0.0, std, t_meas.size)), "yaw_std": std}
    )
    return traj, imu, meas


def best_time(fn: Callable[[], object], repeat: int) -> float:
    """Shortest wall time of ``repeat`` calls [s]."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def best_times(fns: dict[str, Callable[[], object]], repeat: int) -> dict[str, float]:
    """Shortest wall time of each function [s], the functions interleaved round by round
    (a slow spell of the machine then hits all of them, not one)."""
    best = dict.fromkeys(fns, np.inf)
    for _ in range(repeat):
        for key, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            best[key] = min(best[key], time.perf_counter() - t0)
    return best


def gtsam_run(
    imu: pd.DataFrame, model: polins.ImuModel, readout: bool = False
) -> Callable[[], None]:
    """GTSAM's EKF predict over the samples, one call per sample (a function to time);
    ``readout``: also read the state and covariance after every sample (what a row per
    sample of a solution table needs)."""
    import gtsam

    g = float(polins.ins.earth.normal_gravity(np.radians(SITE["lat_deg"]), SITE["alt_m"]))
    params = gtsam.PreintegrationParams.MakeSharedU(g)
    params.setGyroscopeCovariance(np.eye(3) * model.gyro_arw**2)
    params.setAccelerometerCovariance(np.eye(3) * model.accel_vrw**2)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    w = imu[["gx", "gy", "gz"]].to_numpy()
    f = imu[["ax", "ay", "az"]].to_numpy()
    dt = np.diff(imu["t"].to_numpy())

    def run() -> None:
        ekf = gtsam.NavStateImuEKF(gtsam.NavState(), np.eye(9) * 1e-4, params)
        for k in range(len(dt)):
            ekf.predict(w[k], f[k], dt[k])

    def run_readout() -> None:
        ekf = gtsam.NavStateImuEKF(gtsam.NavState(), np.eye(9) * 1e-4, params)
        for k in range(len(dt)):
            ekf.predict(w[k], f[k], dt[k])
            ekf.state()
            ekf.covariance()

    return run_readout if readout else run


def filterpy_floor(n_samples: int, n_updates: int, repeat: int, n: int) -> float:
    """Samples/s if the run cost only filterpy's predict + update of an ``n``-state filter
    at each 10 Hz epoch."""
    from filterpy.kalman import predict, update

    rng = np.random.default_rng(0)
    Phi = np.eye(n) + 1e-3 * rng.standard_normal((n, n))
    Q, P = np.eye(n) * 1e-8, np.eye(n) * 1e-4
    H = np.zeros((1, n))
    H[0, 2] = 1.0
    R = np.array([[1e-5]])

    def run() -> None:
        x, Pk = np.zeros(n), P
        for _ in range(n_updates):
            x, Pk = predict(x, Pk, Phi, Q)
            x, Pk = update(x, Pk, np.array([1e-3]), R, H)

    return n_samples / best_time(run, repeat)


@contextlib.contextmanager
def fine_steps(dt: float) -> Iterator[None]:
    """The ESKF of ``polins.fuse`` and ``build_filter`` with one covariance step per IMU
    interval ``dt`` [s] (an implementation constant, reached here through the class)."""
    fine = functools.partial(ESKF, cov_step_s=dt)
    with (
        mock.patch("polins.fusion.eskf.batch.ESKF", fine),
        mock.patch("polins.fusion.api.ESKF", fine),
    ):
        yield


def streaming(imu: pd.DataFrame, meas: pd.DataFrame, kw: dict, run_len: int | None):
    """A filter fed sample by sample (``run_len`` None) or in runs of ``run_len`` samples
    (``propagate_many``; 0: the whole log in one call); returns the filter."""
    t = imu["t"].to_numpy()
    w = imu[["gx", "gy", "gz"]].to_numpy()
    f = imu[["ax", "ay", "az"]].to_numpy()
    filt = build_filter(float(t[0]), float(t[1] - t[0]), **kw)
    filt.add_items(items_from_table(meas))
    if run_len is None:
        for k in range(len(t)):
            filt.propagate(t[k], w[k], f[k])
    else:
        step = run_len or len(t)
        for k in range(0, len(t), step):
            filt.propagate_many(t[k : k + step], w[k : k + step], f[k : k + step])
    return filt


def odometer(traj, duration: float) -> pd.DataFrame:
    """A 10 Hz wheel odometer: the true ground speed [m/s]."""
    t = np.arange(0.05, duration, 0.1)
    truth = traj.truth_frame()
    speed = np.hypot(truth["ve"].to_numpy(), truth["vn"].to_numpy())
    return pd.DataFrame({"t": t, "speed": np.interp(t, truth["t"].to_numpy(), speed)})


def update_costs(imu: pd.DataFrame, meas: pd.DataFrame, kw: dict, repeat: int) -> dict[str, float]:
    """Wall time [s] of one Kalman update of the default filter (its size, its state and
    covariance after 10 s), through the filter's filterpy call: a scalar yaw and a 2-dof
    update."""
    import timeit

    from polins.fusion.eskf.update import kalman_update
    from polins.fusion.measurement import Linearized

    t = imu["t"].to_numpy()
    k = int(np.searchsorted(t, t[0] + 10.0))
    filt = streaming(imu.iloc[:k], meas[meas["t"] < t[k - 1]], kw, 0)
    n = filt.n
    H1 = np.zeros((1, n))
    H1[0, 2] = 1.0
    H2 = np.zeros((2, n))
    H2[0, 3], H2[1, 4] = 1.0, 1.0
    one = Linearized(np.array([1e-3]), H1, np.array([[1e-5]]), "yaw")
    two = Linearized(np.array([1e-2, 1e-2]), H2, np.diag([1e-2, 1e-2]), "nhc")
    from filterpy.kalman import KalmanFilter

    kf = KalmanFilter(dim_x=n, dim_z=1)  # as the filter holds one
    out = {}
    for key, lin in (("update_1", one), ("update_2", two)):
        runs = timeit.repeat(lambda lin=lin: kalman_update(kf, filt.x, filt.P, lin),
                             number=200, repeat=repeat)  # fmt: skip
        out[key] = min(runs) / 200
    return out


# the steps of the filter timed by --sections: ("module[:class]", attribute, label), the
# functions replaced by timed ones where they are called from
SECTIONS = (
    ("polins.fusion.eskf.propagate", "strapdown", "strapdown (compiled), per segment"),
    ("polins.fusion.eskf.propagate", "_chunk", "error dynamics F of 64 steps"),
    ("polins.fusion.eskf.propagate", "discretize", "Phi, Q of 64 steps (Van Loan)"),
    ("polins.fusion.eskf.filter:ESKF", "predict", "predict: Phi P Phi^T + Q"),
    ("polins.fusion.eskf.filter:ESKF", "linearize", "linearize an item (z, H, R)"),
    ("polins.fusion.eskf.filter", "innovation", "innovation, NIS (the gate)"),
    ("polins.fusion.eskf.filter", "kalman_update", "filterpy update (Joseph form)"),
    ("polins.fusion.eskf.filter:ESKF", "_model_heading_bias", "heading-bias model, a heading"),
    ("polins.fusion.eskf.filter:ESKF", "apply", "apply an item (the four above in it)"),
    ("polins.fusion.eskf.batch", "advance", "the filter's run (fast path)"),
    ("polins.fusion.eskf.batch", "interpolate", "rows: nominal (+) x, sigmas"),
    ("polins.fusion.eskf.batch", "solution_table", "solution table"),
    ("polins.fusion.api", "prepare", "inputs: validation, fault policy, items"),
)


def sections(fn: Callable[[], object]) -> tuple[float, dict[str, tuple[float, int]]]:
    """CPU time [s] of ``fn()`` and of each of :data:`SECTIONS` in it ([s], calls)."""
    import importlib

    spent: dict[str, list[float]] = {label: [0.0, 0] for _, _, label in SECTIONS}
    patches = []
    for where, name, label in SECTIONS:
        mod_name, _, cls = where.partition(":")
        owner = importlib.import_module(mod_name)
        owner = getattr(owner, cls) if cls else owner
        inner = getattr(owner, name)

        def timed(*a, _inner=inner, _acc=spent[label], **k):
            t0 = time.process_time()
            try:
                return _inner(*a, **k)
            finally:
                _acc[0] += time.process_time() - t0
                _acc[1] += 1

        patches.append(mock.patch.object(owner, name, timed))
    with contextlib.ExitStack() as stack:
        for p in patches:
            stack.enter_context(p)
        t0 = time.process_time()
        fn()
        total = time.process_time() - t0
    return total, {k: (v[0], int(v[1])) for k, v in spent.items()}


def print_sections(name: str, fn: Callable[[], object], n_samples: int) -> None:
    fn()  # warm
    total, spent = sections(fn)
    print(f"\n{name}: CPU {1e3 * total:.1f} ms ({1e6 * total / n_samples:.2f} us a sample), "
          "of which (nested: apply holds linearize .. filterpy):")  # fmt: skip
    for label, (sec, calls) in spent.items():
        if calls:
            print(f"  {label:42s} {1e3 * sec:8.1f} ms {calls:7d} calls "
                  f"{1e6 * sec / calls:9.1f} us/call")  # fmt: skip


FIRST_FUSE = """
import time, pickle, warnings
warnings.simplefilter("ignore")
t0 = time.perf_counter()
import polins.fusion
t1 = time.perf_counter()
import polins
imu, meas, kw = pickle.load(open({path!r}, "rb"))
t2 = time.perf_counter()
polins.fuse(imu, meas, **kw)
t3 = time.perf_counter()
polins.fuse(imu, meas, **kw)
t4 = time.perf_counter()
print(t1 - t0, t3 - t2, t4 - t3)
"""


def first_fuse(imu: pd.DataFrame, meas: pd.DataFrame, kw: dict) -> tuple[float, ...]:
    """In a fresh process: import ``polins.fusion`` [s], the first ``polins.fuse`` after it
    and the second [s], on the first 10 s of the log."""
    import pickle
    import tempfile

    t = imu["t"].to_numpy()
    short = imu[t <= t[0] + 10.0]
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "log.pkl")
        with open(path, "wb") as fh:
            pickle.dump((short, meas[meas["t"] <= t[0] + 10.0], kw), fh)
        out = subprocess.run([sys.executable, "-c", FIRST_FUSE.format(path=path)],
                             capture_output=True, text=True, check=True)  # fmt: skip
    return tuple(float(v) for v in out.stdout.split())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=120.0, help="drive length [s]")
    ap.add_argument("--imu", default="mems-typical", help="IMU model name")
    ap.add_argument("--repeat", type=int, default=5, help="timing repeats (best is kept)")
    ap.add_argument("--sections", action="store_true",
                    help="also print where the CPU time of one fuse goes")  # fmt: skip
    ap.add_argument("--graph", action="store_true",
                    help="also time the graph backend (batch) once on the same inputs")  # fmt: skip
    args = ap.parse_args()
    warnings.simplefilter("ignore", UserWarning)
    load0 = os.getloadavg()[0]
    model = polins.load_imu(args.imu)
    traj, imu, meas = simulate(args.duration, model)
    odo = odometer(traj, args.duration)
    kw = dict(SITE, imu_model=model)
    gkw = dict(kw, vehicle="ground", odometry=odo)
    n = len(imu)
    run_01 = max(1, round(0.1 * model.sample_rate_hz))
    times = best_times(
        {
            "gtsam": gtsam_run(imu, model),
            "gtsam_out": gtsam_run(imu, model, readout=True),
            "all": lambda: polins.fuse(imu, meas, output_rate_hz="imu", **kw),
            "10": lambda: polins.fuse(imu, meas, **kw),
            "g_all": lambda: polins.fuse(imu, meas, output_rate_hz="imu", **gkw),
            "g_10": lambda: polins.fuse(imu, meas, **gkw),
            "many": lambda: streaming(imu, meas, kw, run_01),
            "whole": lambda: streaming(imu, meas, kw, 0),
        },
        args.repeat,
    )
    times["one"] = best_time(lambda: streaming(imu, meas, kw, None), max(1, args.repeat // 3))
    rates = {key: n / value for key, value in times.items()}
    n_states = build_filter(0.0, 1.0 / model.sample_rate_hz, **kw).n  # the default blocks
    rates["floor"] = filterpy_floor(n, len(meas), args.repeat, n_states)
    upd = update_costs(imu, meas, kw, args.repeat)
    first = first_fuse(imu, meas, kw)

    # discretisation error: against a fine-step reference (one covariance step per sample)
    dt = float(imu["t"].iloc[1] - imu["t"].iloc[0])
    fast = polins.fuse(imu, meas, **kw)
    with fine_steps(dt):
        ref = polins.fuse(imu, meas, **kw)
        one = streaming(imu, meas, kw, None)
    d_fuse = max(
        float(np.nanmax(np.abs(wrap_angle(fast[c] - ref[c])))) for c in ("roll", "pitch", "yaw")
    )
    stds = ["roll_std", "pitch_std", "yaw_std"]
    r_fuse = float(np.nanmax(np.abs(fast[stds].to_numpy() / ref[stds].to_numpy() - 1.0)))
    many = streaming(imu, meas, kw, run_01)
    a, b = one.state(), many.state()
    d_many = float((a.rot_nb * b.rot_nb.inv()).magnitude())
    r_many = float(np.max(np.abs(b.sigma["att"] / a.sigma["att"] - 1.0)))

    print(f"{os.cpu_count()} cores, load average {load0:.1f} at the start, "
          f"{os.getloadavg()[0]:.1f} at the end")  # fmt: skip
    print(f"IMU {model.name}, {n} samples at {model.sample_rate_hz:g} Hz, "
          f"{len(meas)} yaw updates (10 Hz), best of {args.repeat}")  # fmt: skip
    name_w = 66
    print(f"{'method':{name_w}s} {'samples/s':>11s} {'vs GTSAM':>9s}")
    table = [
        ("GTSAM NavStateImuEKF.predict (C++, 9 states, no updates)", "gtsam"),
        (f"polins.fuse, {n_states}-state ESKF + 10 Hz yaw, 10 rows/s (the default)", "10"),
        ("polins.fuse, the same, a row per sample (output_rate_hz='imu')", "all"),
        ("polins.fuse, ground (NHC, ZUPT, zero rate, 10 Hz odometer), 10 rows/s", "g_10"),
        ("polins.fuse, ground, a row per sample", "g_all"),
        ("GTSAM predict + state() and covariance() read every sample", "gtsam_out"),
        ("ESKF.propagate, one call per sample (streaming)", "one"),
        (f"ESKF.propagate_many, runs of 0.1 s ({run_01} samples)", "many"),
        ("ESKF.propagate_many, the whole log in one call", "whole"),
        (f"floor: filterpy predict+update ({n_states} states) alone per 10 Hz epoch", "floor"),
    ]
    for name, key in table:
        print(f"{name:{name_w}s} {rates[key]:11.0f} {rates[key] / rates['gtsam']:9.2f}")
    print(f"a row per sample vs GTSAM with its state read every sample: "
          f"{rates['all'] / rates['gtsam_out']:.2f}x")  # fmt: skip
    print(f"per-sample propagate: {1e6 / rates['one']:.1f} us/sample")
    print(f"one Kalman update of the {n_states}-state filter through filterpy: scalar "
          f"{1e6 * upd['update_1']:.1f} us, 2-dof {1e6 * upd['update_2']:.1f} us "
          f"(GTSAM predict: {1e6 / rates['gtsam']:.1f} us per sample)")  # fmt: skip
    print(f"a fresh process: import polins.fusion {first[0]:.2f} s, the first polins.fuse "
          f"after it (10 s log) {first[1]:.3f} s, the second {first[2]:.3f} s")  # fmt: skip
    print(f"max difference to the fine-step reference: fuse {d_fuse:.1e} rad (Euler sigmas "
          f"{r_fuse:.1e} relative); propagate_many at the end {d_many:.1e} rad (attitude "
          f"sigmas {r_many:.1e})")  # fmt: skip
    if args.sections:
        print_sections("polins.fuse, default, 10 rows/s", lambda: polins.fuse(imu, meas, **kw), n)
        print_sections("polins.fuse, ground, 10 rows/s", lambda: polins.fuse(imu, meas, **gkw), n)
    if args.graph:
        graph_s = best_time(lambda: polins.fuse(imu, meas, "graph", **kw), 1)
        print(f"graph backend (batch solver), the same inputs and options: {graph_s:.2f} s "
              f"({n / graph_s:.0f} samples/s; the ESKF above: {times['10']:.2f} s)")  # fmt: skip


if __name__ == "__main__":
    main()
