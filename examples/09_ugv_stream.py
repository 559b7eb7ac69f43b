"""09 - Embed polins in a ground vehicle: NavigationStream fed by a 200 Hz IMU callback, a wheel odometer and a camera thread.

The way a robot's navigation node uses polins (docs/streaming.md): the stream is built from
the vehicle's log manifest (``NavigationStream.from_manifest``: camera and IMU model files,
site, epoch and the ``[vehicle]`` table: a ground vehicle with its IMU mounting and a wheel
odometer), so it runs the filter ``polins fuse`` runs on that vehicle's logs: the
non-holonomic constraint, zero-velocity updates at standstills and the odometer's speeds
with its scale factor. The IMU driver calls ``on_imu`` 200 times a second (the odometer's
10 Hz speeds come with it), a camera thread delivers the DoFP images (5 Hz, each arriving
40 ms after its exposure) through a queue, and a 2 Hz timer reads the estimate. The stream
is used from the IMU thread only; the camera thread never touches it. The images are
measured in a worker process (``executor="process"``), so ``add_imu`` never waits for an
image and the measurement does not hold the IMU thread through Python's GIL.

What it shows:

- the levelling window: ``state().aligning`` for the first ``align_s`` (1 s) at rest, then
  ``heading_known`` False until the first images agree on the yaw;
- heading +- 1 sigma at every timer tick, against the simulated truth;
- a camera dropout (no images for 8 s): the heading sigma grows with the gyro's noise and
  falls back at the next image;
- the cost of the ``add_imu``, ``add_image`` and ``state()`` calls on the IMU thread
  (median, 99th percentile, max), and each image's age when its verdict was known;
- the updates of every kind (images, NHC, zero-velocity, odometer) and the events.

The drive is simulated (``polins simulate --scenario ugv``: a MEMS IMU, road vibration,
images at 1/8 resolution) and replayed as fast as the computer allows.

    python examples/09_ugv_stream.py [--quick] [--out out/09_ugv_stream] [--seed 9]

--quick: a 25 s drive (dropout 10-18 s); default: 60 s (dropout 25-33 s).
"""

from __future__ import annotations

import argparse
import queue
import threading
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

import polins
from polins.evaluation import truth_at
from polins.io import read_log
from polins.loop import NavigationStream
from polins.sim.scenario import simulate_log

IMU_HZ = 200.0
CAMERA_HZ = 5.0
CAMERA_DELAY_S = 0.04  # exposure to delivery
TIMER_HZ = 2.0


class Camera(threading.Thread):
    """A camera driver thread: puts ``(t, image file)`` in the queue once the vehicle clock
    passes its exposure time plus the delivery delay."""

    def __init__(self, images, dropout, clock, out: queue.Queue) -> None:
        super().__init__(daemon=True)
        self.images, self.dropout, self.clock, self.out = images, dropout, clock, out

    def run(self) -> None:
        cond = self.clock["cond"]
        for t, path in self.images:
            if self.dropout[0] <= t < self.dropout[1]:
                continue  # the camera is dark (a cable, a bridge, the driver restarting)
            due = t + CAMERA_DELAY_S
            with cond:
                self.clock["camera_due"] = due
                cond.notify_all()
                cond.wait_for(lambda due=due: self.clock["t"] >= due)
            self.out.put((float(t), path))
        with cond:
            self.clock["camera_due"] = np.inf
            cond.notify_all()
        self.out.put(None)


class NavigationNode:
    """The vehicle's navigation node: IMU callback (with the odometer), image queue, timer."""

    def __init__(self, manifest: Path, odometer: np.ndarray) -> None:
        self.nav = NavigationStream.from_manifest(manifest, executor="process")
        self.odometer = odometer  # (t [s], speed [m/s]) rows, delivered with the IMU
        self.next_odo = 0
        self.images: queue.Queue = queue.Queue()
        self.cost: dict[str, list[float]] = {"add_imu": [], "add_image": [], "state": []}
        self.added_at: dict[float, float] = {}  # image t -> wall time it was added
        self.ages: list[float] = []  # wall time from add_image to the verdict [s]
        self.rows: list[dict] = []
        self.next_tick = 0.0

    def on_imu(self, t: float, gyro_b, accel_b) -> None:
        """IMU driver callback (200 Hz): the sample, the odometer's speeds and the images
        that arrived, the timer."""
        c0 = time.perf_counter()
        self.nav.add_imu(t, gyro_b, accel_b)
        self.cost["add_imu"].append(time.perf_counter() - c0)
        while self.next_odo < len(self.odometer) and self.odometer[self.next_odo, 0] <= t:
            self.nav.add_odometry(*self.odometer[self.next_odo])
            self.next_odo += 1
        while True:
            try:
                item = self.images.get_nowait()
            except queue.Empty:
                break
            if item is not None:
                c0 = time.perf_counter()
                self.nav.add_image(*item)
                self.cost["add_image"].append(time.perf_counter() - c0)
                self.added_at[item[0]] = c0
        if t >= self.next_tick:
            self.on_timer(t)
            self.next_tick += 1.0 / TIMER_HZ

    def on_timer(self, t: float) -> None:
        """2 Hz timer: read the estimate (what a planner would use)."""
        c0 = time.perf_counter()
        st = self.nav.state()
        self.cost["state"].append(time.perf_counter() - c0)
        now = time.perf_counter()
        for _, row in self.nav.drain_measurements().iterrows():
            if row["t"] in self.added_at and row.get("update_reason") != "skipped":
                self.ages.append(now - self.added_at.pop(row["t"]))
        if st.aligning:
            self.rows.append({"t": t, "status": "levelling"})
        elif not st.heading_known:
            self.rows.append({"t": t, "status": "no heading yet"})
        else:
            est = st.nav.row()  # a solution-table row: angles [rad], heading_deg [deg]
            self.rows.append({"t": t, "status": "ok", "heading_deg": est["heading_deg"],
                              "heading_std_deg": np.degrees(est["yaw_std"]),
                              "pending": int(st.images_pending)})  # fmt: skip


def percentiles_ms(x) -> str:
    """Median / 99 % / max of a list of durations [s], in ms."""
    a = 1e3 * np.asarray(x)
    return f"{np.median(a):7.3f} {np.percentile(a, 99):7.3f} {a.max():7.3f}  ({a.size} calls)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="25 s drive instead of 60 s")
    ap.add_argument("--out", type=Path, default=Path("out/09_ugv_stream"), help="figure folder")
    ap.add_argument("--seed", type=int, default=9, help="random seed")
    args = ap.parse_args()
    warnings.simplefilter("ignore", UserWarning)
    args.out.mkdir(parents=True, exist_ok=True)
    duration, dropout = (25.0, (10.0, 18.0)) if args.quick else (60.0, (25.0, 33.0))

    # the drive: polins simulate --scenario ugv (a ground vehicle with a wheel odometer)
    sim = simulate_log(args.out / "drive", scenario="ugv", duration_s=duration,
                       image_rate_hz=CAMERA_HZ, downscale=8, imu="mems-typical",
                       seed=args.seed, progress=False)  # fmt: skip
    log = read_log(sim.manifest)
    vehicle = log.manifest["vehicle"]
    node = NavigationNode(sim.manifest, log.odometry[["t", "speed"]].to_numpy())
    # the vehicle clock; the recorded IMU runs faster than real time, so it waits for the
    # camera thread to deliver each image due (a real camera keeps pace by itself)
    clock = {"t": -1.0, "camera_due": 0.0, "cond": threading.Condition()}
    camera = Camera(list(log.images), dropout, clock, node.images)
    camera.start()
    data = log.imu[["t", "gx", "gy", "gz", "ax", "ay", "az"]].to_numpy()
    wall = drive_imu(node, data, clock)
    camera.join()
    node.nav.close()
    events = node.nav.drain_events()
    updates = node.nav.drain_updates()

    table = pd.DataFrame(node.rows)
    ok = table["status"] == "ok"
    true_heading = polins.heading_deg_from_yaw(truth_at(log.truth, table["t"].to_numpy())["yaw"])
    table["error_deg"] = (table.get("heading_deg") - true_heading + 180.0) % 360.0 - 180.0
    print(f"UGV drive {duration:g} s: a {vehicle['kind']} vehicle with a wheel odometer "
          f"({sim.manifest}: [vehicle]), IMU {IMU_HZ:g} Hz, camera {CAMERA_HZ:g} Hz "
          f"(+{CAMERA_DELAY_S * 1e3:g} ms delivery), dropout {dropout[0]:g}-{dropout[1]:g} s; "
          f"{len(data)} samples in {wall:.1f} s wall")  # fmt: skip
    with pd.option_context("display.float_format", "{:.3f}".format, "display.width", 120):
        print(table.iloc[:: max(1, len(table) // 20)].to_string(index=False))
    inside = ok & (table["t"] > dropout[0]) & (table["t"] < dropout[1])
    before = ok & (table["t"] > dropout[0] - 3) & (table["t"] <= dropout[0])
    print(f"heading sigma: {table.loc[before, 'heading_std_deg'].mean():.3f} deg before the "
          f"dropout, {table.loc[inside, 'heading_std_deg'].max():.3f} deg at its end")  # fmt: skip
    print("latency [ms]         median     99%     max")
    for name, values in node.cost.items():
        print(f"  {name:<18} {percentiles_ms(values)}")
    print(f"  image verdict age  {percentiles_ms(node.ages)}  (add_image -> filter verdict)")
    print("  (add_imu: the filter runs in the call that completes each 0.25 s block of IMU\n"
          "   time; docs/streaming.md states every cost)")  # fmt: skip
    kinds = {str(k): int(v) for k, v in updates["name"].value_counts().items()}
    print(f"updates by kind: {kinds} (yaw: images; nhc, zupt, odo: the ground vehicle's)")
    counts = {str(k): int(v) for k, v in events["kind"].value_counts().items()}
    print(f"events: {counts if counts else 'none'}")

    plot_heading(table, dropout, args.out / "stream_heading.png")
    table.to_csv(args.out / "timer_ticks.csv", index=False)
    print(f"figure stream_heading.png and timer_ticks.csv in {args.out}")


def drive_imu(node: NavigationNode, data: np.ndarray, clock: dict) -> float:
    """The IMU driver: one ``on_imu`` callback per sample row ``(t, gyro_b, accel_b)``, each
    after the camera thread has delivered the images due; the wall time taken [s]."""
    wall0 = time.perf_counter()
    cond = clock["cond"]
    for row in data:
        with cond:
            cond.wait_for(lambda t=row[0]: clock["camera_due"] > t - 0.1)
            clock["t"] = row[0]
            cond.notify_all()
        node.on_imu(row[0], row[1:4], row[4:7])
    with cond:  # the IMU has stopped: images after its last sample are never due
        clock["t"] = np.inf
        cond.notify_all()
    return time.perf_counter() - wall0


def plot_heading(table: pd.DataFrame, dropout: tuple[float, float], path: Path) -> None:
    """Heading error with the stream's ±3σ and the heading sigma at the timer ticks."""
    ok = table["status"] == "ok"
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    t_ok = table.loc[ok, "t"]
    sig = 3 * table.loc[ok, "heading_std_deg"]
    ax1.fill_between(t_ok, -sig, sig, color="C0", alpha=0.25, label="±3σ (the stream's)")
    ax1.plot(t_ok, table.loc[ok, "error_deg"], "o-", ms=3, color="C0", label="heading error")
    for ax in (ax1, ax2):
        ax.axvspan(*dropout, color="0.85", label="camera dropout")
        ax.axvspan(0, 1.0, color="C1", alpha=0.2, label="levelling (aligning)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    ax1.set_ylabel("heading error [deg]")
    ax1.set_title("NavigationStream at 2 Hz timer ticks: heading error against the truth")
    ax2.plot(t_ok, table.loc[ok, "heading_std_deg"], "o-", ms=3, color="C2",
             label="heading 1σ")  # fmt: skip
    ax2.set_ylabel("heading sigma [deg]")
    ax2.set_xlabel("time [s]")
    ax2.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
