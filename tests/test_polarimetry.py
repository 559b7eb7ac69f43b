"""Polarimetry: mosaic -> channels -> calibrated Stokes, quality masks, sunlight compensation,
the paper's Algorithm 1 (docs/model.md §6.2, 7, 8)."""

import numpy as np
import pytest
from render_simple import render
from scipy.spatial.transform import Rotation

import polins
from polins.compass.pixels import check_raw, gather_channels, mosaic_channels, pixel_set
from polins.compass.polarimetry import (
    aop,
    dop,
    polarizer_rotation_slope,
    relative_gradient,
    stokes_calibration,
    stokes_from_channels,
    stokes_image,
    stokes_noise_variance,
    stokes_rows,
    unpolarized_intensity,
    validity_mask,
    validity_rows,
)
from polins.compass.sunlight import stokes_compensated, stokes_with_sunlight, sunlight_direction
from polins.sim.algorithm1 import paper_algorithm1

CAM = polins.load_camera("paper-table1")
SMALL = CAM.downscaled(8)
SUN_N = polins.sun_vector_n(np.radians(247.11), np.radians(60.21))


def _sensor(stokes, cam, offset=True):
    """docs/model.md §6.2 channel model, written out: I_k = g_k/2 [S0 + eta_k (S1 cos2a + S2 sin2a)] + o_k."""
    two_a = 2 * cam.transmission_angle
    s0, s1, s2 = (stokes[..., i, None] for i in range(3))
    i = 0.5 * cam.gain * (s0 + cam.efficiency * (s1 * np.cos(two_a) + s2 * np.sin(two_a)))
    return i + (cam.dark_offset_dn if offset else 0.0)


def _odd_camera():
    """A non-ideal calibration: unequal gains, efficiencies, angle errors, dark offsets."""
    return CAM.with_changes(
        gain=np.array([1.03, 0.98, 1.05, 1.01]),
        efficiency=np.array([0.97, 0.99, 0.95, 0.98]),
        transmission_angle=np.radians([0.7, 44.2, 90.9, 135.4]),
        dark_offset_dn=np.array([12.0, 11.0, 13.5, 12.5]),
    )


def test_mosaic_channels_follow_the_layout():
    # Sony layout row 0 = (90, 45), row 1 = (135, 0): fill each mosaic position with its label.
    raw = np.zeros(SMALL.shape, dtype=np.uint16)
    raw[0::2, 0::2], raw[0::2, 1::2], raw[1::2, 0::2], raw[1::2, 1::2] = 90, 45, 135, 0
    ch = mosaic_channels(raw, SMALL)
    assert ch.shape == (*SMALL.superpixel_shape, 4)
    np.testing.assert_array_equal(ch[3, 5], [0, 45, 90, 135])


def test_check_raw_names_shape_and_dtype():
    with pytest.raises(ValueError, match=r"\(256, 306\)"):
        check_raw(np.zeros((10, 10), np.uint16), SMALL)
    with pytest.raises(ValueError, match="dtype int32"):
        check_raw(np.zeros(SMALL.shape, np.int32), SMALL)
    assert check_raw(np.zeros(SMALL.shape, np.float32), SMALL).dtype == np.float32


def test_ideal_stokes_is_sum_and_differences():
    # docs/model.md §7.2 ideal case: S0 = (I0+I45+I90+I135)/2 after gains, S1 = I0 - I90, S2 = I45 - I135.
    # Arbitrary (not Malus-consistent) channels: for equal gains the least-squares estimate
    # is exactly this formula.
    rng = np.random.default_rng(0)
    ideal = CAM.with_changes(gain=np.full(4, 1.02))
    ch = rng.uniform(50, 300, (1000, 4))
    s, nu = stokes_from_channels(ch, ideal)
    hat = ch / ideal.gain
    np.testing.assert_allclose(s[:, 0], hat.sum(-1) / 2, rtol=1e-12)
    np.testing.assert_allclose(s[:, 1], hat[:, 0] - hat[:, 2], rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(s[:, 2], hat[:, 1] - hat[:, 3], rtol=1e-12, atol=1e-10)
    # Redundancy: proportional to I0 - I45 + I90 - I135 (gain-corrected), unit noise gain.
    combo = hat[:, 0] - hat[:, 1] + hat[:, 2] - hat[:, 3]
    assert abs(np.corrcoef(nu, combo)[0, 1]) == pytest.approx(1.0, abs=1e-12)
    cal = stokes_calibration(ideal)
    assert np.linalg.norm(cal.null) == pytest.approx(1.0)
    assert stokes_calibration(CAM.with_changes(gain=np.ones(4))).sigma_l_factor == pytest.approx(
        np.sqrt(2)
    )


def test_calibrated_stokes_inverts_a_non_ideal_sensor():
    cam = _odd_camera()
    rng = np.random.default_rng(1)
    s0 = rng.uniform(50, 500, 2000)
    d, zeta = rng.uniform(0, 0.9, 2000), rng.uniform(-np.pi, np.pi, 2000)
    stokes = np.stack([s0, s0 * d * np.cos(2 * zeta), s0 * d * np.sin(2 * zeta)], -1)
    est, nu = stokes_from_channels(_sensor(stokes, cam), cam)
    np.testing.assert_allclose(est, stokes, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(nu, 0.0, atol=1e-9)  # blind to every Stokes input
    np.testing.assert_allclose(aop(est), 0.5 * np.angle(np.exp(2j * zeta)), atol=1e-9)
    np.testing.assert_allclose(dop(est), d, atol=1e-12)
    # The gain-blind estimator (the paper's uncorrected baseline) sees pseudo-polarization.
    blind, _ = stokes_from_channels(_sensor(stokes, cam), cam, gain_correction=False)
    assert np.abs(blind - stokes).max() > 1.0


def test_redundancy_has_the_channel_noise():
    cam = _odd_camera()
    rng = np.random.default_rng(2)
    stokes = np.tile([200.0, 40.0, -30.0], (200_000, 1))
    ch = _sensor(stokes, cam) + rng.normal(0, 1.5, (200_000, 4))
    s, nu = stokes_from_channels(ch, cam)
    assert nu.std() == pytest.approx(1.5, rel=0.01)
    cal = stokes_calibration(cam)
    assert s[:, 1].std() == pytest.approx(1.5 * np.sqrt(cal.covariance[1, 1]), rel=0.01)
    # The redundancy is independent of the Stokes estimate (orthogonal projections).
    assert abs(np.corrcoef(nu, s[:, 1])[0, 1]) < 0.01


def test_stokes_sign_is_pinned_by_a_polarizer():
    # A polarizer at 0 deg (along +u) gives S1 > 0; at 45 deg (from +u towards +v) S2 > 0.
    for angle, index in [(0.0, 1), (45.0, 2)]:
        raw = render(SMALL, SUN_N, Rotation.identity(), polarizer_deg=angle)
        s, _ = stokes_from_channels(mosaic_channels(raw, SMALL), SMALL)
        assert np.nanmedian(s[..., index]) > 0.9 * np.nanmedian(s[..., 0])
        assert np.degrees(np.nanmedian(aop(s))) == pytest.approx(angle, abs=1e-9)


def test_rotating_polarizer_detects_swapped_45_135_channels():
    # docs/model.md §3.4: with the correct labels the AoP follows the polarizer (slope +1); a camera
    # model with the 45 and 135 deg channels swapped sees it turn backwards (slope -1).
    angles = np.radians([0.0, 20.0, 40.0, 60.0, 80.0])
    raws = [render(SMALL, SUN_N, Rotation.identity(), polarizer_deg=np.degrees(a)) for a in angles]
    assert polarizer_rotation_slope(raws, angles, SMALL) == pytest.approx(1.0, abs=1e-6)
    layout = {int(k): pos for pos, k in np.ndenumerate(SMALL.channel_at)}
    chan = SMALL.channel_at.copy()
    chan[layout[1]], chan[layout[3]] = 3, 1
    swapped = SMALL.with_changes(channel_at=chan)
    assert polarizer_rotation_slope(raws, angles, swapped) == pytest.approx(-1.0, abs=1e-2)


def test_exact_compensation_inverts_the_sunlight_term():
    # docs/model.md §12.4: noise-free, eps = 0.0125, exact compensation with the true angle: AoP error
    # < 1e-9 deg; without it the AoP error near the sun (low DoP) is large.
    rng = np.random.default_rng(3)
    n = 50_000
    radiance = rng.uniform(100, 400, n)
    d = rng.uniform(0.005, 0.9, n)
    zeta = rng.uniform(-np.pi / 2, np.pi / 2, n)
    sky = np.stack([radiance, radiance * d * np.cos(2 * zeta), radiance * d * np.sin(2 * zeta)], -1)
    sun_c = np.array([-0.3, 0.7, 0.64])
    w = sunlight_direction(sun_c)
    assert np.degrees(np.arctan2(-w[1], -w[0]) / 2) == pytest.approx(
        np.degrees(np.arctan2(0.7, -0.3)) - 180.0, abs=1e-9
    )
    measured = stokes_with_sunlight(sky, 0.0125, w)
    np.testing.assert_allclose(measured[:, 0], radiance * (1 - 0.0125 * (1 - d)), rtol=1e-12)
    back = stokes_compensated(measured, 0.0125, w)
    err = np.degrees(np.abs(np.angle(np.exp(2j * (aop(back) - zeta))) / 2))
    assert err.max() < 1e-9
    np.testing.assert_allclose(back, sky, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(unpolarized_intensity(back), radiance * (1 - d), rtol=1e-9)
    before = np.degrees(np.abs(np.angle(np.exp(2j * (aop(measured) - zeta))) / 2))
    assert before.max() > 10.0
    with pytest.raises(ValueError, match="epsilon"):
        stokes_compensated(measured, 0.7, w)


def _sky_channels(cam, rot, epsilon, noise=0.0, seed=0):
    raw = render(cam, SUN_N, rot, epsilon=epsilon, noise_std=noise, rng=np.random.default_rng(seed))
    return mosaic_channels(raw, cam)


def test_paper_algorithm1_known_behaviour():
    # docs/model.md §8.2: with m = 2 the Eq. 22 numerator is identically zero without noise (k_m = 0,
    # nothing compensated, whatever eps); with the printed m = 4, k_m ~ 80/(1 - d);
    # sum_k P_hat_k = -(1 - d)/2 does not depend on the sun azimuth.
    rot = Rotation.from_euler("ZYX", [0.4, 0.0, 0.0])
    ch = _sky_channels(SMALL, rot, epsilon=0.0125)
    inside = np.isfinite(ch).all(-1) & (ch.sum(-1) > 0)
    sun_c = rot.inv().apply(SUN_N)
    s_cons, km_cons = paper_algorithm1(ch[inside], SMALL, sun_c)
    assert np.abs(km_cons).max() < 1e-9
    s_ls, _ = stokes_from_channels(ch[inside], SMALL)
    np.testing.assert_allclose(aop(s_cons), aop(s_ls), atol=1e-9)
    _, km_printed = paper_algorithm1(ch[inside], SMALL, sun_c, eq22="printed")
    d = dop(s_ls)
    keep = d < 0.6
    np.testing.assert_allclose(km_printed[keep] * (1 - d[keep]), 80.0, rtol=0.08)
    # The denominator does not see the sun azimuth: k_m is the same for any prior.
    _, km_other = paper_algorithm1(ch[inside], SMALL, [0.5, -0.2, 0.84], eq22="printed")
    np.testing.assert_allclose(km_other, km_printed, rtol=1e-12)
    # Eq. 14 as printed turns the AoP by 90 deg.
    s_printed, _ = paper_algorithm1(ch[inside], SMALL, sun_c, eq14="printed")
    turned = np.angle(np.exp(2j * (aop(s_printed) - aop(s_cons)))) / 2
    np.testing.assert_allclose(np.abs(np.degrees(turned)), 90.0, atol=1e-9)


def test_paper_k_m_is_amplified_noise():
    # With noise, the scale-consistent k_m is pure noise: zero median, spread ~ k_c * noise.
    rot = Rotation.from_euler("ZYX", [0.4, 0.0, 0.0])
    ch = _sky_channels(SMALL, rot, epsilon=0.0125, noise=1.5, seed=4)
    inside = np.isfinite(ch).all(-1) & (ch.sum(-1) > 100)
    _, km = paper_algorithm1(ch[inside], SMALL, rot.inv().apply(SUN_N))
    iqr = np.subtract(*np.percentile(km, [75, 25]))
    assert abs(np.median(km)) < 0.1 * iqr
    assert (
        0.7 < iqr < 2.5
    )  # docs/errata.md §3: IQR +-0.7 around 0 at sigma = 1.5 DN (true k_m = 0.05)


def test_validity_mask_criteria():
    rot = Rotation.from_euler("ZYX", [0.4, 0.0, 0.0])
    raw = render(SMALL, SUN_N, rot, epsilon=0.0, radiance=220.0)
    sun_c = rot.inv().apply(SUN_N)
    base = validity_mask(raw, SMALL, sun_c=sun_c)
    fov = np.asarray(polins.compass.camera.fov_mask(SMALL))
    assert not base[~fov].any() and base.sum() > 0.9 * fov.sum() * 0.9
    i, j = np.argwhere(base)[len(np.argwhere(base)) // 2]
    ri, rj = 2 * i, 2 * j
    # One saturated channel masks its superpixel.
    sat = raw.copy()
    sat[ri, rj + 1] = SMALL.saturation_dn
    assert not validity_mask(sat, SMALL, sun_c=sun_c)[i, j]
    # A corrupted channel (calibration error) fails the redundancy test.
    bad = raw.copy()
    bad[ri + 1, rj] += 20.0
    assert not validity_mask(bad, SMALL, sun_c=sun_c, gradient_max=None)[i, j]
    # NaN pixels of a float mosaic are masked, and only them (gradient test off).
    nan = raw.copy()
    nan[ri, rj] = np.nan
    m = validity_mask(nan, SMALL, sun_c=sun_c, gradient_max=None)
    assert (
        not m[i, j]
        and m.sum() == validity_mask(raw, SMALL, sun_c=sun_c, gradient_max=None).sum() - 1
    )
    # The sun circle: exactly the pixels within 10 deg of the sun are removed.
    rays = polins.compass.camera.pixel_rays_c(SMALL)
    with np.errstate(invalid="ignore"):
        angle = np.degrees(np.arccos(np.clip(rays @ sun_c, -1, 1)))
    assert not base[angle < 10.0].any()
    no_sun = validity_mask(raw, SMALL, dop_min=0.0)
    with_sun = validity_mask(raw, SMALL, dop_min=0.0, sun_c=sun_c)
    assert no_sun[angle < 10.0].any() and not with_sun[angle < 10.0].any()
    np.testing.assert_array_equal(with_sun[angle > 10.01], no_sun[angle > 10.01])
    # The Rayleigh DoP (d_max 0.75) is below 0.03 within 16.1 deg of the sun.
    assert not base[angle < 15.9].any() and base[(angle > 16.3) & fov].all()
    # A step in intensity masks the pixels along the edge (gradient), and DoP_min the dark
    # unpolarized region.
    step = raw.copy()
    step[:, : SMALL.width_px // 2] *= 2.0
    m_step = validity_mask(step, SMALL, sun_c=sun_c)
    edge = SMALL.superpixel_shape[1] // 2
    assert not m_step[:, edge - 1 : edge + 1].any() and m_step[:, edge + 3].sum() > 0


def test_relative_gradient_of_a_ramp():
    pixels = pixel_set(SMALL)
    hs, ws = SMALL.superpixel_shape
    v, u = np.mgrid[0:hs, 0:ws].astype(float)
    s0 = (1000.0 + 3.0 * u + 4.0 * v).ravel()[pixels.index]
    np.testing.assert_allclose(relative_gradient(s0, pixels) * s0, 5.0, rtol=1e-12)


@pytest.mark.parametrize(
    "variant", ["odd", "shot noise", "dop cut, no gradient test", "per-pixel maps"]
)
def test_compiled_stokes_pass_is_bit_identical(variant):
    # The compiled pass of an integer mosaic gives the very numbers of the numpy row kernels
    # (docs/measurement.md §10), on a pixel set with holes (runs split inside rows),
    # saturated channels and pixels that fail each test.
    cam = _odd_camera().downscaled(4)
    kw = {"s0_min": 10.0, "redundancy_max_sigma": 4.0, "gradient_max": 0.05, "dop_min": 0.0}
    if variant == "shot noise":
        cam = cam.with_changes(conversion_gain_e_per_dn=2.5)
    if variant == "dop cut, no gradient test":
        kw.update(gradient_max=None, dop_min=0.05)
    rng = np.random.default_rng(7)
    if variant == "per-pixel maps":
        shape = (*cam.superpixel_shape, 4)
        cam = cam.with_changes(
            gain_map=cam.gain * (1.0 + 0.01 * rng.normal(size=shape)),
            transmission_angle_map=cam.transmission_angle + 0.005 * rng.normal(size=shape),
        )
    raw = render(cam, SUN_N, Rotation.from_euler("ZYX", [0.4, 0.05, -0.03]), epsilon=0.01,
                 noise_std=1.5, rng=rng, dtype=np.uint16)  # fmt: skip
    raw[rng.integers(0, raw.shape[0], 300), rng.integers(0, raw.shape[1], 300)] = 4095
    raw[rng.integers(0, raw.shape[0], 300), rng.integers(0, raw.shape[1], 300)] = 0
    holes = rng.random(cam.superpixel_shape) < 0.1
    pixels = pixel_set(cam, np.asarray(polins.compass.camera.roi_mask(cam)) & ~holes)
    cal = stokes_calibration(cam, True, pixels)
    assert (cal.pixel is not None) == (variant == "per-pixel maps")
    got = stokes_image(raw, pixels, cam, cal, **kw)
    channels = gather_channels(raw, pixels, np.float32)
    rows = stokes_rows(channels, cal, np.float32)
    sigma2 = stokes_noise_variance(cam, rows[0])
    valid = validity_rows(channels, rows, pixels, cam, sigma2, finite_check=False, **kw)
    assert got.channels is None and got.rows.dtype == np.float32
    np.testing.assert_array_equal(got.rows, rows)
    np.testing.assert_array_equal(got.sigma2, sigma2)
    np.testing.assert_array_equal(got.valid, valid)
    np.testing.assert_array_equal(got.unsaturated, channels.max(axis=0) < cam.saturation_dn)
    assert 0.5 < valid.mean() < 0.99 and not got.unsaturated.all()
    # With the channels asked for, the same numbers again; and from a big-endian mosaic.
    again = stokes_image(raw, pixels, cam, cal, channels=True, **kw)
    np.testing.assert_array_equal(again.channels, channels)
    np.testing.assert_array_equal(again.valid, got.valid)
    swapped = stokes_image(raw.astype(">u2"), pixels, cam, cal, **kw)
    np.testing.assert_array_equal(swapped.rows, rows)
    np.testing.assert_array_equal(swapped.valid, valid)
