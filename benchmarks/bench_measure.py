"""Speed of the measurement chain: ms per full-resolution 2048 x 2448 raw image, per method,
next to a bare numpy superpixel Stokes of the same image (one core unless --threads).

    python benchmarks/bench_measure.py [--repeat 15] [--threads 1]

Prints a table; no assertions (timings depend on the machine).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=15, help="timed runs per method")
    parser.add_argument("--threads", type=int, default=1, help="BLAS/OpenMP threads")
    parser.add_argument("--camera", default="paper-table1")
    args = parser.parse_args()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)

    import numpy as np
    from scipy.spatial.transform import Rotation

    import polins
    from polins.compass.measure import measure

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from render_simple import render  # the independent test renderer

    cam = polins.load_camera(args.camera)
    sun_n = polins.sun_vector_n(np.radians(247.11), np.radians(60.21))
    rot = Rotation.from_euler("ZYX", [0.4, np.radians(5.0), np.radians(-3.0)])
    rng = np.random.default_rng(0)
    raw = render(cam, sun_n, rot, epsilon=0.0125, noise_std=1.5, rng=rng, dtype=np.uint16)

    def bare_stokes() -> object:
        # Superpixel Stokes with numpy only: float32 channels, S0 = sum/2, S1, S2.
        layout = {cam.channel_at[r, c]: (r, c) for r in range(2) for c in range(2)}
        ch = [raw[r::2, c::2].astype(np.float32) for r, c in (layout[k] for k in range(4))]
        return (ch[0] + ch[1] + ch[2] + ch[3]) * 0.5, ch[0] - ch[2], ch[1] - ch[3]

    def timed(fn) -> tuple[float, float, float, float]:
        fn()  # warm-up (caches: rays, masks, lens constants; numba import and compilation)
        wall, cpu = [], []
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        return (
            1e3 * float(np.median(wall)),
            1e3 * float(np.min(wall)),
            1e3 * float(np.median(cpu)),
            1e3 * float(np.min(cpu)),
        )

    rows = [("bare numpy superpixel Stokes", *timed(bare_stokes))]
    results = {}
    for method in ("traditional", "compensated"):

        def run(method: str = method) -> None:
            results[method] = measure(raw, cam, sun_n=sun_n, rot_nb_prior=rot, method=method)

        rows.append((f"measure(method={method!r})", *timed(run)))
    print(
        f"camera {cam.name}, raw {raw.shape} {raw.dtype}, threads {args.threads}, "
        f"{args.repeat} runs; wall-clock and CPU (process) time, median and min [ms]"
    )
    print(
        f"{'':34s} {'wall med':>9s} {'wall min':>9s} {'CPU med':>8s} {'CPU min':>8s} {'x bare':>7s}"
    )
    bare_min = rows[0][2]
    for name, med, best, cpu, cpu_best in rows:
        print(
            f"{name:34s} {med:9.1f} {best:9.1f} {cpu:8.1f} {cpu_best:8.1f} {best / bare_min:7.2f}"
        )
    print("(x bare: ratio of the wall-clock minima; on a shared machine the CPU minima are the")
    print(" least load-sensitive figures)")
    for method, m in results.items():
        print(
            f"  {method:12s} n_pixels={m.n_pixels} yaw_std_meas={np.degrees(m.yaw_std_meas):.5f} deg "
            f"yaw_std={np.degrees(m.yaw_std):.4f} deg (model {np.degrees(m.yaw_std_model):.4f}, "
            f"correlated {np.degrees(m.yaw_std_correlated):.4f}) heading={m.heading_deg:.4f} deg"
        )


if __name__ == "__main__":
    main()
