"""Sun-free measurement (no ephemeris), its 180 deg branch, the robust compensated estimator
and the hygiene of ``polins.measure`` (docs/measurement.md §11), on images of
``polins.sim.render_raw``."""

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import polins
from polins.compass.camera import pixel_rays_c
from polins.compass.measure import NoiseModelWarning, measure
from polins.frames import wrap_angle
from polins.sim import render_raw

CAM = polins.load_camera("paper-table1")
CAM8 = CAM.downscaled(8)


def _truth_azimuth_b(sun_n, rot):
    s = rot.inv().apply(sun_n)
    return float(np.arctan2(s[1], s[0]))


def _random_case(rng, elevation_deg=(20.0, 70.0), tilt_deg=5.0):
    sun_n = polins.sun_vector_n(
        rng.uniform(0, 2 * np.pi), np.radians(90 - rng.uniform(*elevation_deg))
    )
    tilt = np.radians(rng.uniform(-tilt_deg, tilt_deg, 2))
    rot = Rotation.from_euler("ZYX", [rng.uniform(-np.pi, np.pi), *tilt])
    return sun_n, rot


def narrow_camera(tmp_path, half_fov_deg=26.0, factor=4):
    """The paper camera with a pinhole lens looking up (horizontal half field ``half_fov_deg``,
    the vertical one 22 deg at 26), at ``1/factor`` resolution (also the camera of
    tests/test_zenith.py and tests/test_calibration_narrow.py)."""
    fx = 612.0 / np.tan(np.radians(half_fov_deg))  # superpixel image 1224 wide
    text = CAM.path.read_text()
    for old, new in [
        ('projection = "kannala-brandt"', 'projection = "pinhole"'),
        ("[0.029274, -0.013300, 0.009758, -0.004919]", "[0.0, 0.0, 0.0, 0.0, 0.0]"),
        ("fov_max_deg = 80.0", "fov_max_deg = 40.0"),
        ("fx_superpixel = 259.10", f"fx_superpixel = {fx:.1f}"),
        ("fy_superpixel = 259.20", f"fy_superpixel = {fx:.1f}"),
    ]:
        assert old in text
        text = text.replace(old, new)
    (tmp_path / "narrow.toml").write_text(text)
    return polins.load_camera(tmp_path / "narrow.toml").downscaled(factor)


def _clear_sky(cam, sun_n, rot, rng, noise_std=1.5):
    """A clear sky brighter towards the sun: render_raw's sky times the CIE standard clear-sky
    relative luminance (ISO 15469 type 12) per superpixel, then read noise."""
    raw = render_raw(cam, sun_n, rot, rng=None, quantize=False)
    rays_n = pixel_rays_c(cam) @ (rot.as_matrix() @ cam.mat_bc).T
    cos_z = rays_n[..., 2]
    chi = np.arccos(np.clip(rays_n @ sun_n, -1.0, 1.0))
    sky = np.isfinite(cos_z) & (cos_z > 0.02)
    gradation = 1.0 - np.exp(-0.32 / np.where(sky, cos_z, 1.0))
    indicatrix = 1.0 + 10.0 * (np.exp(-3.0 * chi) - np.exp(-1.5 * np.pi)) + 0.45 * np.cos(chi) ** 2
    factor = np.where(sky, gradation * indicatrix, np.nan)
    factor = np.nan_to_num(factor / np.nanmean(factor), nan=1.0)
    dark = float(np.mean(cam.dark_offset_dn))
    raw = dark + (raw - dark) * np.kron(factor, np.ones((2, 2)))
    return raw + rng.normal(0.0, noise_std, raw.shape)


# ----------------------------------------------------------------------------- azimuth
@pytest.mark.parametrize("method", ["compensated", "traditional"])
def test_sun_azimuth_matches_the_truth_within_its_sigma(method):
    rng = np.random.default_rng(151)
    z = []
    for _ in range(24):
        sun_n, rot = _random_case(rng)
        raw = render_raw(CAM8, sun_n, rot, epsilon=0.0125 if method == "compensated" else 0.0,
                         rng=rng)  # fmt: skip
        m = measure(raw, CAM8, method=method, rot_nb_prior=rot, instrumental_dop_std=0.0)
        assert m.ok and m.reason == "" and m.method == method and m.sun_branch == "elevation"
        assert np.isnan(m.yaw) and np.isnan(m.heading_deg) and np.isnan(m.yaw_std)
        assert m.sun_azimuth_b == pytest.approx(np.arctan2(m.sun_b[1], m.sun_b[0]), abs=1e-12)
        true_b = rot.inv().apply(sun_n)
        assert np.isfinite(m.sun_elevation_b)
        assert abs(m.sun_elevation_b - np.arcsin(true_b[2])) < 5 * m.sun_elevation_b_std + 1e-4
        z.append(
            float(wrap_angle(m.sun_azimuth_b - _truth_azimuth_b(sun_n, rot))) / m.sun_azimuth_b_std
        )
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.5 <= rms <= 1.5, rms
    assert max(np.abs(z)) < 4.0


def test_with_sun_n_the_body_azimuth_is_consistent_with_the_yaw():
    rng = np.random.default_rng(3)
    sun_n, rot = _random_case(rng)
    raw = render_raw(CAM8, sun_n, rot, rng=rng)
    m = measure(raw, CAM8, sun_n=sun_n, rot_nb_prior=rot)
    free = measure(raw, CAM8, rot_nb_prior=rot)
    assert m.ok and m.sun_branch == "elevation"
    assert m.sun_azimuth_b == pytest.approx(np.arctan2(m.sun_b[1], m.sun_b[0]), abs=1e-12)
    # The heading error and the body-frame azimuth error are one error (level camera: equal).
    err_az = float(wrap_angle(m.sun_azimuth_b - _truth_azimuth_b(sun_n, rot)))
    assert abs(err_az) < 4 * m.sun_azimuth_b_std
    assert abs(float(wrap_angle(free.sun_azimuth_b - m.sun_azimuth_b))) < 3 * m.sun_azimuth_b_std
    assert m.sun_elevation_b == pytest.approx(np.arcsin(m.sun_b[2]))
    assert np.isnan(m.sun_elevation_b_std)  # fixed zenith: from the ephemeris


# ----------------------------------------------------------------------------- branch
def test_brightness_chooses_the_branch_on_clear_skies():
    # The elevation is not allowed to decide (horizon_fallback 89 deg): the sky's brightness
    # alone picks the sun over the antisun, for suns 20-70 deg high and tilts up to 5 deg.
    rng = np.random.default_rng(7)
    for _ in range(12):
        sun_n, rot = _random_case(rng)
        raw = _clear_sky(CAM8, sun_n, rot, rng)
        m = measure(raw, CAM8, rot_nb_prior=rot, horizon_fallback=np.radians(89.0))
        assert m.ok and m.sun_branch == "brightness", m.reason
        assert abs(float(wrap_angle(m.sun_azimuth_b - _truth_azimuth_b(sun_n, rot)))) < 0.01


def test_prior_decides_when_the_brightness_is_inconclusive():
    # render_raw's constant-radiance sky is as bright towards the antisun as towards the sun.
    rng = np.random.default_rng(8)
    sun_n, rot = _random_case(rng)
    raw = render_raw(CAM8, sun_n, rot, rng=rng)
    truth = _truth_azimuth_b(sun_n, rot)
    opts = {"rot_nb_prior": rot, "horizon_fallback": np.radians(89.0)}
    near = measure(raw, CAM8, sun_azimuth_b_prior=truth + 1.0, **opts)
    assert near.ok and near.sun_branch == "prior" and near.reason == ""
    assert abs(float(wrap_angle(near.sun_azimuth_b - truth))) < 0.01
    far = measure(raw, CAM8, sun_azimuth_b_prior=truth + np.pi - 1.0, **opts)
    assert far.sun_branch == "prior"
    assert abs(abs(float(wrap_angle(far.sun_azimuth_b - truth))) - np.pi) < 0.01
    amb = measure(raw, CAM8, **opts)
    assert amb.ok and amb.sun_branch == "ambiguous" and "ambiguous: 180 deg" in amb.reason
    alt = float(wrap_angle(amb.sun_azimuth_b_alt - amb.sun_azimuth_b))
    assert abs(abs(alt) - np.pi) < 1e-9
    assert (
        min(abs(float(wrap_angle(a - truth))) for a in (amb.sun_azimuth_b, amb.sun_azimuth_b_alt))
        < 0.01
    )
    with pytest.raises(ValueError, match="sun_azimuth_b_prior"):
        measure(raw, CAM8, sun_azimuth_b_prior=float("nan"))
    with pytest.raises(ValueError, match=r"polins\.sim\.algorithm1"):
        measure(raw, CAM8, method="paper")


def test_narrow_field_at_the_horizon_falls_back_and_brightness_resolves(tmp_path):
    # A pinhole with a 30 deg field of view looks at the zenith, the sun 2 deg above the
    # horizon: epsilon and the zenith cannot be told apart, the compensated estimate falls
    # back to weighted traditional and says why; the elevation cannot choose the branch, the
    # brightness of the clear sky does.
    cam = narrow_camera(tmp_path, 15.0)
    rng = np.random.default_rng(9)
    sun_n = polins.sun_vector_n(np.radians(200.0), np.radians(88.0))
    rot = Rotation.from_euler("ZYX", [0.4, 0.01, -0.02])
    raw = _clear_sky(cam, sun_n, rot, rng)
    m = measure(raw, cam)
    assert m.ok and m.method == "traditional" and np.isnan(m.epsilon)
    assert m.reason.startswith("compensated -> traditional: epsilon and zenith not separable")
    assert m.sun_branch == "brightness" and m.sun_elevation_b < np.radians(5.0)
    assert abs(float(wrap_angle(m.sun_azimuth_b - _truth_azimuth_b(sun_n, rot)))) < 0.01
    with_sun = measure(raw, cam, sun_n=sun_n, rot_nb_prior=rot, fixed_zenith=False)
    assert with_sun.ok and with_sun.method == "traditional" and "not separable" in with_sun.reason


# ----------------------------------------------------------------------------- robust ML
def test_compensated_never_accepts_an_unphysical_epsilon(tmp_path):
    rng = np.random.default_rng(10)
    narrow = narrow_camera(tmp_path, 15.0)
    for cam in (CAM8, narrow):
        for elevation, epsilon0 in [(2.0, 0.0), (30.0, 5.0), (60.0, -3.0), (10.0, 0.09)]:
            sun_n = polins.sun_vector_n(rng.uniform(0, 2 * np.pi), np.radians(90 - elevation))
            rot = Rotation.from_euler("ZYX", [rng.uniform(-3, 3), 0.02, -0.01])
            raw = render_raw(cam, sun_n, rot, rng=rng)
            for kw in ({}, {"sun_n": sun_n, "rot_nb_prior": rot}):
                m = measure(raw, cam, epsilon0=epsilon0, **kw)
                assert m.ok, m.reason  # from any start: a compensated estimate or the fallback
                if m.method == "compensated":
                    assert abs(m.epsilon) < 0.1 and m.epsilon == pytest.approx(0.0125, abs=0.02)
                else:
                    assert m.reason.startswith("compensated -> traditional: ")
    with pytest.raises(TypeError, match="separability_max -> a constant"):
        measure(raw, CAM8, separability_max=1.5)


# ----------------------------------------------------------------------------- hygiene
def test_no_numpy_warnings_escape_measure():
    rng = np.random.default_rng(11)
    sun_n, rot = _random_case(rng)
    raw = render_raw(CAM8, sun_n, rot, rng=rng)
    top = np.iinfo(raw.dtype).max
    half_saturated = raw.copy()
    half_saturated[: raw.shape[0] // 2] = top
    overhead = polins.sun_vector_n(0.3, np.radians(1.0))
    tiny = CAM8.with_changes(fov_max=np.radians(3.0))
    cases = [
        (np.full(CAM8.shape, top, raw.dtype), CAM8, {}),
        (half_saturated, CAM8, {}),
        (np.zeros(CAM8.shape, raw.dtype), CAM8, {}),
        (np.full(CAM8.shape, np.nan), CAM8, {}),
        (raw, tiny, {}),
        (raw, tiny, {"min_pixels": 3}),
        (raw, tiny, {"min_pixels": 3, "sun_n": sun_n, "rot_nb_prior": rot}),
        (render_raw(CAM8, overhead, rot, rng=rng), CAM8, {}),
        (render_raw(CAM8, overhead, rot, rng=rng), CAM8, {"sun_n": overhead, "rot_nb_prior": rot}),
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for image, cam, kw in cases:
            for method in ("compensated", "traditional"):
                m = measure(image, cam, method=method, **kw)
                assert m.ok or m.reason


def test_noise_ratio_and_its_warning():
    rng = np.random.default_rng(12)
    sun_n, rot = _random_case(rng)
    declared = CAM8.read_noise_dn
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = measure(render_raw(CAM8, sun_n, rot, noise_std=declared, rng=rng), CAM8)
    assert m.noise_ratio == pytest.approx(1.0, abs=0.1)
    noisy = render_raw(CAM8, sun_n, rot, noise_std=3.0 * declared, rng=rng)
    with pytest.warns(NoiseModelWarning, match=r"measured noise is \d\.\d\d x the camera file"):
        m = measure(noisy, CAM8)
    assert m.ok and m.noise_ratio == pytest.approx(3.0, rel=0.15)
