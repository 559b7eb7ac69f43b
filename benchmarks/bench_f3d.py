"""Real frames: relative heading and sky-rotation calibration on the F3D turntable sequence.

    python benchmarks/bench_f3d.py [FRAMES_DIR]      (or POLINS_F3D_DIR=FRAMES_DIR)

FRAMES_DIR holds the 19 raw DoFP TIFFs of the ``test/`` folder of the public repository
github.com/zhouwwenzhou/F3D_master_release (1280 x 720, 8-bit, Sony IMX250MZR-type mosaic;
a camera looking up from a turntable turned 0:10:180 deg). That repository has no licence:
the frames are NOT redistributable, so neither they nor anything derived from them may
enter this repository or its test data. Without them this script prints a message and
exits with status 0; CI runs the independent renderer (tests/test_realsky.py) instead.

The camera file is written from the repository's ``main.m``: a pinhole with fx = fy =
1280 px and the principal point at the image centre, no distortion, the Sony layout, and
otherwise the defaults of a new camera file (unit gains, nominal angles, no dark offset,
no calibration record). The turntable turns the camera counter-clockwise seen from above
(the images' ring-mean angle of polarization turns by -10 deg per step).

Scoring (polins.calibration.turntable): no clock, so the true relative heading is the turn
plus the sun's azimuth change; an offset and a drift linear in the frames' own counter
(the hexadecimal number in each file name) are fitted and the RMSE of what remains is
reported, with RMS(err/sigma) of the measurement's sigma, modulo 180 deg. Rows:

* for each camera, the mean angle of polarization of the central disc (radius 100 px, as
  main.m, and the largest disc inside the image, 360 px), as a reference;
* uncalibrated: all 19 frames, and with the field cut to 4.5, 8 and 16 deg from the axis
  (``max_field_angle``; 4.5 deg is main.m's disc): how the channel errors grow with the
  field angle;
* calibrated from all 19 frames without their angles, scored on the odd frames;
* calibrated from the even frames with their turntable angles, scored on the odd frames.

Each calibration prints its channels, the channel-dependent radial shading it fits (written
as a per-pixel gain map when significant), its notes and what its residual looks like, and
what its channels at the principal point cost a camera that is not calibrated (the floor
no choice of pixels goes below: :func:`centre_floor_deg`).

Prints figures; no assertions.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

CAMERA_TOML = """\
name = "f3d-main-m"
description = "F3D turntable camera, pinhole of main.m (fx = fy = 1280 px, centre)"
[sensor]
width_px = 1280
height_px = 720
bit_depth = 8
saturation_dn = 255
mosaic_layout_deg = [[90, 45], [135, 0]]
[polarizer]
nominal_angle_deg = [0, 45, 90, 135]
transmission_angle_deg = [0.0, 45.0, 90.0, 135.0]
gain = [1.0, 1.0, 1.0, 1.0]
efficiency = [1.0, 1.0, 1.0, 1.0]
dark_offset_dn = [0.0, 0.0, 0.0, 0.0]
[noise]
read_noise_dn = 1.5
conversion_gain_e_per_dn = inf
[lens]
projection = "pinhole"
polarization_model = "projection"
fx_superpixel = 640.0
fy_superpixel = 640.0
cx_superpixel = 319.5
cy_superpixel = 179.5
distortion = [0.0, 0.0, 0.0, 0.0]
fov_max_deg = 30.0
[mount]
mat_bc = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
[occlusion]
polygons_superpixel = []
"""

STEP_DEG = 10.0  # the turntable's step
DISC_RADIUS_PX = 100.0  # main.m's central disc
INSCRIBED_RADIUS_PX = 360.0  # the largest disc about the centre inside a 1280 x 720 image
FIELD_DEG = (4.5, 8.0, 16.0)  # uncalibrated rows with the field cut to these angles [deg]


def frames_dir() -> Path | None:
    """The frames' folder from the argument or ``POLINS_F3D_DIR``; None when absent."""
    given = sys.argv[1] if len(sys.argv) > 1 else os.environ.get("POLINS_F3D_DIR")
    if not given:
        return None
    path = Path(given)
    return path if path.is_dir() and any(path.glob("*.tif*")) else None


def disc_headings(raws, cam, radius_px=DISC_RADIUS_PX):  # type: ignore[no-untyped-def]
    """Relative heading [rad] from the mean angle of polarization of the central disc of
    ``radius_px`` (full-resolution pixels)."""
    import numpy as np

    from polins.calibration.images import channel_stack
    from polins.calibration.malus import base_stokes

    hs, ws = cam.superpixel_shape
    v, u = np.mgrid[0:hs, 0:ws].astype(float)
    disc = np.hypot(u - cam.camera_matrix[0, 2], v - cam.camera_matrix[1, 2]) < radius_px / 2
    stokes = base_stokes(channel_stack(raws, cam).channels[:, disc], cam).mean(axis=1)
    return -0.5 * np.arctan2(stokes[:, 2], stokes[:, 1])  # the pattern turns by -phi


def centre_floor_deg(res, cam, turns, counter, dop=0.69):  # type: ignore[no-untyped-def]
    """RMSE [deg] of the relative heading that the channel errors alone cause at the
    principal point when the nominal channels are used: the calibrated channels there (the
    gain map's, else the gains) seeing a sky of DoP ``dop`` turning with the turntable,
    read back with the camera file's channels, scored like the measurements. No choice of
    pixels removes this part: a camera-fixed polarization common to the pixels does not
    cancel in any of their means."""
    import numpy as np

    from polins.calibration.malus import base_stokes
    from polins.calibration.turntable import relative_heading_errors

    hs, ws = cam.superpixel_shape
    gain = res.gain if res.gain_map is None else res.gain_map[hs // 2, ws // 2]
    two_a, eta = 2.0 * res.transmission_angle, res.efficiency
    chi = -np.asarray(turns)  # the pattern turns by -phi
    stokes = np.stack([np.ones_like(chi), dop * np.cos(2 * chi), dop * np.sin(2 * chi)], -1)
    response = 0.5 * gain[:, None] * np.stack([np.ones(4), eta * np.cos(two_a),
                                               eta * np.sin(two_a)], -1)  # fmt: skip
    seen = base_stokes(stokes @ response.T, cam)
    err = relative_heading_errors(-0.5 * np.arctan2(seen[:, 2], seen[:, 1]), turns, counter)
    return float(np.degrees(np.sqrt(np.mean(err**2))))


def speed(raws, cam) -> str:  # type: ignore[no-untyped-def]
    """CPU time per frame [ms] of ``polins.measure(raw, cam)`` on the decoded frames, warm:
    minimum and median over the frames (after one call)."""
    import time
    import warnings

    import numpy as np

    from polins.compass.measure import measure

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the noise-model warning
        measure(raws[0], cam)
        cpu = []
        for raw in raws:
            c0 = time.process_time()
            measure(raw, cam)
            cpu.append(1e3 * (time.process_time() - c0))
    low, mid = np.min(cpu), np.median(cpu)
    return f"measure(raw, cam): {low:.1f} ms CPU per frame (median {mid:.1f}), warm"


def main() -> int:
    folder = frames_dir()
    if folder is None:
        print("bench_f3d: F3D frames not found (pass their folder or set POLINS_F3D_DIR); "
              "they are not redistributable and not in this repository: skipped")  # fmt: skip
        return 0
    import time
    import warnings

    import numpy as np

    from polins.calibration import SkyRotationResidualWarning, fit_sky_rotation
    from polins.calibration.turntable import relative_heading_errors, score_turntable
    from polins.errors import UserInputError
    from polins.io.images import read_image
    from polins.models import load_camera

    files = sorted(folder.glob("*.tif*"))
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "f3d.toml").write_text(CAMERA_TOML)
        cam = load_camera(Path(tmp) / "f3d.toml")
    raws = np.stack([read_image(f, shape=cam.shape) for f in files])
    counter = np.array([int(f.stem.rsplit("_", 1)[-1], 16) for f in files], dtype=float)
    turns = np.radians(STEP_DEG * np.arange(len(files)))
    print(
        f"{len(files)} frames from {folder}; turns 0:{STEP_DEG:g}:{STEP_DEG * (len(files) - 1):g} deg"
    )

    def row(label, camera, idx):  # type: ignore[no-untyped-def]
        for radius in (DISC_RADIUS_PX, INSCRIBED_RADIUS_PX):
            err = relative_heading_errors(disc_headings(raws[idx], camera, radius), turns[idx],
                                          counter[idx])  # fmt: skip
            print(f"{label:31s}: mean AoP of the central disc of {radius:.0f} px: RMSE "
                  f"{np.degrees(np.sqrt(np.mean(err**2))):.3f} deg")  # fmt: skip
        for method in ("traditional", "compensated"):
            s = score_turntable(raws[idx], camera, turns[idx], counter[idx], method=method)
            print(f"{label:31s}: {method:11s} {s.summary()}")

    start = time.perf_counter()
    row("uncalibrated, 19 frames", cam, slice(None))
    print(f"  (first call and both methods: {time.perf_counter() - start:.1f} s)")
    print(f"  {speed(raws, cam)}")
    for field_deg in FIELD_DEG:  # how the channel errors grow with the field angle
        s = score_turntable(raws, cam, turns, counter, method="traditional",
                            max_field_angle=np.radians(field_deg))  # fmt: skip
        print(f"  field within {field_deg:4.1f} deg      : {s.summary()}")
    odd, even = slice(1, None, 2), slice(0, None, 2)
    for label, kwargs in (
        ("calibrated from 19 without angles", {"raws": raws}),
        ("calibrated from even with angles", {"raws": raws[even], "turns": turns[even]}),
    ):
        try:
            with warnings.catch_warnings():  # the residual is printed below
                warnings.simplefilter("ignore", SkyRotationResidualWarning)
                res = fit_sky_rotation(cam=cam, **kwargs)
        except UserInputError as exc:
            print(f"{label}: refused: {exc}")
            continue
        print(f"{label}: gains {np.round(res.gain, 4).tolist()}, angles "
              f"{np.round(np.degrees(res.transmission_angle), 2).tolist()} deg, efficiencies "
              f"{np.round(res.efficiency, 3).tolist()}, noise ratio {res.noise_ratio:.1f}")  # fmt: skip
        print(f"  radial shading {np.round(res.radial_gain, 3).tolist()} per rho^2 (std "
              f"{np.round(res.radial_gain_std, 3).tolist()}), gain map "
              f"{'written' if res.gain_map is not None else 'none'}")  # fmt: skip
        for note in (*res.notes, res.residual_pattern):
            if note:
                print(f"  {note}")
        row("  scored on odd frames", cam.with_changes(**res.camera_changes()), odd)
        print(f"  its channel errors at the principal point cost the uncalibrated camera "
              f"{centre_floor_deg(res, cam, turns, counter):.3f} deg RMSE (DoP 0.69)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
