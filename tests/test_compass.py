"""Polarization compass: raw image -> sun vector -> heading, covariance and refusals
(docs/model.md §9-10, 12), on images from the independent renderer tests/render_simple.py."""

import dataclasses
import warnings

import numpy as np
import pytest
from render_simple import random_attitude, render
from scipy.spatial.transform import Rotation

import polins
from polins.compass.camera import pixel_rays_c
from polins.compass.crlb import yaw_crlb
from polins.compass.eigen import sun_eigen
from polins.compass.heading import yaw_from_sun_level
from polins.compass.lens import evectors_from_stokes, lens_basis
from polins.compass.measure import (
    MeasureOptions,
    check_measure_options,
    measure,
    measure_options,
    measure_with_maps,
)
from polins.compass.pixels import mosaic_channels
from polins.compass.polarimetry import stokes_from_channels
from polins.errors import UserInputError
from polins.frames import wrap_angle, yaw_from_rot_nb
from polins.sim.algorithm1 import measure_algorithm1, measure_baseline

CAM = polins.load_camera("paper-table1")
CAM4 = CAM.downscaled(4)
SUN_N = polins.sun_vector_n(np.radians(247.11), np.radians(60.21))  # paper Table 1


def _err_deg(m, rot):
    return float(np.degrees(wrap_angle(m.yaw - yaw_from_rot_nb(rot))))


def _level(yaw_deg):
    return Rotation.from_euler("ZYX", [np.radians(yaw_deg), 0.0, 0.0])


# ----------------------------------------------------------------------------- exactness
@pytest.mark.parametrize("model", ["projection", "meridian"])
def test_noise_free_heading_is_exact_for_any_attitude(model):
    # docs/model.md §12.2 and §12.8: noise-free, eps = 0, tilt up to 10 deg, both lens models:
    # heading error < 1e-6 deg for every method and for the paper's Algorithm 1 (here < 1e-9 deg
    # in float64).
    cam = CAM4.with_changes(polarization_model=model)
    rng = np.random.default_rng(10)
    for _ in range(3):
        sun_n = polins.sun_vector_n(rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(20, 75)))
        rot = random_attitude(rng, 10.0)
        raw = render(cam, sun_n, rot)
        for method, opts in [
            ("traditional", {}),
            ("equal weights", {}),
            ("compensated", {}),
            ("compensated", {"fixed_zenith": False, "loss": "huber"}),
        ]:
            if method == "equal weights":  # the paper's Eq. 31
                m = measure_baseline(raw, cam, sun_n=sun_n, rot_nb_prior=rot, weighted=False)
            else:
                m = measure(raw, cam, sun_n=sun_n, rot_nb_prior=rot, method=method, **opts)
            assert m.ok, m.reason
            assert abs(_err_deg(m, rot)) < 1e-9
            np.testing.assert_allclose(m.sun_b, rot.inv().apply(sun_n), atol=1e-10)
            assert m.heading_deg == pytest.approx(
                float(polins.heading_deg_from_yaw(yaw_from_rot_nb(rot))), abs=1e-8
            )
            assert m.eigen_gap > 0.99 and m.n_pixels > 15_000
        # docs/model.md §8.2: with the scale-consistent Eq. 22 the paper's k_m is exactly 0 without
        # noise, so Algorithm 1 is exact here too (it only adds noise).
        m, _ = measure_algorithm1(raw, cam, sun_n=sun_n, rot_nb_prior=rot)
        assert abs(_err_deg(m, rot)) < 1e-9 and m.epsilon == 0.0


def test_rayleigh_sky_skips_the_berry_solve():
    # On the estimator's Rayleigh sky the score test at zero neutral-point separation finds
    # nothing to fit: the default (Berry sky, separation fitted) is the Rayleigh solution, to
    # the last bit, with and without the sun (docs/measurement.md §5).
    rng = np.random.default_rng(12)
    for _ in range(2):
        sun_n = polins.sun_vector_n(rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(30, 70)))
        rot = random_attitude(rng, 5.0)
        raw = render(CAM4, sun_n, rot, epsilon=0.01, noise_std=1.5, rng=rng, dtype=np.uint16)
        for sun in (sun_n, None):
            m = measure(raw, CAM4, sun_n=sun, rot_nb_prior=rot)
            r = measure(raw, CAM4, sun_n=sun, rot_nb_prior=rot, sky_model="rayleigh")
            assert m.ok and m.method == "compensated", m.reason
            assert m.sun_azimuth_b == r.sun_azimuth_b and m.epsilon == r.epsilon
            assert m.sun_azimuth_b_std == r.sun_azimuth_b_std


def test_integer_mosaic_runs_in_float32_without_bias():
    # uint16 input is processed in float32; at a high radiance the quantisation is small.
    rot = random_attitude(np.random.default_rng(11), 10.0)
    raw = render(CAM4, SUN_N, rot, radiance=3000.0, dtype=np.uint16)
    for method in ("traditional", "compensated"):
        m = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, method=method)
        assert m.ok and abs(_err_deg(m, rot)) < 1e-3


def test_noise_free_sunlight_is_compensated_exactly():
    # docs/model.md §12.5: eps = 0.0125, noise-free: heading error < 1e-4 deg, eps to 1e-3 relative,
    # with tilt and for both the fixed- and the free-zenith variant.
    rot = Rotation.from_euler("ZYX", [0.4, np.radians(5.0), np.radians(-3.0)])
    raw = render(CAM4, SUN_N, rot, epsilon=0.0125, rayleigh_radiance=True)
    for fixed in (True, False):
        m = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, fixed_zenith=fixed)
        assert m.ok and abs(_err_deg(m, rot)) < 1e-4
        assert m.epsilon == pytest.approx(0.0125, rel=1e-3)
    # The traditional estimator is biased by the sunlight term once the symmetry is broken.
    m = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, method="traditional")
    assert abs(_err_deg(m, rot)) > 0.005


def test_world_fixed_occluder_bias():
    # docs/model.md §12.6: occluder at compass azimuth 260-350 deg below 40 deg elevation,
    # eps = 0.0125, noise-free. The paper's (unweighted) traditional estimator shows the bias
    # of about -0.1 deg; the joint ML stays below 0.005 deg and recovers eps to 1e-3.
    for yaw_deg in (0.0, 73.0, 200.0):
        rot = _level(yaw_deg)
        raw = render(CAM4, SUN_N, rot, epsilon=0.0125, occluder_az_deg=(260.0, 350.0))
        trad = measure_baseline(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, weighted=False)
        assert -0.15 < _err_deg(trad, rot) < -0.05
        # p^2 weights alone shrink it (the biased pixels have a low DoP) but do not remove it.
        trad_w = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, method="traditional")
        assert 0.0005 < abs(_err_deg(trad_w, rot)) < 0.01
        comp = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot)
        assert abs(_err_deg(comp, rot)) < 0.005 and abs(_err_deg(comp, rot)) < 1e-6
        assert comp.epsilon == pytest.approx(0.0125, rel=1e-3)
        assert comp.n_pixels < 0.9 * trad.n_pixels + 0.1 * 25_000  # the occluder is masked


def test_tilt_handled_in_the_camera_frame():
    # docs/model.md §12.8: E-vectors built with camera-frame ray angles and then rotated are
    # exact; the paper's Eq. 28 (level-frame ray angles with the camera-frame AoP) is not.
    rot = Rotation.from_euler("ZYX", [0.4, np.radians(5.0), np.radians(-3.0)])
    raw = render(CAM4, SUN_N, rot)
    m, maps = measure_with_maps(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, method="traditional")
    assert abs(_err_deg(m, rot)) < 1e-9
    valid = maps.valid
    rays_c = pixel_rays_c(CAM4)[valid]
    stokes = np.stack(
        [np.ones(valid.sum()), np.cos(2 * maps.aop[valid]), np.sin(2 * maps.aop[valid])], -1
    )
    mat_lc = polins.frames.rot_lb_from_rot_nb(rot).as_matrix()  # camera = body here
    right = evectors_from_stokes(stokes, lens_basis(rays_c, "projection")) @ mat_lc.T
    wrong = evectors_from_stokes(stokes, lens_basis(rays_c @ mat_lc.T, "projection"))
    yaw = yaw_from_rot_nb(rot)
    err_right = np.degrees(wrap_angle(yaw_from_sun_level(sun_eigen(right).sun, SUN_N) - yaw))
    err_wrong = np.degrees(wrap_angle(yaw_from_sun_level(sun_eigen(wrong).sun, SUN_N) - yaw))
    assert abs(err_right) < 1e-9 and 0.3 < abs(err_wrong) < 5.0


# ----------------------------------------------------------------------------- conventions
def test_flipped_stokes_sign_is_90_degrees_off():
    # The paper's Eq. 14 signs (I90 - I0, I135 - I45) turn the AoP by 90 deg: E-vectors then
    # lie in the scattering plane and the heading is ~90 deg wrong.
    rot = Rotation.from_euler("ZYX", [1.0, np.radians(3.0), 0.0])
    raw = render(CAM4, SUN_N, rot)
    m, _ = measure_algorithm1(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, eq14="printed")
    assert abs(abs(_err_deg(m, rot)) - 90.0) < 5.0
    # Same with the library's own eigen solution on sign-flipped Stokes vectors.
    stokes, _ = stokes_from_channels(mosaic_channels(raw, CAM4), CAM4)
    valid = measure_with_maps(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot)[1].valid
    mat_lc = polins.frames.rot_lb_from_rot_nb(rot).as_matrix()
    basis = lens_basis(pixel_rays_c(CAM4)[valid], "projection")
    flipped = stokes[valid] * [1.0, -1.0, -1.0]
    sun_l = sun_eigen(evectors_from_stokes(flipped, basis) @ mat_lc.T).sun
    err = np.degrees(wrap_angle(yaw_from_sun_level(sun_l, SUN_N) - yaw_from_rot_nb(rot)))
    assert abs(abs(err) - 90.0) < 5.0


def test_swapped_45_135_channels_are_detected():
    # docs/model.md §3.4: a camera model with the 45 and 135 deg channels swapped mirrors the AoP. The
    # result is not a Rayleigh pattern: residual RMS >> 1 (vs ~1), the heading is wrong, and
    # residual_rms_max refuses the image.
    layout = {int(k): pos for pos, k in np.ndenumerate(CAM4.channel_at)}
    chan = CAM4.channel_at.copy()
    chan[layout[1]], chan[layout[3]] = 3, 1
    swapped = CAM4.with_changes(channel_at=chan)
    rng = np.random.default_rng(12)
    for _ in range(3):
        rot = random_attitude(rng, 10.0)
        raw = render(CAM4, SUN_N, rot, epsilon=0.0125, noise_std=1.5, rng=rng)
        good = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot)
        assert good.ok and 0.9 < good.residual_rms < 1.15
        for method in ("traditional", "compensated"):
            bad = measure(raw, swapped, sun_n=SUN_N, rot_nb_prior=rot, method=method)
            assert not bad.ok or (bad.residual_rms > 10.0 and abs(_err_deg(bad, rot)) > 5.0)
            refused = measure(
                raw, swapped, sun_n=SUN_N, rot_nb_prior=rot, method=method, residual_rms_max=3.0
            )
            assert not refused.ok


# ----------------------------------------------------------------------------- statistics
def _monte_carlo(cam, rot, n_images, seed, dtype=np.float64, **render_kw):
    base = render(cam, SUN_N, rot, **render_kw)
    rng = np.random.default_rng(seed)
    out = {"traditional": [], "compensated": []}
    for _ in range(n_images):
        raw = base + rng.normal(0.0, 1.5, base.shape)
        if dtype != np.float64:
            raw = np.clip(np.round(raw), 0, 4095).astype(dtype)
        for method, rows in out.items():
            m = measure(raw, cam, sun_n=SUN_N, rot_nb_prior=rot, method=method)
            assert m.ok, m.reason
            rows.append((_err_deg(m, rot), np.degrees(m.yaw_std_meas), m.epsilon, m.epsilon_std))
    return {k: np.array(v) for k, v in out.items()}


def _check_monte_carlo(res, crlb_deg):
    for method, rows in res.items():
        spread, predicted = rows[:, 0].std(ddof=1), rows[:, 1].mean()
        assert predicted == pytest.approx(spread, rel=0.15), method
    comp = res["compensated"]
    assert comp[:, 0].std(ddof=1) < 1.3 * crlb_deg
    assert comp[:, 3].mean() == pytest.approx(comp[:, 2].std(ddof=1), rel=0.2)  # eps sigma
    assert abs(comp[:, 2].mean() - 0.0125) < 3 * comp[:, 2].std(ddof=1) / np.sqrt(len(comp))
    assert abs(comp[:, 0].mean()) < 4 * comp[:, 0].std(ddof=1) / np.sqrt(len(comp))


def test_monte_carlo_covariance_and_crlb():
    # 150 noisy images (sigma = 1.5 DN) of a tilted camera with eps = 0.0125: the predicted
    # sigmas match the empirical spread within 15 %, the joint ML is within 1.3x the CRLB.
    rot = Rotation.from_euler("ZYX", [0.4, np.radians(5.0), np.radians(-3.0)])
    res = _monte_carlo(CAM4, rot, 150, seed=13, epsilon=0.0125)
    crlb = yaw_crlb(CAM4, SUN_N, rot, dop_max=0.75, radiance=220.0, noise_std=1.5, epsilon=0.0125)
    _check_monte_carlo(res, np.degrees(crlb))


@pytest.mark.slow
def test_monte_carlo_full_resolution():
    # 200 full-resolution uint16 images (quantised): the Monte-Carlo criteria of docs/model.md §12.
    rot = Rotation.from_euler("ZYX", [0.4, np.radians(5.0), np.radians(-3.0)])
    res = _monte_carlo(CAM, rot, 200, seed=14, dtype=np.uint16, epsilon=0.0125)
    crlb = yaw_crlb(CAM, SUN_N, rot, dop_max=0.75, radiance=220.0, noise_std=1.5, epsilon=0.0125)
    _check_monte_carlo(res, np.degrees(crlb))
    for method, rows in res.items():
        print(
            f"{method}: sd {rows[:, 0].std(ddof=1):.5f} deg, predicted {rows[:, 1].mean():.5f}"
            f" deg, mean {rows[:, 0].mean():+.5f} deg, CRLB {np.degrees(crlb):.5f} deg"
        )


@pytest.mark.slow
def test_full_resolution_occluder_and_exactness():
    for yaw_deg in (0.0, 120.0):
        rot = _level(yaw_deg)
        raw = render(CAM, SUN_N, rot, epsilon=0.0125, occluder_az_deg=(260.0, 350.0))
        trad = measure_baseline(raw, CAM, sun_n=SUN_N, rot_nb_prior=rot, weighted=False)
        comp = measure(raw, CAM, sun_n=SUN_N, rot_nb_prior=rot)
        print(
            f"yaw {yaw_deg}: traditional {_err_deg(trad, rot):+.4f} deg, compensated "
            f"{_err_deg(comp, rot):+.2e} deg, eps {comp.epsilon:.6f}"
        )
        assert -0.15 < _err_deg(trad, rot) < -0.07  # docs/model.md §12.6: about -0.11 deg
        assert abs(_err_deg(comp, rot)) < 1e-6
        assert comp.epsilon == pytest.approx(0.0125, rel=1e-4)


def test_crlb_reference_value_and_scaling():
    # docs/errata.md §5: level, full resolution, sigma = 1.5 DN, d_max 0.75, radiance 220:
    # CRLB(yaw) = 1.36e-3 deg. It scales with the noise and inversely with the radiance.
    rot = _level(22.9)
    crlb = yaw_crlb(CAM, SUN_N, rot, dop_max=0.75, radiance=220.0, noise_std=1.5)
    assert np.degrees(crlb) == pytest.approx(1.36e-3, rel=0.02)
    small = yaw_crlb(CAM4, SUN_N, rot, dop_max=0.75, radiance=220.0, noise_std=1.5)
    assert small == pytest.approx(4.0 * crlb, rel=0.03)  # 16x fewer pixels
    assert yaw_crlb(CAM4, SUN_N, rot, dop_max=0.75, radiance=440.0, noise_std=3.0) == pytest.approx(
        small, rel=1e-9
    )
    half = np.zeros(CAM4.superpixel_shape, dtype=bool)
    half[:, : half.shape[1] // 2] = True
    masked = yaw_crlb(
        CAM4, SUN_N, rot, dop_max=0.75, radiance=220.0, noise_std=1.5, pixel_mask=half
    )
    assert masked > 1.2 * small


# ----------------------------------------------------------------------------- covariance
def test_inflation_terms():
    # docs/measurement.md §12: yaw_std = sqrt(noise^2 + model^2 + (cot Z tilt)^2), with the
    # model part sqrt((2 sky)^2 + instrumental^2), the sky part the jackknife variance
    # beyond the noise.
    rot = _level(40.0)
    raw = render(CAM4, SUN_N, rot, noise_std=1.5, rng=np.random.default_rng(15))
    base = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, instrumental_dop_std=0.0)
    sky = 2.0 * np.sqrt(max(base.yaw_std_jackknife**2 - base.yaw_std_meas**2, 0.0))
    assert base.yaw_std_correlated == 0.0 and base.yaw_std_model == pytest.approx(sky, rel=1e-12)
    assert base.yaw_std_noise == base.yaw_std_meas
    assert base.yaw_std == pytest.approx(np.hypot(base.yaw_std_meas, sky), rel=1e-12)
    m = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, tilt_std=np.radians(0.1))
    zen = np.arccos(SUN_N[2])
    model = np.hypot(sky, m.yaw_std_correlated)
    assert m.yaw_std_correlated > 0 and m.yaw_std_model == pytest.approx(model, rel=1e-12)
    assert m.yaw_std_noise == m.yaw_std_meas
    expected = np.sqrt(
        m.yaw_std_noise**2 + m.yaw_std_model**2 + (np.radians(0.1) / np.tan(zen)) ** 2
    )
    assert m.yaw_std == pytest.approx(expected, rel=1e-12)
    assert m.sun_std == pytest.approx(
        np.sin(zen) * np.hypot(m.yaw_std_noise, m.yaw_std_model), rel=1e-12
    )
    assert m.yaw == base.yaw  # inflation never changes the estimate


# ----------------------------------------------------------------------------- refusals
def test_refusals_and_input_errors():
    rot = _level(10.0)
    raw = render(CAM4, SUN_N, rot)
    below = polins.sun_vector_n(1.0, np.radians(95.0))
    m = measure(raw, CAM4, sun_n=below, rot_nb_prior=rot)
    assert (
        not m.ok and "below the horizon" in m.reason and np.isnan(m.yaw) and np.isnan(m.sun_b).all()
    )
    overhead = polins.sun_vector_n(1.0, np.radians(3.0))
    assert "zenith" in measure(raw, CAM4, sun_n=overhead, rot_nb_prior=rot).reason
    # The paper's baselines and Algorithm 1 refuse the same suns as the chain.
    for sun in (below, overhead):
        for m in (
            measure_baseline(raw, CAM4, sun_n=sun, rot_nb_prior=rot, weighted=False),
            measure_algorithm1(raw, CAM4, sun_n=sun, rot_nb_prior=rot)[0],
        ):
            assert not m.ok
            assert m.reason == measure(raw, CAM4, sun_n=sun, rot_nb_prior=rot).reason
    for f in (measure_baseline, measure_algorithm1):
        with pytest.raises(UserInputError, match=f"^{f.__name__} needs sun_n and rot_nb_prior$"):
            f(raw, CAM4, sun_n=None, rot_nb_prior=rot)
        with pytest.raises(UserInputError, match=f"^{f.__name__} needs sun_n and rot_nb_prior$"):
            f(raw, CAM4, sun_n=SUN_N, rot_nb_prior=None)
    dark = np.zeros(CAM4.shape, dtype=np.uint16)
    assert "too few valid pixels" in measure(dark, CAM4, sun_n=SUN_N, rot_nb_prior=rot).reason
    gated = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=_level(40.0), yaw_gate=np.radians(5.0))
    assert not gated.ok and "gate" in gated.reason
    assert measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=_level(40.0)).ok  # prior yaw unused
    with pytest.raises(ValueError, match=r"\(512, 612\)"):
        measure(raw[:100], CAM4, sun_n=SUN_N, rot_nb_prior=rot)
    with pytest.raises(ValueError, match="dtype"):
        measure(raw.astype(np.int16), CAM4, sun_n=SUN_N, rot_nb_prior=rot)
    with pytest.raises(TypeError, match="valid options: fixed_zenith"):
        measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, fixed_zenit=False)
    # A replaced option fails with one line naming what replaces it.
    for old, new in [
        ("sun_exclusion_deg", r"sun_exclusion \[rad\]"),
        ("cloud_dop_ratio", r"clouds \('auto' or 'off'\)"),
        ("cloud_aop_z", "clouds"),
        ("sigma_floor", "yaw_std_model"),
        ("kappa", "yaw_std_model"),
        ("gain_correction", r"polins\.sim\.algorithm1\.measure_baseline"),
        ("gn_pixels", "a constant"),
    ]:
        with pytest.raises(TypeError, match=f"{old} -> [^;]*{new}") as info:
            measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, **{old: 0.1})
        assert "\n" not in str(info.value)
    # "off" is off, "auto" is automatic, None is neither.
    off = {"yaw_gate": "off", "residual_rms_max": "off", "max_field_angle": "off"}
    assert MeasureOptions(**off) == MeasureOptions()
    for name in ("yaw_gate", "residual_rms_max", "max_field_angle", "instrumental_dop_std"):
        with pytest.raises(ValueError, match=name):
            MeasureOptions(**{name: None})
    with pytest.raises(ValueError, match="clouds"):
        MeasureOptions(clouds="sometimes")
    with pytest.raises(ValueError, match="instrumental_mixing_std"):
        MeasureOptions(instrumental_mixing_std="off")
    with pytest.raises(TypeError, match="eq22"):  # a paper-only switch
        measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, method="traditional", eq22="printed")
    with pytest.raises(ValueError, match="eq22"):
        measure_algorithm1(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, eq22="as printed")
    assert measure_options(sun_exclusion=0.3) == MeasureOptions(sun_exclusion=0.3)
    # The one-time check of a stream; the paper's Algorithm 1 is a reproduction, not a method.
    assert check_measure_options("traditional", {"dop_min": 0.05}) == MeasureOptions(dop_min=0.05)
    with pytest.raises(TypeError, match="eq22"):
        check_measure_options("compensated", {"eq22": "printed"})
    with pytest.raises(ValueError, match=r"polins\.sim\.algorithm1"):
        check_measure_options("paper", {})
    with pytest.raises(ValueError, match=r"polins\.sim\.algorithm1"):
        measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, method="paper")
    with pytest.raises(ValueError, match="method"):
        check_measure_options("svd", {})
    with pytest.raises(ValueError, match="method"):
        measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, method="svd")
    with pytest.raises(ValueError, match="Rotation"):
        measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=np.eye(3))
    with pytest.raises(ValueError, match="loss"):
        MeasureOptions(loss="l1")
    d = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot).as_dict()
    assert d["ok"] is True and len(d["sun_b"]) == 3 and d["epsilon"] is not None


def test_options_are_checked_however_constructed():
    # A replaced option is named with its replacement also when MeasureOptions is built
    # directly or replaced; a boolean is not a number (False is not "off", True no 1 rad gate).
    for old, new in [("kappa", "yaw_std_model"), ("sun_exclusion_deg", r"sun_exclusion \[rad\]")]:
        with pytest.raises(TypeError, match=f"^unknown measure option.*{old} -> [^;]*{new}"):
            MeasureOptions(**{old: 1})
        with pytest.raises(TypeError, match=f"{old} -> [^;]*{new}"):
            dataclasses.replace(MeasureOptions(), **{old: 1})
    rot = _level(10.0)
    raw = render(CAM4, SUN_N, rot)
    for flag in (False, True):
        with pytest.raises(ValueError, match=f"^yaw_gate={flag}: expected a number or 'off'$"):
            measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, yaw_gate=flag)
        with pytest.raises(ValueError, match=f"^dop_min={flag}: expected a number$"):
            MeasureOptions(dop_min=flag)
    assert (
        MeasureOptions(yaw_gate=0.1).gate == 0.1
        and MeasureOptions(min_pixels=600).min_pixels == 600
    )


def test_nan_pixels_are_masked_not_propagated():
    rot = _level(-30.0)
    raw = render(CAM4, SUN_N, rot, noise_std=1.5, rng=np.random.default_rng(16))
    holed = raw.copy()
    holed[200:203, 300:340] = np.nan
    holed[10, 10] = np.inf
    a = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot)
    b = measure(holed, CAM4, sun_n=SUN_N, rot_nb_prior=rot)
    assert b.ok and np.isfinite(b.yaw_std) and b.n_pixels < a.n_pixels
    assert abs(np.degrees(b.yaw - a.yaw)) < 3 * np.degrees(a.yaw_std_meas)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_tiny_region_with_a_free_zenith_falls_back_with_a_reason(seed):
    # A 2 deg region with the zenith free leaves the score test's or the separation test's
    # Gauss-Newton step without a selected pixel (residual RMS 0), and the eigen fallback a
    # zero gap: measure returns a result (ok with a finite yaw, or a reason), without a
    # ZeroDivisionError or a RuntimeWarning.
    rng = np.random.default_rng(seed)
    rot = Rotation.from_euler(
        "ZYX", [rng.uniform(-3, 3), rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05)]
    )
    sun_n = polins.sun_vector_n(rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(12, 30)))
    raw = render(CAM4, sun_n, rot, noise_std=1.5, rng=rng, epsilon=0.01)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # and no numpy warning escapes
        m = measure(raw, CAM4, sun_n=sun_n, rot_nb_prior=rot, max_field_angle=np.radians(2.0),
                    min_pixels=10, fixed_zenith=False)  # fmt: skip
    assert (m.ok and np.isfinite(m.yaw) and np.isfinite(m.yaw_std)) or (not m.ok and m.reason)


def test_horizon_fallback_uses_the_prior():
    # Sun 3 deg above the horizon (outside the 80 deg field of view): the sign of the eigen
    # vector is chosen with the prior yaw; a prior 150 deg off picks the 180 deg twin.
    sun_n = polins.sun_vector_n(np.radians(100.0), np.radians(87.0))
    rot = _level(35.0)
    raw = render(CAM4, sun_n, rot)
    for method in ("traditional", "compensated"):
        near = measure(raw, CAM4, sun_n=sun_n, rot_nb_prior=_level(65.0), method=method)
        assert near.ok and abs(_err_deg(near, rot)) < 1e-6
        far = measure(raw, CAM4, sun_n=sun_n, rot_nb_prior=_level(185.0), method=method)
        assert far.ok and abs(abs(_err_deg(far, rot)) - 180.0) < 1e-6
        if method == "compensated":
            # With the zenith fixed (+3 deg), the twin (A + 180 deg) is a sun mirrored to -3 deg:
            # the joint ML can only fit it with an unphysical epsilon, runs into its bound and
            # falls back to the (weighted) eigen solution, whose twin is exact.
            assert near.method == "compensated" and near.reason == ""
            assert far.method == "traditional" and "epsilon 0.1 at its bound" in far.reason


# ----------------------------------------------------------------------------- CLI
def _small_camera_file(tmp_path):
    """The paper camera at 1/4 resolution as a model file (for a fast CLI run)."""
    k = CAM4.camera_matrix
    text = CAM.path.read_text()
    for old, new in [
        ("width_px = 2448", "width_px = 612"),
        ("height_px = 2048", "height_px = 512"),
        ("fx_superpixel = 259.10", f"fx_superpixel = {float(k[0, 0])!r}"),
        ("fy_superpixel = 259.20", f"fy_superpixel = {float(k[1, 1])!r}"),
        ("cx_superpixel = 622.49", f"cx_superpixel = {float(k[0, 2])!r}"),
        ("cy_superpixel = 515.06", f"cy_superpixel = {float(k[1, 2])!r}"),
    ]:
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "small.toml"
    path.write_text(text)
    return path


def test_cli_heading(tmp_path, capsys):
    import json

    import cv2

    from polins.cli import main

    cam_path = _small_camera_file(tmp_path)
    cam = polins.load_camera(cam_path)
    time, lat, lon = "2023-09-05T15:06+08:00", "45.6234", "126.7264"
    sun = polins.sun_position(time, float(lat), float(lon))
    sun_n = polins.sun_vector_n(sun.azimuth, sun.zenith)
    heading, roll, pitch = 123.4, 2.0, -1.5
    rot = polins.rot_nb_from_euler(
        polins.yaw_from_heading_deg(heading), np.radians(pitch), np.radians(roll)
    )
    raw = render(cam, sun_n, rot, radiance=2000.0, dtype=np.uint16)
    png = tmp_path / "sky.png"
    assert cv2.imwrite(str(png), raw)
    args = ["heading", str(png), "--camera", str(cam_path), "--time", time, "--lat", lat]
    args += ["--lon", lon, "--roll", str(roll), "--pitch", str(pitch)]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "heading" in out and "sigma" in out
    printed = float(out.split("heading")[1].split()[0])
    assert printed == pytest.approx(heading, abs=0.01)
    report_file = tmp_path / "m.json"
    assert main([*args, "--json", "--out", str(report_file), "--method", "traditional"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] and report["heading_deg"] == pytest.approx(heading, abs=0.01)
    assert report["method"] == "traditional" and report["heading_std_deg"] > 0
    assert json.loads(report_file.read_text()) == report
    # Night: a refusal (exit 1), not an error.
    night = [*args[:5], "2023-09-05T23:00+08:00", *args[6:]]
    assert main(night) == 1 and "no heading" in capsys.readouterr().out
    # Without a clock and a site: the sun in the body frame, at the truth's body azimuth
    sun_b = rot.inv().apply(sun_n)
    no_site = ["heading", str(png), "--camera", str(cam_path), "--roll", str(roll),
               "--pitch", str(pitch), "--json"]  # fmt: skip
    assert main(no_site) in (0, 1)
    report = json.loads(capsys.readouterr().out)
    assert report["heading_deg"] is None or np.isnan(report["heading_deg"])  # no clock: no heading
    err = np.degrees(np.angle(np.exp(1j * (np.radians(report["sun_azimuth_b_deg"])
                                           - np.arctan2(sun_b[1], sun_b[0])))))  # fmt: skip
    assert min(abs(err), 180.0 - abs(err)) < 0.2  # the sun's body azimuth, branch aside
    # a site given by halves is one line and exit 2
    assert main([*no_site, "--lat", lat]) == 2
    assert "go together" in capsys.readouterr().err


def test_cli_heading_user_errors(tmp_path, capsys):
    import cv2

    from polins.cli import main

    site = ["--time", "2023-09-05T15:06+08:00", "--lat", "45.6", "--lon", "126.7"]
    assert main(["heading", str(tmp_path / "missing.png"), *site]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "not found" in err
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 120), np.uint16))
    assert main(["heading", str(small), *site]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "(2048, 2448)" in err and "Traceback" not in err
    text = tmp_path / "notes.png"
    text.write_text("not an image")
    assert main(["heading", str(text), *site]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "notes.png" in err and "Traceback" not in err
    # The paper's Algorithm 1 is no method of any command: the same one line as in Python.
    for command in ("heading", "fuse", "tune"):
        assert main([command, "--method", "paper"]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "polins.sim.algorithm1" in err


# ----------------------------------------------------------------------------- cross-check
def test_cross_check_with_the_library_renderer():
    # polins.sim.render_raw (written independently) and tests/render_simple.py agree on the
    # sky inside the field of view, and measure() reads render_raw's images.
    from polins.sim import render_raw

    rot = Rotation.from_euler("ZYX", [2.0, np.radians(4.0), np.radians(6.0)])
    kw = {"dop_max": 0.6, "radiance": 300.0, "epsilon": 0.0125}
    mine = render(CAM4, SUN_N, rot, **kw)
    theirs = render_raw(CAM4, SUN_N, rot, **kw, quantize=False, sun_disc_deg=0.0)
    fov = np.repeat(np.repeat(np.asarray(polins.compass.camera.fov_mask(CAM4)), 2, 0), 2, 1)
    np.testing.assert_allclose(theirs[fov], mine[fov], rtol=1e-9)
    raw = render_raw(CAM4, SUN_N, rot, **kw, rng=np.random.default_rng(17))
    m = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot)
    assert m.ok and abs(_err_deg(m, rot)) < 4 * np.degrees(m.yaw_std_meas)
    assert m.epsilon == pytest.approx(0.0125, abs=4 * m.epsilon_std)


def test_pinhole_camera_both_lens_models(tmp_path):
    # A narrow-field pinhole camera (OpenCV distortion model), 40 deg field of view, rendered
    # by polins.sim.render_raw: noise-free headings are exact with either lens model.
    from polins.sim import render_raw

    text = CAM.path.read_text()
    for old, new in [
        ('projection = "kannala-brandt"', 'projection = "pinhole"'),
        ("[0.029274, -0.013300, 0.009758, -0.004919]", "[-0.2, 0.05, 0.001, -0.0005, 0.01]"),
        ("fov_max_deg = 80.0", "fov_max_deg = 40.0"),
        ("fx_superpixel = 259.10", "fx_superpixel = 900.0"),
        ("fy_superpixel = 259.20", "fy_superpixel = 900.0"),
    ]:
        text = text.replace(old, new)
    (tmp_path / "pin.toml").write_text(text)
    cam = polins.load_camera(tmp_path / "pin.toml").downscaled(4)
    rot = Rotation.from_euler("ZYX", [0.3, 0.05, -0.02])
    for model in ("projection", "meridian"):
        c = cam.with_changes(polarization_model=model)
        raw = render_raw(c, SUN_N, rot, quantize=False, epsilon=0.0125)
        for method in ("traditional", "compensated"):
            m = measure(raw, c, sun_n=SUN_N, rot_nb_prior=rot, method=method)
            assert m.ok and m.n_pixels > 50_000
            if method == "compensated":
                assert abs(_err_deg(m, rot)) < 1e-6 and m.epsilon == pytest.approx(0.0125, rel=1e-3)


# ----------------------------------------------------------------------------- sun-vector API
@pytest.mark.parametrize("model", ["projection", "meridian"])
def test_public_sun_vector_functions(model):
    from polins.compass.camera import doubled_aop_from_evector, evector_from_aop
    from polins.compass.eigen import eigen_gap, eigen_sun_covariance
    from polins.compass.heading import sun_level_from_angles, yaw_variance_from_sun_covariance
    from polins.compass.jointml import sun_joint_ml
    from polins.compass.lens import lens_forward
    from polins.compass.residual import ml_residuals
    from polins.compass.sunlight import stokes_with_sunlight, sunlight_direction

    rng = np.random.default_rng(18)
    theta = np.arccos(rng.uniform(np.cos(np.radians(80)), 1.0, 20_000))
    phi = rng.uniform(-np.pi, np.pi, 20_000)
    rays = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    # Lens constants agree with polins.compass.camera's lens models.
    zeta = rng.uniform(-np.pi / 2, np.pi / 2, 20_000)
    e_cam = evector_from_aop(zeta, rays, model)
    e_lib = evectors_from_stokes(
        np.stack([np.ones_like(zeta), np.cos(2 * zeta), np.sin(2 * zeta)], -1),
        lens_basis(rays, model),
    )
    np.testing.assert_allclose(np.abs(np.sum(e_cam * e_lib, -1)), 1.0, atol=1e-12)
    mat_cl = Rotation.from_euler("xy", [0.05, -0.08]).as_matrix()  # level -> camera
    sun_l = sun_level_from_angles(0.7, np.radians(55.0))
    sun_c = mat_cl @ sun_l
    forward = lens_forward(rays, model)
    xy = forward @ sun_c
    c2s2 = doubled_aop_from_evector(np.cross(sun_c, rays), rays, model)
    np.testing.assert_allclose(
        np.stack([xy[:, 0] ** 2 - xy[:, 1] ** 2, 2 * xy[:, 0] * xy[:, 1]], -1)
        / np.sum(xy**2, -1, keepdims=True),
        c2s2,
        atol=1e-12,
    )
    # A noisy Rayleigh field with sunlight: the joint ML recovers sun and eps, the residuals
    # at the truth are the noise, and the covariances are consistent.
    keep = rays @ sun_c < np.cos(np.radians(10))
    rays, forward, c2s2 = rays[keep], forward[keep], c2s2[keep]
    p = 200 * 0.6 * (1 - (rays @ sun_c) ** 2) / (1 + (rays @ sun_c) ** 2)
    sky = np.concatenate([np.full((len(p), 1), 200.0), p[:, None] * c2s2], -1)
    stokes = stokes_with_sunlight(sky, 0.0125, sunlight_direction(sun_c))
    stokes[:, 1:] += rng.normal(0, 2.0, (len(p), 2))
    r = ml_residuals(stokes, forward, mat_cl, sun_l, 0.0125, sigma_l=2.0)
    assert r.std() == pytest.approx(1.0, rel=0.03) and abs(r.mean()) < 0.05
    start = sun_level_from_angles(0.75, np.radians(50.0))
    sol = sun_joint_ml(stokes, forward, mat_cl, start, sigma_l=2.0)
    assert sol.converged and sol.residual_rms == pytest.approx(1.0, rel=0.03)
    assert abs(sol.theta[0] - 0.7) < 5 * np.sqrt(sol.covariance[0, 0])
    assert abs(sol.theta[2] - 0.0125) < 5 * np.sqrt(sol.covariance[2, 2])
    # Convergence from far starts (bounded steps, line search): 34-35 deg off, eps0 0.3.
    for a0, z0 in [(1.3, 40.0), (0.1, 60.0)]:
        far = sun_joint_ml(stokes, forward, mat_cl, sun_level_from_angles(a0, np.radians(z0)),
                           epsilon0=0.3, sigma_l=2.0, max_iterations=40)  # fmt: skip
        assert far.converged and np.allclose(far.theta, sol.theta, atol=1e-6)
    # From random starts (any azimuth, zenith 0-87 deg, eps0 within +-0.1), zenith free and
    # fixed: the coarse grid start and the bounded steps reach the same solution (without the
    # grid: 49 of 80 such starts ended elsewhere, e.g. eps -0.3 with the sun 70 deg off).
    for _ in range(10):
        a0, z0 = rng.uniform(-np.pi, np.pi), np.arccos(rng.uniform(0.05, 1.0))
        for zen, ref in ((None, sol), (np.radians(55.0), None)):
            got = sun_joint_ml(stokes, forward, mat_cl, sun_level_from_angles(a0, z0),
                               epsilon0=rng.uniform(-0.1, 0.1), sigma_l=2.0, zenith=zen,
                               max_iterations=40)  # fmt: skip
            assert got.converged and abs(float(wrap_angle(got.theta[0] - 0.7))) < 1e-3
            assert abs(got.theta[-1] - 0.0125) < 5 * np.sqrt(got.covariance[-1, -1])
            if ref is not None:
                assert np.allclose(got.theta, ref.theta, atol=1e-6)
    fixed = sun_joint_ml(stokes, forward, mat_cl, start, sigma_l=2.0, zenith=np.radians(55.0))
    # (each at its own optimum, so to the 1e-5 the sunlight terms of the Jacobian move it)
    assert fixed.covariance.shape == (2, 2)
    assert fixed.covariance[0, 0] <= sol.covariance[0, 0] * (1 + 1e-4)
    # Weighted eigen solution and its sandwich covariance in the level frame.
    e_l = evectors_from_stokes(stokes, lens_basis(rays, model)) @ mat_cl
    weights = np.sum(stokes[:, 1:] ** 2, -1)
    eig = sun_eigen(e_l, weights)
    assert eigen_gap(eig) > 0.9 and eig.sun[2] > 0
    var = yaw_variance_from_sun_covariance(eig.sun, eigen_sun_covariance(e_l, weights, eig))
    assert 0.5 < np.sqrt(var) / np.sqrt(sol.covariance[0, 0]) < 3.0


def test_the_camera_file_states_its_calibration_residual(tmp_path):
    # [polarizer] instrumental_dop_std in the camera file is the measurement's default for
    # the camera-fixed part; an explicit option still wins; the key and the [roi] table
    # survive a write/read of the file.
    import dataclasses

    from polins.io.model_files import write_camera_file

    rot = _level(40.0)
    raw = render(CAM4, SUN_N, rot, noise_std=1.5, rng=np.random.default_rng(16))
    exact = dataclasses.replace(CAM4, instrumental_dop_std=0.0)
    default = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot)
    stated = measure(raw, exact, sun_n=SUN_N, rot_nb_prior=rot)
    assert default.yaw_std_correlated > 0.0 and stated.yaw_std_correlated == 0.0
    assert stated.yaw_std < default.yaw_std
    explicit = measure(raw, exact, sun_n=SUN_N, rot_nb_prior=rot, instrumental_dop_std=0.002)
    assert explicit.yaw_std_correlated == pytest.approx(default.yaw_std_correlated, rel=1e-12)
    roi = dataclasses.replace(exact, roi_max_field_angle=np.radians(50.0),
                              roi_polygons=(np.array([[1.0, 2.0], [30.0, 2.0], [30.0, 40.0]]),))  # fmt: skip
    write_camera_file(roi, tmp_path / "cam.toml")
    back = polins.load_camera(tmp_path / "cam.toml")
    assert back.instrumental_dop_std == 0.0
    assert back.roi_max_field_angle == pytest.approx(np.radians(50.0))
    np.testing.assert_allclose(back.roi_polygons[0], roi.roi_polygons[0], atol=1e-12)


# ----------------------------------------------------------------------------- stages
def test_stages_compose_to_measure():
    # The chain is its stages (docs/measurement.md §0): composing them by hand gives the
    # same measurement to the last bit, each stage's result is a frozen dataclass, and a
    # stage that refuses says why.
    import dataclasses

    from polins.compass.chain import heading_measurement, instrumental_std, sun_branch
    from polins.compass.heading import image_geometry
    from polins.compass.image import image_stokes
    from polins.compass.pixels import check_raw
    from polins.compass.skypixels import sky_pixels
    from polins.compass.solution import solve_image

    rng = np.random.default_rng(21)
    rot = random_attitude(rng, 5.0)
    raw = render(CAM4, SUN_N, rot, epsilon=0.01, noise_std=1.5, rng=rng, dtype=np.uint16)
    opt = MeasureOptions(tilt_std=np.radians(0.1))
    for method in ("compensated", "traditional"):
        geo = image_geometry(CAM4, SUN_N, rot)
        img = image_stokes(check_raw(raw, CAM4), CAM4, opt)
        px = sky_pixels(img, CAM4, geo, opt)
        sol = solve_image(img, CAM4, px, geo, opt, method)
        n_pixels = int(np.count_nonzero(sol.mask))
        branch = sun_branch(img, px, sol, geo, opt, n_pixels)
        std_instr = instrumental_std(img, CAM4, px, sol, geo, opt)
        fixed = method == "compensated"
        by_hand = heading_measurement(sol, branch, geo, opt, n_pixels, fixed, std_instr)
        m = measure(raw, CAM4, sun_n=SUN_N, rot_nb_prior=rot, method=method, tilt_std=opt.tilt_std)
        assert m.ok and m.method == method and by_hand.method == method
        for f in ("yaw", "yaw_std", "sun_std", "epsilon", "residual_rms", "yaw_std_correlated"):
            assert getattr(by_hand, f) == getattr(m, f) or np.isnan(getattr(m, f)), f
        for stage in (geo, img, px, sol, branch):
            assert dataclasses.is_dataclass(stage)
            with pytest.raises(dataclasses.FrozenInstanceError):
                stage.__setattr__(dataclasses.fields(stage)[0].name, None)
    # A stage leaves its inputs alone: a second run on the same stages gives the same result.
    opt = MeasureOptions(max_field_angle=0.5)
    geo = image_geometry(CAM4, SUN_N, rot)
    img = image_stokes(check_raw(raw, CAM4), CAM4, opt)
    img_copy = {f.name: np.copy(getattr(img, f.name)) for f in dataclasses.fields(img)
                if isinstance(getattr(img, f.name), np.ndarray)}  # fmt: skip
    px = sky_pixels(img, CAM4, geo, opt)
    valid_full = px.select_full.valid.copy()
    sol = solve_image(img, CAM4, px, geo, opt, "compensated")
    for name, value in img_copy.items():
        np.testing.assert_array_equal(getattr(img, name), value, err_msg=name)
    np.testing.assert_array_equal(px.select_full.valid, valid_full)
    assert np.count_nonzero(px.valid) < np.count_nonzero(img.valid)
    px2 = sky_pixels(img, CAM4, geo, opt)
    np.testing.assert_array_equal(px2.valid, px.valid)
    assert solve_image(img, CAM4, px2, geo, opt, "compensated").var_yaw == sol.var_yaw
    dark = np.zeros_like(raw)
    refused = measure(dark, CAM4, sun_n=SUN_N, rot_nb_prior=rot)
    assert not refused.ok and refused.reason.startswith("too few valid pixels")


@pytest.mark.parametrize("tilt_deg", [0.0, 6.0, 15.0])
def test_horizon_cut_of_the_used_pixels(tilt_deg):
    """A used pixel is at least HORIZON_MIN above the prior's level horizon: the 80 deg
    fisheye level or tilted 6 deg lies wholly above it (the per-pixel test is skipped),
    tilted 15 deg it does not; either way the mask is the per-pixel rule's."""
    from polins.compass.heading import image_geometry
    from polins.compass.image import image_stokes
    from polins.compass.measurement import measure_options
    from polins.compass.skypixels import HORIZON_MIN, sky_pixels

    rot = Rotation.from_euler("ZYX", [0.3, np.radians(tilt_deg), 0.0])
    raw = render(CAM4, SUN_N, rot, noise_std=1.5, rng=np.random.default_rng(4), dtype=np.uint16)
    opt = measure_options(clouds="off")
    geo = image_geometry(CAM4, SUN_N, rot, None)
    img = image_stokes(raw, CAM4, opt)
    px = sky_pixels(img, CAM4, geo, opt)
    up = geo.mat_cl[:, 2] @ img.cache.rays.astype(np.float64)
    want = img.valid & (up >= np.sin(HORIZON_MIN))
    np.testing.assert_array_equal(px.valid, want)
    below = np.count_nonzero(img.valid & (up < np.sin(HORIZON_MIN)))
    assert (below > 1000) == (tilt_deg > 10.0)


def test_separability_stop_changes_nothing_but_the_time(tmp_path, monkeypatch):
    """A narrow pinhole (+-14 x +-12 deg) with the sun 5 deg above the horizon: the joint ML
    is not separable, its fit stops at the first linearization (SEPARABILITY_STOP) and
    falls back; without the stop it iterates and falls back to the same measurement."""
    import polins.compass.solve as solve
    from polins.sim import render_raw

    text = CAM.path.read_text()
    for old, new in [
        ('projection = "kannala-brandt"', 'projection = "pinhole"'),
        ("[0.029274, -0.013300, 0.009758, -0.004919]", "[0.0, 0.0, 0.0, 0.0, 0.0]"),
        ("fov_max_deg = 80.0", "fov_max_deg = 40.0"),
        ("fx_superpixel = 259.10", "fx_superpixel = 2500.0"),
        ("fy_superpixel = 259.20", "fy_superpixel = 2500.0"),
    ]:
        text = text.replace(old, new)
    (tmp_path / "narrow.toml").write_text(text)
    cam = polins.load_camera(tmp_path / "narrow.toml").downscaled(4)
    sun_n = polins.sun_vector_n(np.radians(200.0), np.radians(85.0))
    rot = Rotation.from_euler("ZYX", [0.3, 0.02, -0.01])
    raw = render_raw(cam, sun_n, rot, noise_std=1.5, rng=np.random.default_rng(1), epsilon=0.01)
    stopped = measure(raw, cam)
    monkeypatch.setattr(solve, "SEPARABILITY_STOP", 1.0)
    iterated = measure(raw, cam)
    corr = [float(m.reason.split("corr ")[1].split(")")[0]) for m in (stopped, iterated)]
    assert corr[0] > solve.SEPARABILITY_MAX + 0.01 and corr[1] > solve.SEPARABILITY_MAX
    for m in (stopped, iterated):
        assert m.ok and m.method == "traditional" and "not separable" in m.reason
    assert stopped.sun_azimuth_b == iterated.sun_azimuth_b
    assert stopped.sun_azimuth_b_std == iterated.sun_azimuth_b_std
    assert stopped.n_pixels == iterated.n_pixels
