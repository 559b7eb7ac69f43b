"""The zenith angle of polarization of a narrow field (polins.compass.zenith,
docs/measurement.md §13) on the independent renderers."""

import warnings

import numpy as np
from scipy.spatial.transform import Rotation
from test_sun_free import narrow_camera

import polins
from polins.compass.chain import MODEL_SCALE, instrumental_stds
from polins.compass.heading import image_geometry
from polins.compass.image import image_stokes
from polins.compass.measure import measure
from polins.compass.measurement import MeasureOptions
from polins.compass.pixels import check_raw
from polins.compass.zenith import total_std, zenith_cone, zenith_mean
from polins.frames import wrap_angle
from polins.sim import render_raw
from polins.sim.realsky import random_real_sky, render_real_raw

CAM = polins.load_camera("paper-table1")


def _zenith_estimate(raw, cam, sun_n, rot):
    """Error [rad] (modulo pi) of the zenith cone's level sun azimuth and its sigma [rad]."""
    opt = MeasureOptions()
    img = image_stokes(check_raw(raw, cam), cam, opt)
    geo = image_geometry(cam, None, rot)
    zm, _ = zenith_mean(img, img.valid, geo.mat_lc, zenith_cone(img, geo.mat_lc))
    dop_std, mixing_std = instrumental_stds(cam, opt)
    std_instr = np.hypot(dop_std * zm.g_delta, mixing_std * zm.g_mixing)
    sun_l = geo.mat_lb @ rot.inv().apply(sun_n)
    err = float(wrap_angle(2.0 * (zm.azimuth_l - np.arctan2(sun_l[1], sun_l[0])))) / 2.0
    return err, total_std(zm.var_azimuth, zm.var_jack, std_instr, MODEL_SCALE)


def _realistic_case(cam, rng):
    """A random sun (zenith 25-75 deg), a camera tilted up to 3 deg and its realistic sky."""
    sun_n = polins.sun_vector_n(rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(25, 75)))
    tilt, direction = rng.uniform(0, np.radians(3.0)), rng.uniform(0, 2 * np.pi)
    rot = Rotation.from_euler("ZYX", [rng.uniform(-np.pi, np.pi), tilt * np.cos(direction),
                                      tilt * np.sin(direction)])  # fmt: skip
    return sun_n, rot, render_real_raw(cam, sun_n, rot, random_real_sky(rng, sun_n), rng)


def test_zenith_cone_is_unbiased_for_any_sun_elevation(tmp_path):
    # A noise-free Rayleigh sky, level camera: the cone about the zenith is symmetric about
    # the sun's vertical plane, so the mean doubled E-vector gives the azimuth exactly,
    # whether the sun is 5 or 80 deg high, up to the pixel grid's asymmetry about that plane.
    cam = narrow_camera(tmp_path)
    rot = Rotation.from_euler("ZYX", [0.7, 0.0, 0.0])
    for elevation_deg in (5.0, 30.0, 60.0, 80.0):
        sun_n = polins.sun_vector_n(np.radians(40.0), np.radians(90.0 - elevation_deg))
        raw = render_raw(cam, sun_n, rot, epsilon=0.0, noise_std=0.0, quantize=False)
        err, _ = _zenith_estimate(raw, cam, sun_n, rot)
        assert abs(err) < 3e-4, (elevation_deg, err)


def test_zenith_cone_sigma_is_honest_on_realistic_skies(tmp_path):
    # Realistic skies (clouds on half, vignetting, neutral points, gain residual), camera
    # tilted up to 3 deg: the vignetting about the tilted axis and the clouds break the
    # cone's symmetry; the mirror-pair jackknife covers them.
    cam = narrow_camera(tmp_path)
    rng = np.random.default_rng(1)
    out = []
    for _ in range(10):
        sun_n, rot, raw = _realistic_case(cam, rng)
        out.append(_zenith_estimate(raw, cam, sun_n, rot))
    err, sigma = np.array(out).T
    rms_z = float(np.sqrt(np.mean((err / sigma) ** 2)))
    assert 0.6 <= rms_z <= 1.5, rms_z
    assert np.degrees(np.sqrt(np.mean(err**2))) < 1.5


def test_narrow_field_takes_the_smaller_sigma_and_stays_honest(tmp_path):
    # Sun-free measurement with a narrow pinhole: the eigen solution or the zenith cone,
    # whichever states the smaller sigma; the sigma covers the error.
    cam = narrow_camera(tmp_path)
    rng = np.random.default_rng(1)
    out, zenith_used = [], 0
    for _ in range(10):
        sun_n, rot, raw = _realistic_case(cam, rng)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", polins.compass.measure.NoiseModelWarning)
            m = measure(raw, cam, rot_nb_prior=rot)
        assert m.ok and m.method == "traditional", m.reason
        zenith_used += "zenith angle of polarization" in m.reason
        true_b = rot.inv().apply(sun_n)
        out.append((float(wrap_angle(m.sun_azimuth_b - np.arctan2(true_b[1], true_b[0]))),
                    m.sun_azimuth_b_std))  # fmt: skip
    err, sigma = np.array(out).T
    assert zenith_used >= 1
    assert 0.6 <= float(np.sqrt(np.mean((err / sigma) ** 2))) <= 1.5
    assert np.degrees(np.sqrt(np.mean(err**2))) < 0.6
