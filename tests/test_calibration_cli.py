"""``polins calibrate``: the round trip (rendered images -> new camera file -> better headings), maps, check, one-line errors."""

import json
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_calibration_intrinsics import BOARD, SQUARE_M, _board_images, _poses
from test_calibration_polarizer import STEPS, _polarizer_frames
from test_calibration_scenes import dark_mosaic_of, perturbed_camera, sensor, small_camera
from test_calibration_sensor import _flat_frames

import polins
from polins.cli import main
from polins.compass.measure import NoiseModelWarning
from polins.io import write_image
from polins.io.model_files import camera_model_toml
from polins.sim.render import direction_n

SUN_N = direction_n(30.0, 50.0)


def _write_images(folder, raws):
    folder.mkdir(parents=True)
    for i, raw in enumerate(raws):
        write_image(folder / f"{i:03d}.png", np.asarray(raw, dtype=np.uint16))
    return folder


def _relative_heading_rms_deg(raws, turns_deg, cam):
    """RMS heading error [deg] after removing the mean (the unidentifiable common offset)."""
    err = []
    for raw, a in zip(raws, turns_deg, strict=True):
        rot = Rotation.from_euler("z", a, degrees=True)
        m = polins.measure(raw, cam, sun_n=SUN_N, rot_nb_prior=rot)
        assert m.ok, m.reason
        err.append(np.angle(np.exp(1j * (m.yaw - np.radians(a)))))
    e = np.degrees(np.array(err))
    e -= np.degrees(np.angle(np.mean(np.exp(1j * np.radians(e)))))
    return float(np.sqrt(np.mean(e**2)))


@pytest.fixture(scope="module")
def sky(tmp_path_factory):
    """A base camera file, dark frames and a clear-sky rotation of a camera with gains
    +-3 %, angles +-1 deg, efficiencies 0.96-1 and dark offsets 10-40 DN, half of it held
    out."""
    tmp = tmp_path_factory.mktemp("calibrate")
    rng = np.random.default_rng(21)
    true = perturbed_camera(small_camera(8), rng)
    base = tmp / "base.toml"
    base.write_text(camera_model_toml(small_camera(8)))
    dark = dark_mosaic_of(true)
    _write_images(
        tmp / "dark", [sensor(dark, dark, true, rng, read_noise_dn=1.5) for _ in range(4)]
    )
    turns = np.concatenate([[0.0], np.sort(rng.uniform(0.0, 360.0, 23))])
    radiance = 220.0 * rng.uniform(0.9, 1.1, 24)
    raws = np.stack([
        polins.sim.render_raw(true, SUN_N, Rotation.from_euler("z", a, degrees=True),
                              radiance=r, rng=rng, ifov=True)
        for a, r in zip(turns, radiance, strict=True)
    ])  # fmt: skip
    _write_images(tmp / "fit", raws[::2])
    (tmp / "fit_turns_deg.txt").write_text(",".join(f"{a:.6f}" for a in turns[::2]))
    _write_images(tmp / "held_out", raws[1::2])
    return tmp, true, turns[1::2], raws[1::2]


def test_calibrate_round_trip_beats_the_uncalibrated_file(sky, capsys):
    tmp, true, turns, held_out = sky
    assert main(["calibrate", "dark", str(tmp / "dark"), "--camera", str(tmp / "base.toml"),
                 "--out", str(tmp / "dark.toml")]) == 0  # fmt: skip
    assert "dark_offset_dn" in capsys.readouterr().out
    assert main(["calibrate", "sky-rotation", str(tmp / "fit"), "--camera", str(tmp / "dark.toml"),
                 "--out", str(tmp / "sky.toml"), "--name", "my-camera"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "noise_ratio" in out and "wrote" in out and "sky.toml" in out

    cam = polins.load_camera(tmp / "sky.toml")
    dark_only = polins.load_camera(tmp / "dark.toml")
    assert cam.name == "my-camera"
    assert [e["kind"] for e in cam.calibration] == ["dark", "sky-rotation"]
    entry = cam.calibration[-1]
    assert entry["n_images"] == 12 and entry["date"].endswith("+00:00") and entry["noise_ratio"] < 2
    text = (tmp / "sky.toml").read_text()
    assert text.startswith("# camera model written by polins calibrate sky-rotation")
    assert "# base camera: " in text and "dark.toml" in text
    np.testing.assert_allclose(cam.dark_offset_dn, true.dark_offset_dn, atol=0.5)
    np.testing.assert_allclose(cam.gain / cam.gain.mean(), true.gain / true.gain.mean(), atol=3e-3)

    # Headings on the held-out images: the calibrated file beats the uncalibrated one.
    with warnings.catch_warnings():
        warnings.simplefilter("error", NoiseModelWarning)  # the calibrated file explains the noise
        calibrated = _relative_heading_rms_deg(held_out, turns, cam)
        perfect = _relative_heading_rms_deg(held_out, turns, true)
    with pytest.warns(NoiseModelWarning, match="x the camera file's noise model"):
        uncalibrated = _relative_heading_rms_deg(held_out, turns, dark_only)  # and says so
    assert calibrated < 0.2 * uncalibrated and calibrated < 1.5 * perfect + 0.01

    # The check reads the same: redundancy about the noise with the new file, not the old.
    assert main(["calibrate", "check", str(tmp / "sky.toml"), str(tmp / "held_out"), "--json"]) == 0
    ratio_new = json.loads(capsys.readouterr().out)["noise_ratio"]
    assert main(["calibrate", "check", str(tmp / "dark.toml"), str(tmp / "held_out")]) == 0
    assert "redundancy residual" in capsys.readouterr().out
    report = polins.calibration.check(dark_only, held_out)
    assert ratio_new < 1.3 < report.noise_ratio


def test_polarizer_maps_go_to_the_maps_folder_and_are_used(tmp_path, capsys):
    rng = np.random.default_rng(12)
    cam = small_camera(8)
    true = perturbed_camera(cam, rng, eff=(0.95, 0.99))
    frames, _ = _polarizer_frames(true, rng, np.concatenate([STEPS, STEPS + 0.1]),
                                  pixel_angle_deg=0.5)  # fmt: skip
    base = tmp_path / "base.toml"
    known = {
        "dark_offset_dn": true.dark_offset_dn,
        "read_noise_dn": 2.0,
        "conversion_gain_e_per_dn": 4.0,
    }  # the frames' sensor: dark and noise known
    base.write_text(camera_model_toml(cam.with_changes(**known)))
    _write_images(tmp_path / "fit", frames[:12])
    _write_images(tmp_path / "held_out", frames[12:])
    angles = ",".join(f"{a:g}" for a in np.degrees(STEPS))
    argv = ["calibrate", "polarizer", str(tmp_path / "fit"), "--camera", str(base),
            "--out", str(tmp_path / "cams" / "pol.toml"), "--angles-deg", angles]  # fmt: skip
    assert main([*argv, "--pixel-maps", "--maps-dir", str(tmp_path / "maps")]) == 0
    out = capsys.readouterr().out
    assert "per-pixel transmission_angle_map written" in out
    assert sorted(p.name for p in (tmp_path / "maps").iterdir()) == [
        "pol.efficiency_map.npy", "pol.gain_map.npy", "pol.transmission_angle_map.npy"
    ]  # fmt: skip
    text = (tmp_path / "cams" / "pol.toml").read_text()
    assert 'transmission_angle_map_rad_npy = "../maps/pol.transmission_angle_map.npy"' in text
    mapped = polins.load_camera(tmp_path / "cams" / "pol.toml")
    assert mapped.has_pixel_maps and mapped.calibration[-1]["kind"] == "polarizer"
    np.testing.assert_allclose(np.degrees(mapped.transmission_angle),
                               np.degrees(true.transmission_angle), atol=0.1)  # fmt: skip
    # The maps explain the per-pixel angle spread that the channel values cannot.
    with_maps = polins.calibration.check(mapped, frames[12:]).noise_ratio
    without = polins.calibration.check(mapped.without_pixel_maps(), frames[12:]).noise_ratio
    # (the maps' own fit error from 12 frames leaves about sqrt(1 + 3/12) = 1.12)
    assert with_maps < 1.2 and with_maps < without - 0.1  # measured: 1.14 and 1.28
    # A later step that fits the channel angles drops the old maps (never overrides them).
    assert main([*argv[:5], "--camera", str(tmp_path / "cams" / "pol.toml"),
                 "--out", str(tmp_path / "again.toml"), "--angles-deg", angles]) == 0  # fmt: skip
    assert "dropped the base camera's gain_map" in capsys.readouterr().out
    again = polins.load_camera(tmp_path / "again.toml")
    assert not again.has_pixel_maps and len(again.calibration) == 2


def test_noise_flat_and_intrinsics_steps_chain(tmp_path, capsys):
    """Each step's --out is the next step's --camera: the record grows, each step sets its
    fields, the flat's gain map is written and named."""
    rng = np.random.default_rng(5)
    true = perturbed_camera(small_camera(8), rng)
    base = tmp_path / "base.toml"
    base.write_text(camera_model_toml(small_camera(8, dark_offset_dn=true.dark_offset_dn)))
    levels = np.repeat([0.0, 100.0, 400.0, 1000.0, 2000.0, 3500.0], 2)
    _write_images(tmp_path / "ptc", _flat_frames(true, rng, levels, read_noise=2.5,
                                                  conversion_gain=1.6))  # fmt: skip
    _write_images(tmp_path / "flat", _flat_frames(true, rng, np.full(8, 1500.0)))
    assert main(["calibrate", "noise", str(tmp_path / "ptc"), "--camera", str(base),
                 "--out", str(tmp_path / "n.toml")]) == 0  # fmt: skip
    assert main(["calibrate", "flat", str(tmp_path / "flat"), "--camera", str(tmp_path / "n.toml"),
                 "--out", str(tmp_path / "f.toml"), "--gain-map"]) == 0  # fmt: skip
    assert "per-pixel gain_map written" in capsys.readouterr().out
    cam = polins.load_camera(tmp_path / "f.toml")
    assert [e["kind"] for e in cam.calibration] == ["noise", "flat"]
    assert cam.read_noise_dn == pytest.approx(2.5, rel=0.05)
    assert cam.conversion_gain_e_per_dn == pytest.approx(1.6, rel=0.05)
    np.testing.assert_allclose(cam.gain / cam.gain.mean(), true.gain / true.gain.mean(), atol=1e-3)
    assert cam.gain_map is not None and (tmp_path / "f.gain_map.npy").is_file()

    # Intrinsics on rendered checkerboards, from a 5 % wrong focal length.
    lens = small_camera(2, dark_offset_dn=np.full(4, 12.0))  # 612 x 512 superpixels
    _write_images(tmp_path / "boards", _board_images(lens, _poses(rng, 8), rng))
    start = lens.with_changes(
        camera_matrix=lens.camera_matrix * [[1.05, 1, 1], [1, 1.05, 1], [1, 1, 1]]
    )
    (tmp_path / "start.toml").write_text(camera_model_toml(start))
    assert main(["calibrate", "intrinsics", str(tmp_path / "boards"), "--camera",
                 str(tmp_path / "start.toml"), "--out", str(tmp_path / "lens.toml"),
                 "--board", f"{BOARD[0]}x{BOARD[1]}", "--square-mm", f"{1000 * SQUARE_M:g}"]) == 0  # fmt: skip
    assert "reprojection_rms_px" in capsys.readouterr().out
    fitted = polins.load_camera(tmp_path / "lens.toml")
    assert fitted.calibration[-1]["reprojection_rms_px"] < 0.5
    assert np.diag(fitted.camera_matrix)[:2] == pytest.approx(
        np.diag(lens.camera_matrix)[:2], rel=5e-3
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["intrinsics", "IMG", "--board", "9-6", "--square-mm", "25"], "--board '9-6'"),
        (["intrinsics", "IMG", "--board", "9x2", "--square-mm", "25"], "at least 3x3"),
        (["intrinsics", "IMG", "--board", "9x6", "--square-mm", "0"], "--square-mm 0"),
        (["polarizer", "IMG", "--angles-deg", "0,15,x"], "--angles-deg '0,15,x'"),
        (["polarizer", "IMG", "--angles-deg", "0,15"], "2 angles for 1 images"),
        (["polarizer", "IMG", "--polarizer-dop", "1.5"], "--polarizer-dop 1.5"),
        (["polarizer", "IMG"], "at least 6 images"),
        (["dark", "IMG", "--out", "new.txt"], "must end in .toml"),
        (["dark", "nope.png"], "image not found: nope.png"),
        (["dark", "IMG", "--camera", "no-such-camera"], "no-such-camera"),
        (["camera-imu", "no-log"], "manifest not found: no-log"),
        (["camera-imu", "no-log", "--max-offset-s", "0"], "--max-offset-s 0: expected > 0"),
        (["sky-rotation", "WRONG"], "image shape (64, 64) does not match the camera model"),
        (["sky-rotation", "IMG", "--lat", "45"], "--times-utc, --lat and --lon go together"),
        (
            ["sky-rotation", "IMG", "--times-utc", "TIMES", "--lat", "45", "--lon", "126"],
            "--times-utc TIMES: 2 times for 1 images",
        ),
        (
            ["sky-rotation", "IMG", "--times-utc", "NAIVE", "--lat", "45", "--lon", "126"],
            "naive datetime",
        ),
    ],
)
def test_calibrate_mistakes_are_one_line_exit_2(tmp_path, capsys, args, message):
    cam = small_camera(8)
    base = tmp_path / "base.toml"
    base.write_text(camera_model_toml(cam))
    write_image(tmp_path / "img.png", np.full(cam.shape, 100, dtype=np.uint16))
    write_image(tmp_path / "wrong.png", np.full((64, 64), 100, dtype=np.uint16))
    argv = ["calibrate", *args]
    (tmp_path / "times.txt").write_text("2023-09-05T01:00:00Z\n2023-09-05T01:01:00Z\n")
    (tmp_path / "naive.txt").write_text("2023-09-05T01:00:00\n")
    names = {"IMG": tmp_path / "img.png", "WRONG": tmp_path / "wrong.png",
             "TIMES": tmp_path / "times.txt", "NAIVE": tmp_path / "naive.txt"}  # fmt: skip
    argv = [str(names[a]) if a in names else a for a in argv]
    message = message.replace("TIMES", str(names["TIMES"]))
    if "--camera" not in argv:
        argv += ["--camera", str(base)]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "new.toml")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err, err
    assert err.startswith(f"polins calibrate {args[0]}: error:")
    assert not (tmp_path / "new.toml").exists()


def test_a_log_carries_the_camera_file_with_its_maps(tmp_path):
    """write_log with a calibrated camera file (maps named relative to it) writes the maps
    into the log folder too, so that the log reads back with them."""
    import pandas as pd

    from polins.io import read_log, write_log
    from polins.io.model_files import write_camera_file

    cam = small_camera(8)
    gain = np.ones((*cam.superpixel_shape, 4)) * 1.01
    write_camera_file(cam.with_changes(gain_map=gain), tmp_path / "cams" / "mine.toml")
    imu = pd.DataFrame({"t": 0.01 * np.arange(20), **{c: np.zeros(20) for c in ("gx", "gy", "gz")},
                        "ax": np.zeros(20), "ay": np.zeros(20), "az": np.full(20, 9.8)})  # fmt: skip
    images = [(0.05, np.full(cam.shape, 100, dtype=np.uint16))]
    for i, camera in enumerate([tmp_path / "cams" / "mine.toml",
                                polins.load_camera(tmp_path / "cams" / "mine.toml")]):  # fmt: skip
        manifest = write_log(tmp_path / f"log{i}", epoch_utc="2023-09-05T15:06:00+08:00",
                             camera=camera, imu_model="fins-paper", lat_deg=45.6, lon_deg=126.7,
                             alt_m=0.0, imu=imu, images=images)  # fmt: skip
        log = read_log(manifest)
        np.testing.assert_allclose(log.camera.gain_map, gain, rtol=1e-6)
        assert (tmp_path / f"log{i}" / "camera.gain_map.npy").is_file()


# ----------------------------------------------------------------------------- camera-imu
ROT_BC = Rotation.from_euler("xyz", [0.3, -0.5, 1.2], degrees=True)


@pytest.fixture(scope="module")
def turning_log(tmp_path_factory):
    """A simulated 60 s UGV log (turns, road grade and roll) whose camera is mounted
    ``ROT_BC`` and stamps its images 10 ms early, and a base camera file with identity."""
    import pandas as pd

    from polins.io.model_files import write_camera_file
    from polins.sim.scenario import simulate_log

    folder = tmp_path_factory.mktemp("camera_imu")
    true = polins.load_camera("paper-table1").with_changes(mat_bc=ROT_BC.as_matrix())
    sim = simulate_log(folder / "log", scenario="ugv", duration_s=60.0, camera=true, seed=3,
                       progress=False)  # fmt: skip
    index = pd.read_csv(folder / "log" / "images.csv")
    index["t"] -= 0.010  # the camera clock: images really taken 10 ms after their stamps
    index.to_csv(folder / "log" / "images.csv", index=False)
    write_camera_file(sim.camera.with_changes(mat_bc=np.eye(3), name="base"), folder / "base.toml")
    return folder


@pytest.mark.parametrize(
    ("extra", "mode", "tol_deg"),
    [([], "mode: clock", 0.05), (["--no-clock"], "mode: no clock", 0.1)],
)
def test_calibrate_camera_imu_from_a_log(turning_log, capsys, extra, mode, tol_deg):
    """``polins calibrate camera-imu LOG``: the clock mode with the log's truth attitude, the
    no-clock mode with its gyro alone (the boresight's yaw there only from the road's 5 deg
    of pitch: std 0.035 deg, hence the wider tolerance)."""
    out = turning_log / "new.toml"
    argv = ["calibrate", "camera-imu", str(turning_log / "log"), "--camera",
            str(turning_log / "base.toml"), "--out", str(out), *extra]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert mode in text and "time offset dt = " in text and "wrote" in text
    cam = polins.load_camera(out)
    entry = cam.calibration[-1]
    assert entry["kind"] == "camera-imu" and entry["n_images"] > 250
    assert abs(entry["time_offset_s"] - 0.010) <= 1e-3  # measured: 10.09 / 10.05 ms
    err = (Rotation.from_matrix(cam.mat_bc) * ROT_BC.inv()).as_rotvec(degrees=True)
    assert np.abs(err).max() <= tol_deg  # measured: 0.0014 / 0.036 deg
    if extra:
        assert "attitude: the integrated gyro" in text
        assert abs(err[2]) < 4 * entry["boresight_std_deg"][2]
    else:
        assert "attitude: the log's truth table" in text


@pytest.mark.slow
def test_calibrate_sky_rotation_with_the_clock(tmp_path, capsys):
    """``--times-utc FILE --lat --lon``: the sun's motion over a 20-minute sequence from the
    ephemeris, as ``fit_sky_rotation(..., times_utc=, site=)`` does."""
    from test_calibration_sky_rotation import moving_sun_scene

    from polins.io.model_files import write_camera_file

    true, base, raws, times, site = moving_sun_scene()
    _write_images(tmp_path / "sky", raws)
    write_camera_file(base, tmp_path / "base.toml")
    (tmp_path / "times.txt").write_text("# UTC time of each image\n"
                                        + "\n".join(t.isoformat() for t in times) + "\n")  # fmt: skip
    argv = ["calibrate", "sky-rotation", str(tmp_path / "sky"), "--camera",
            str(tmp_path / "base.toml"), "--out", str(tmp_path / "new.toml"), "--times-utc",
            str(tmp_path / "times.txt"), "--lat", str(site.lat_deg), "--lon", str(site.lon_deg),
            "--alt", str(site.alt_m)]  # fmt: skip
    assert main(argv) == 0
    assert "the sun's motion from the ephemeris" in capsys.readouterr().out
    cam = polins.load_camera(tmp_path / "new.toml")
    d = cam.transmission_angle - true.transmission_angle
    assert np.degrees(np.abs(d - d.mean())).max() <= 0.2  # 0.41 deg without the clock


def test_check_scores_a_turntable_sequence(sky, capsys):
    """``check --turns-deg``: sun-free relative headings against the turns, an offset and a
    drift taken out; the true camera scores a few hundredths of a degree with an honest
    sigma, and turns of the wrong sign score tens of degrees."""
    tmp, true, turns, _ = sky
    path = tmp / "true.toml"
    path.write_text(camera_model_toml(true.with_changes(instrumental_dop_std=0.0)))
    turns_arg = ",".join(f"{a:.6f}" for a in turns)
    assert main(["calibrate", "check", str(path), str(tmp / "held_out"),
                 f"--turns-deg={turns_arg}", "--json"]) == 0  # fmt: skip
    score = json.loads(capsys.readouterr().out)
    assert score["n_ok"] == 12 and score["clock"] == "the image order"
    assert score["rmse_deg"] < 0.1 and 0.3 < score["rms_err_over_sigma"] < 2.0
    flipped = ",".join(f"{-a:.6f}" for a in turns)
    assert main(["calibrate", "check", str(path), str(tmp / "held_out"),
                 f"--turns-deg={flipped}"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "relative heading over 12 images: RMSE" in out
    assert float(out.split("RMSE ")[1].split(" deg")[0]) > 10.0


def test_sky_rotation_with_the_turntable_angles(sky, capsys):
    """``sky-rotation --turns-deg``: the turntable's angles go into the fit; the wrong sign
    is one line naming it."""
    tmp, true, _, _ = sky
    turns_arg = (tmp / "fit_turns_deg.txt").read_text()
    assert main(["calibrate", "dark", str(tmp / "dark"), "--camera", str(tmp / "base.toml"),
                 "--out", str(tmp / "dark2.toml")]) == 0  # fmt: skip
    assert main(["calibrate", "sky-rotation", str(tmp / "fit"), "--camera", str(tmp / "dark2.toml"),
                 "--out", str(tmp / "known.toml"), f"--turns-deg={turns_arg}"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "with the turns known" in out and "wrote" in out
    cam = polins.load_camera(tmp / "known.toml")
    np.testing.assert_allclose(cam.gain / cam.gain.mean(), true.gain / true.gain.mean(), atol=3e-3)
    flipped = ",".join(f"{-float(a):.6f}" for a in turns_arg.split(","))
    assert main(["calibrate", "sky-rotation", str(tmp / "fit"), "--camera", str(tmp / "dark2.toml"),
                 "--out", str(tmp / "flipped.toml"), f"--turns-deg={flipped}"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "negate them" in err and len(err.strip().splitlines()) == 1
