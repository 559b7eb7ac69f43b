"""End-to-end throughput of ``polins fuse``: images/s and IMU samples/s on a simulated log,
one process vs the process pool, and the streaming API's per-call latency.

    python benchmarks/bench_pipeline.py [--quick] [--duration 60] [--downscale 4] [--workers N]

Prints figures only (no assertions). The loop is: per image ``polins.measure`` with the
filter's lagged attitude as prior (parallel in the pool), and one ESKF over the IMU samples
(sequential, its fast path between images), whose estimates are the final solution
(``polins.loop.offline``); the smoother and the graph run once more on the measurements.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from polins.fusion.config import FuseConfig
from polins.io import load_raw, read_log
from polins.loop import NavigationStream, run_log
from polins.sim.scenario import simulate_log


def _row(label: str, r) -> str:  # type: ignore[no-untyped-def]
    t = r.info["timing"]
    return (
        f"{label:<22}{t['run_s']:9.2f} {t['loop_s']:9.2f} {t['fuse_s']:8.2f} "
        f"{t['images'] / t['run_s']:10.1f} {t['imu_samples'] / t['run_s']:11.0f} "
        f"{1e3 * t['measure_s_mean']:12.1f}"
    )


def streaming_latency(manifest: Path, executor: str, workers: int) -> dict[str, float]:
    """Per-call wall time of ``add_imu`` / ``add_image`` / ``state`` while streaming a log."""
    log = read_log(manifest)
    nav = NavigationStream(log.camera, log.imu_model, site=log.site, epoch_utc=log.epoch_utc,
                           executor=executor, workers=workers)  # fmt: skip
    imu = log.imu.to_numpy()
    images = [(t, load_raw(item)) for t, item in log.images]
    lat_imu, lat_img, lat_state = [], [], []
    k = 0
    start = time.perf_counter()
    for t, raw in images:
        while k < len(imu) and imu[k, 0] <= t + 0.05:  # images arrive 50 ms late
            a = time.perf_counter()
            nav.add_imu(imu[k, 0], imu[k, 1:4], imu[k, 4:7])
            lat_imu.append(time.perf_counter() - a)
            if k % 20 == 0 and imu[k, 0] > 1.5:  # a 10 Hz navigation output
                a = time.perf_counter()
                nav.state()
                lat_state.append(time.perf_counter() - a)
            k += 1
        a = time.perf_counter()
        nav.add_image(t, raw)
        lat_img.append(time.perf_counter() - a)
    while k < len(imu):
        nav.add_imu(imu[k, 0], imu[k, 1:4], imu[k, 4:7])
        k += 1
    nav.close()
    total = time.perf_counter() - start
    out = {"total_s": total, "realtime_factor": (imu[-1, 0] - imu[0, 0]) / total}
    for name, lat in (("add_imu", lat_imu), ("add_image", lat_img), ("state", lat_state)):
        arr = 1e3 * np.asarray(lat)
        out[f"{name}_p50_ms"] = float(np.percentile(arr, 50))
        out[f"{name}_p99_ms"] = float(np.percentile(arr, 99))
        out[f"{name}_max_ms"] = float(arr.max())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="20 s log at 1/8 resolution")
    parser.add_argument("--duration", type=float, default=60.0, help="log length [s]")
    parser.add_argument("--downscale", type=int, default=4, help="image downscale factor")
    parser.add_argument("--image-rate", type=float, default=5.0, help="camera rate [Hz]")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--imu", default="fins-paper", help="IMU model of the simulation")
    args = parser.parse_args()
    if args.quick:
        args.duration, args.downscale = 20.0, 8

    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate_log(Path(tmp) / "log", scenario="ugv", duration_s=args.duration,
                           image_rate_hz=args.image_rate, downscale=args.downscale,
                           imu=args.imu, seed=0, progress=False)  # fmt: skip
        log = read_log(sim.manifest)
        h, w = log.camera.shape
        print(f"simulated UGV log: {args.duration:g} s, {len(log.imu)} IMU samples "
              f"({args.imu}), {len(log.images)} images {w}x{h} px, {os.cpu_count()} cores")  # fmt: skip
        print(f"{'run':<22}{'total [s]':>9} {'loop [s]':>9} {'fuse [s]':>8} {'images/s':>10} "
              f"{'IMU samp/s':>11} {'measure [ms]':>12}")  # fmt: skip
        single = run_log(log, workers=1, progress=False)
        print(_row("1 process", single))
        if args.workers > 1:
            pool = run_log(log, workers=args.workers, progress=False)
            print(_row(f"pool of {args.workers} processes", pool))
            diff = np.nanmax(np.abs(single.solution["yaw"] - pool.solution["yaw"]))
            print(f"largest yaw difference (1 vs {args.workers} workers): {diff:.1e} rad")
        smooth = run_log(log, workers=args.workers, progress=False,
                         config=FuseConfig.from_log(log).replace(smooth=True))  # fmt: skip
        print(_row("pool + RTS smoother", smooth))

        print("\nstreaming API (images 50 ms late, state() at 10 Hz), per-call wall time [ms]:")
        print(f"{'executor':<12}{'add_imu p50/p99/max':>24}{'add_image p50/p99/max':>26}"
              f"{'state p50/p99/max':>24}{'x real time':>13}")  # fmt: skip
        for executor, n in (("inline", 1), ("process", max(1, args.workers - 1))):
            lat = streaming_latency(sim.manifest, executor, n)
            cells = [
                "/".join(f"{lat[f'{c}_{q}_ms']:.2f}" for q in ("p50", "p99", "max"))
                for c in ("add_imu", "add_image", "state")
            ]
            print(f"{executor:<12}{cells[0]:>24}{cells[1]:>26}{cells[2]:>24}"
                  f"{lat['realtime_factor']:13.1f}")  # fmt: skip


if __name__ == "__main__":
    main()
