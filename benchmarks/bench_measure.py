"""Speed of ``polins.measure``: ms per frame warm, and the first call after import, for the
shipped fisheye camera and a 1280 x 720 8-bit pinhole camera (one core unless --threads).

    python benchmarks/bench_measure.py [--repeat 15] [--threads 1] [--no-first-call]

Frames (rendered in memory by the project's realistic renderer, polins.sim.realsky):

* ``paper-table1`` at full resolution (2048 x 2448, 12-bit in uint16) and at half
  resolution (1024 x 1224), the sun 60 deg from the zenith, tilt 5 deg;
* ``pinhole-1280x720``: a pinhole looking up, fx = fy = 1280 px, principal point at the
  image centre, Sony mosaic, 8-bit (a +-26 x +-16 deg field), level, the sun 10 deg above
  the horizon: the compensated method falls back to the traditional solution and the
  zenith cone, as on real turntable frames of such a camera (docs/measurement.md §10).

Rows: a bare numpy superpixel Stokes of the frame (the floor), then
``measure(raw, cam)`` (the default: compensated, sun-free; on the pinhole's narrow field it
falls back to the traditional solution and the zenith cone) and, with the ephemeris,
``measure(raw, cam, sun_n=..., rot_nb_prior=...)``. Warm: CPU (process) and wall-clock time
per frame, minimum and median of ``--repeat`` runs after one warm-up call. First call: a
fresh Python process per camera times ``import polins`` and its first ``measure`` (numba's
import, the cached machine code, the camera's pixel constants).

Prints tables; no assertions (timings depend on the machine and its load).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_f3d import CAMERA_TOML as PINHOLE_TOML  # the F3D camera of main.m (benchmarks/)

CAMERAS = ("paper-table1", "paper-table1/2", "pinhole-1280x720")


def load(name: str):  # type: ignore[no-untyped-def]
    """The benchmark's camera ``name`` (a shipped one, ``/2`` at half resolution)."""
    import polins

    if name == "pinhole-1280x720":
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "pinhole.toml"
            path.write_text(PINHOLE_TOML)
            return polins.load_camera(path)
    base, _, factor = name.partition("/")
    cam = polins.load_camera(base)
    return cam.downscaled(int(factor)) if factor else cam


def frame(cam):  # type: ignore[no-untyped-def]
    """A realistic sky for ``cam`` (module notes): raw mosaic, ENU sun, attitude."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    import polins
    from polins.sim.realsky import RealSky, render_real_raw

    rng = np.random.default_rng(0)
    if cam.bit_depth == 8:
        sun_n = polins.sun_vector_n(np.radians(200.0), np.radians(80.0))
        rot = Rotation.from_euler("ZYX", [0.4, 0.0, 0.0])
        sky = RealSky(zenith_dn=180.0, vignetting=0.1)  # about 100 DN per channel
        raw = render_real_raw(cam, sun_n, rot, sky, rng).astype(np.uint8)
    else:
        sun_n = polins.sun_vector_n(np.radians(247.11), np.radians(60.21))
        rot = Rotation.from_euler("ZYX", [0.4, np.radians(5.0), np.radians(-3.0)])
        raw = render_real_raw(cam, sun_n, rot, RealSky(), rng)
    return raw, sun_n, rot


def timed(fn, repeat: int) -> tuple[float, float, float, float]:  # type: ignore[no-untyped-def]
    """CPU min, CPU median, wall min, wall median [ms] of ``repeat`` calls after one."""
    import numpy as np

    fn()
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return tuple(1e3 * float(f(x)) for x in (cpu, wall) for f in (np.min, np.median))  # type: ignore[return-value]


def warm(name: str, repeat: int) -> None:
    """The warm rows of camera ``name``."""
    import warnings

    import numpy as np

    from polins.compass.measure import measure

    cam = load(name)
    raw, sun_n, rot = frame(cam)
    layout = {cam.channel_at[r, c]: (r, c) for r in range(2) for c in range(2)}

    def bare() -> object:  # superpixel Stokes with numpy only (float32)
        ch = [raw[r::2, c::2].astype(np.float32) for r, c in (layout[k] for k in range(4))]
        return (ch[0] + ch[1] + ch[2] + ch[3]) * 0.5, ch[0] - ch[2], ch[1] - ch[3]

    results = {}

    def sun_free() -> None:
        results["sun-free"] = measure(raw, cam)

    def ephemeris() -> None:
        results["ephemeris"] = measure(raw, cam, sun_n=sun_n, rot_nb_prior=rot)

    print(f"\n{cam.name}: raw {raw.shape} {raw.dtype}, {repeat} runs [ms per frame]")
    print(f"  {'':34s} {'CPU min':>8s} {'CPU med':>8s} {'wall min':>9s} {'wall med':>9s}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the noise-model warning of a rendered frame
        for label, fn in (("bare numpy superpixel Stokes", bare),
                          ("measure(raw, cam)", sun_free),
                          ("measure(raw, cam, sun_n, rot_nb_prior)", ephemeris)):  # fmt: skip
            c_min, c_med, w_min, w_med = timed(fn, repeat)
            print(f"  {label:34s} {c_min:8.1f} {c_med:8.1f} {w_min:9.1f} {w_med:9.1f}")
    for key, m in results.items():
        print(f"    {key:9s}: method {m.method}, n_pixels {m.n_pixels}, sun azimuth (body) "
              f"{np.degrees(m.sun_azimuth_b):.3f} +- {np.degrees(m.sun_azimuth_b_std):.3f} deg"
              + (f"; {m.reason}" if m.reason else ""))  # fmt: skip


FIRST_CALL = """
import time
c0, t0 = time.process_time(), time.perf_counter()
import polins
c1, t1 = time.process_time(), time.perf_counter()
import bench_measure, warnings
cam = bench_measure.load({name!r})
raw, sun_n, rot = bench_measure.frame(cam)
warnings.simplefilter("ignore")
c2, t2 = time.process_time(), time.perf_counter()
polins.measure(raw, cam)
c3, t3 = time.process_time(), time.perf_counter()
polins.measure(raw, cam)
c4, t4 = time.process_time(), time.perf_counter()
print(c1 - c0, t1 - t0, c3 - c2, t3 - t2, c4 - c3, t4 - t3)
"""


def first_call(name: str) -> None:
    """``import polins`` and the first ``measure`` of camera ``name`` in a fresh process."""
    here = str(Path(__file__).resolve().parent)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([here, os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", FIRST_CALL.format(name=name)], env=env,
                         capture_output=True, text=True, check=True).stdout  # fmt: skip
    c_imp, w_imp, c_first, w_first, c_next, w_next = (float(x) for x in out.split())
    print(f"  {name:18s} import polins {c_imp:5.2f} s CPU ({w_imp:5.2f} wall); first measure "
          f"{c_first:5.2f} s CPU ({w_first:5.2f} wall); the next {1e3 * c_next:6.1f} ms CPU ({1e3 * w_next:6.1f} wall)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=15, help="timed runs per row")
    parser.add_argument("--threads", type=int, default=1, help="BLAS/OpenMP threads")
    parser.add_argument("--no-first-call", action="store_true", help="skip the fresh processes")
    args = parser.parse_args()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)
    print(f"threads {args.threads}; load average {os.getloadavg()[0]:.1f}")
    for name in CAMERAS:
        warm(name, args.repeat)
    if not args.no_first_call:
        print("\nfirst call after import (fresh process; numba's machine code cached on disk):")
        for name in ("paper-table1/2", "pinhole-1280x720"):
            first_call(name)
    print("\n(on a shared machine the CPU minima are the least load-sensitive figures)")


if __name__ == "__main__":
    main()
