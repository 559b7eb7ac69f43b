"""07 - An offline log from start to report: simulate -> fuse (Eq. 13 loop) -> report.

The same as the two commands::

    polins simulate --scenario ugv --out sim/
    polins fuse sim/manifest.toml --out run/

Simulates a UGV drive (IMU + raw polarization images + truth) into a log folder, runs the
measurement-and-fusion loop over it (each image measured with the filter's attitude as the
prior, its inflated sigma as R), and writes the solution, the per-image measurements, a JSON
summary and the plots (heading with its 3-sigma band, heading error, measurement errors and
NIS, epsilon) to ``--out``. Prints the summary table.

    python examples/07_offline_log.py [--quick] [--out out/07_offline_log]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

from polins.evaluation import format_summary, summarize, write_report
from polins.io import read_log
from polins.loop import run_log
from polins.sim.scenario import simulate_log


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="30 s drive at 1/8 resolution")
    parser.add_argument("--out", type=Path, default=Path("out/07_offline_log"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=None, help="image processes (all cores)")
    args = parser.parse_args()
    duration, downscale = (30.0, 8) if args.quick else (120.0, 4)

    sim = simulate_log(args.out / "sim", scenario="ugv", duration_s=duration, image_rate_hz=5.0,
                       downscale=downscale, imu="mems-typical", seed=args.seed,
                       progress=not args.quick)  # fmt: skip
    log = read_log(sim.manifest)
    print(f"log: {sim.manifest} ({duration:g} s UGV drive, {len(log.images)} images "
          f"{log.camera.shape[1]}x{log.camera.shape[0]} px, IMU {log.imu_model.name})")  # fmt: skip

    result = run_log(log, workers=args.workers, progress=not args.quick)
    measurements = result.measurements  # one row per image
    assert measurements is not None
    summary = summarize(result.solution, measurements, result.events, truth=log.truth,
                        timing=result.info["timing"], settings=result.info["settings"],
                        settle_s=5.0, gate_prob=result.config.gate_probability,
                        updates=result.updates)  # fmt: skip
    files = write_report(args.out / "run", result.solution, measurements, result.events,
                         summary, truth=log.truth, title="simulated UGV drive")  # fmt: skip
    print(format_summary(summary))
    print("figures:", ", ".join(str(p) for name, p in files.items() if p.suffix == ".png"))


if __name__ == "__main__":
    main()
