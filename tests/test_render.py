"""The raw-image renderer: mosaic layout, Malus law per channel, sunlight term, noise,
saturation, occluders, clouds, IFOV sampling, determinism."""

import numpy as np
import pytest

import polins
from polins.compass.camera import fov_mask, pixel_rays_c
from polins.sim import CloudPatch, azimuth_band, render_raw
from polins.sim.render import (
    azimuth_elevation_deg,
    channel_intensity,
    direction_n,
    mosaic_rays_c,
    occluded,
)

CAM = polins.load_camera("paper-table1").downscaled(8)  # 306 x 256 mosaic: fast
SUN_N = polins.sun_vector_n(np.radians(247.04), np.radians(60.15))
ROT = polins.rot_nb_from_euler(0.3, 0.04, -0.03)

# A deliberately odd camera: permuted layout, unequal gains/efficiencies/offsets, rotated
# transmission axes, so that any mix-up of channels or calibration terms shows.
ODD = CAM.with_changes(
    channel_at=np.array([[2, 0], [3, 1]]),
    gain=np.array([1.1, 0.9, 1.05, 0.95]),
    efficiency=np.array([0.98, 0.9, 0.95, 0.85]),
    dark_offset_dn=np.array([10.0, 20.0, 30.0, 40.0]),
    transmission_angle=np.radians([3.0, 41.0, 95.0, 131.0]),
)


def _channels(raw, cam):
    """(4, Hs, Ws) channel images in channel order (independent of the renderer)."""
    out = np.empty((4, *cam.superpixel_shape))
    for r in (0, 1):
        for c in (0, 1):
            out[cam.channel_at[r, c]] = raw[r::2, c::2]
    return out


def _expected_malus(cam, rays_c, rot_nb, channel, radiance=220.0, dop_max=0.75):
    """Independent per-channel response: the partially polarized light is an unpolarized
    part plus a fully polarized part at the projected E-vector angle, and the polarized
    part passes the analyser by Malus' law with efficiency eta:
    I = g R [(1 - d)/2 + d ((1 - eta)/2 + eta cos^2(zeta - alpha))] + o."""
    sun_c = rot_nb.inv().apply(SUN_N)  # mount is identity
    e = np.cross(sun_c, rays_c)
    zeta = np.arctan2(e[..., 1], e[..., 0])  # lens model (P): angle of the projected E
    cos_t = rays_c @ sun_c
    d = dop_max * (1 - cos_t**2) / (1 + cos_t**2)
    g, eta = cam.gain[channel], cam.efficiency[channel]
    alpha, o = cam.transmission_angle[channel], cam.dark_offset_dn[channel]
    malus = (1 - eta) / 2 + eta * np.cos(zeta - alpha) ** 2
    return g * radiance * ((1 - d) / 2 + d * malus) + o


def _sky(cam):
    return fov_mask(cam) & np.isfinite(pixel_rays_c(cam)[..., 2])


@pytest.mark.parametrize("ifov", [False, True])
def test_malus_law_per_channel_through_the_mosaic(ifov):
    raw = render_raw(ODD, SUN_N, ROT, epsilon=0.0, sun_disc_deg=0.0, quantize=False, ifov=ifov)
    assert raw.shape == ODD.shape and raw.dtype == np.float64
    sky = _sky(ODD)
    for r in (0, 1):
        for c in (0, 1):
            k = ODD.channel_at[r, c]
            rays = mosaic_rays_c(ODD, r, c) if ifov else pixel_rays_c(ODD)
            expected = _expected_malus(ODD, rays, ROT, k)
            np.testing.assert_allclose(raw[r::2, c::2][sky], expected[sky], rtol=0, atol=1e-9)


def test_fully_polarized_single_angle_comes_back_per_channel():
    # A uniform, fully polarized field at AoP zeta: channel k reads g_k R cos^2(zeta - alpha_k)
    # + o_k (eta = 1), and the ideal Stokes formula returns zeta.
    cam = ODD.with_changes(efficiency=np.ones(4), transmission_angle=np.radians([0, 45, 90, 135]))
    for zeta in np.radians([0.0, 17.0, 45.0, 100.0, 160.0]):
        stokes = 220.0 * np.array([1.0, np.cos(2 * zeta), np.sin(2 * zeta)])
        vals = np.array([channel_intensity(stokes, cam, k) for k in range(4)])
        alphas = cam.transmission_angle
        np.testing.assert_allclose(
            vals, cam.gain * 220 * np.cos(zeta - alphas) ** 2 + cam.dark_offset_dn
        )
        i = (vals - cam.dark_offset_dn) / cam.gain
        assert np.angle(np.exp(1j * np.arctan2(i[1] - i[3], i[0] - i[2]))) == pytest.approx(
            np.angle(np.exp(2j * zeta)), abs=1e-12
        )


def test_mosaic_layout_of_the_shipped_camera():
    # Sony IMX250MZR: row 0 = (90, 45), row 1 = (135, 0). With a sky of known AoP the
    # brightest position follows the layout: at the principal point the E-vector is
    # perpendicular to the sun's camera-frame azimuth.
    cam = polins.load_camera("paper-table1").downscaled(8)
    assert cam.nominal_angle_deg[cam.channel_at].tolist() == [[90, 45], [135, 0]]
    for yaw_deg in (0.0, 30.0, 75.0, 120.0, 160.0):
        rot = polins.rot_nb_from_euler(np.radians(yaw_deg), 0.0, 0.0)
        raw = render_raw(cam, SUN_N, rot, epsilon=0.0, quantize=False, dop_max=1.0)
        sun_c = rot.inv().apply(SUN_N)
        zeta = np.arctan2(sun_c[1], sun_c[0]) + np.pi / 2
        i, j = np.round(cam.camera_matrix[[1, 0], 2]).astype(int)
        block = raw[2 * i : 2 * i + 2, 2 * j : 2 * j + 2]
        angles = np.radians(cam.nominal_angle_deg[cam.channel_at])
        best = angles.ravel()[np.argmax(block.ravel() / cam.gain[cam.channel_at].ravel())]
        assert abs(np.angle(np.exp(2j * (best - zeta)))) / 2 <= np.radians(45.0 / 2 + 1)


def test_sunlight_term_is_the_spec_stokes_form():
    base = render_raw(CAM, SUN_N, ROT, epsilon=0.0, sun_disc_deg=0.0, quantize=False)
    eps = 0.05
    lit = render_raw(CAM, SUN_N, ROT, epsilon=eps, sun_disc_deg=0.0, quantize=False)
    sky = _sky(CAM)

    def stokes(raw):
        i = _channels(raw, CAM) / CAM.gain[:, None, None]
        return np.stack([0.5 * i.sum(0), i[0] - i[2], i[1] - i[3]], -1)

    s_base, s_lit = stokes(base), stokes(lit)
    u = s_base[..., 0] - np.hypot(s_base[..., 1], s_base[..., 2])
    sun_c = ROT.inv().apply(SUN_N)
    a_s = np.arctan2(sun_c[1], sun_c[0])
    w = -np.array([np.cos(2 * a_s), np.sin(2 * a_s)])
    np.testing.assert_allclose(s_lit[sky, 0], s_base[sky, 0] - eps * u[sky], atol=1e-9)
    np.testing.assert_allclose(s_lit[sky, 1:], s_base[sky, 1:] + eps * u[sky, None] * w, atol=1e-9)
    # The sun behind an occluder: no direct sunlight.
    az, el = azimuth_elevation_deg(SUN_N)
    hidden = [azimuth_band(az - 5, az + 5, el + 5)]
    a = render_raw(CAM, SUN_N, ROT, epsilon=eps, occluders=hidden, quantize=False)
    b = render_raw(CAM, SUN_N, ROT, epsilon=0.0, occluders=hidden, quantize=False)
    np.testing.assert_array_equal(a, b)


def test_determinism_and_noise_free():
    a = render_raw(CAM, SUN_N, ROT, rng=np.random.default_rng(7))
    b = render_raw(CAM, SUN_N, ROT, rng=np.random.default_rng(7))
    c = render_raw(CAM, SUN_N, ROT, rng=np.random.default_rng(8))
    assert a.dtype == np.uint16 and a.shape == CAM.shape
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    clean = render_raw(CAM, SUN_N, ROT)
    np.testing.assert_array_equal(clean, render_raw(CAM, SUN_N, ROT, noise_std=9.0))


@pytest.mark.parametrize("shot", [False, True])
def test_noise_statistics(shot):
    gain_e = 2.0
    cam = CAM.with_changes(conversion_gain_e_per_dn=gain_e)
    sky = np.repeat(np.repeat(_sky(cam), 2, 0), 2, 1)
    clean = render_raw(cam, SUN_N, ROT, quantize=False, sun_disc_deg=0.0)[sky]
    sigma = 1.5
    resid = []
    for seed in range(4):
        raw = render_raw(
            cam,
            SUN_N,
            ROT,
            rng=np.random.default_rng(seed),
            noise_std=sigma,
            shot_noise=shot,
            sun_disc_deg=0.0,
        )
        resid.append(raw[sky].astype(float) - clean)
    resid = np.concatenate(resid)
    signal = np.tile(clean, 4)
    var = sigma**2 + 1.0 / 12.0 + (signal / gain_e if shot else 0.0)  # + quantisation
    z = resid / np.sqrt(var)
    n = z.size
    assert abs(z.mean()) < 4 / np.sqrt(n)
    assert z.var() == pytest.approx(1.0, abs=4 * np.sqrt(2 / n) + 0.01)
    if shot:  # the variance grows with the signal: brighter pixels are noisier
        bright = signal > np.median(signal)
        assert resid[bright].var() > resid[~bright].var() * 1.05
    with pytest.raises(ValueError, match="conversion_gain"):
        render_raw(CAM, SUN_N, ROT, rng=np.random.default_rng(0), shot_noise=True)


def test_saturation_and_sun_disc():
    raw = render_raw(CAM, SUN_N, ROT, radiance=40000.0, rng=np.random.default_rng(0))
    sky = np.repeat(np.repeat(_sky(CAM), 2, 0), 2, 1)
    assert raw.max() == 4095 and np.all(raw[sky] == 4095)
    raw = render_raw(CAM, SUN_N, ROT, sun_disc_deg=5.0, rng=np.random.default_rng(0))
    sun_c = ROT.inv().apply(SUN_N)
    near = np.degrees(np.arccos(np.clip(pixel_rays_c(CAM) @ sun_c, -1, 1))) < 5.0
    assert near.sum() > 4
    for r in (0, 1):
        for c in (0, 1):
            assert np.all(raw[r::2, c::2][near] == 4095)
            assert raw[r::2, c::2][~near & _sky(CAM)].max() < 400


def test_world_fixed_occluder():
    band = azimuth_band(350.0, 40.0, 35.0)  # wraps through North
    ground = 33.0
    for yaw in (0.0, 1.0, 2.5):
        rot = polins.rot_nb_from_euler(yaw, 0.0, 0.0)
        raw = render_raw(
            CAM, SUN_N, rot, epsilon=0.0, ground_radiance=ground, occluders=[band], quantize=False
        )
        ch = _channels(raw, CAM)
        rays_n = rot.apply(pixel_rays_c(CAM))
        az, el = azimuth_elevation_deg(rays_n)
        inside = ((az > 350) | (az < 40)) & (el < 35) & _sky(CAM)
        outside = ~(((az > 349) | (az < 41)) & (el < 36)) & _sky(CAM) & (el > 0.5)
        assert inside.sum() > 50 and outside.sum() > 1000
        # Occluded: unpolarized ground radiance in every channel.
        np.testing.assert_allclose(
            ch[:, inside], np.broadcast_to((0.5 * CAM.gain * ground)[:, None], (4, inside.sum()))
        )
        # Not occluded: the sky.
        assert np.all(ch[:, outside].mean(0) > 60)
    # Below the horizon is ground even without occluders (tilted camera).
    rot = polins.rot_nb_from_euler(0.0, np.radians(25.0), 0.0)
    raw = render_raw(CAM, SUN_N, rot, epsilon=0.0, ground_radiance=ground, quantize=False)
    below = (rot.apply(pixel_rays_c(CAM))[..., 2] < -0.01) & np.isfinite(pixel_rays_c(CAM)[..., 2])
    assert below.sum() > 100
    expected = np.broadcast_to((0.5 * CAM.gain * ground)[:, None], (4, below.sum()))
    np.testing.assert_allclose(_channels(raw, CAM)[:, below], expected)


def test_occluded_polygon_geometry():
    d = direction_n([10.0, 100.0, 355.0, 5.0], [10.0, 10.0, 10.0, 50.0])
    poly = [[350.0, -90.0], [20.0, -90.0], [20.0, 40.0], [350.0, 40.0]]
    assert occluded(d, [poly]).tolist() == [True, False, True, False]
    # A triangle (gable roof), azimuths given past 360.
    tri = [[300.0, 0.0], [400.0, 0.0], [350.0, 60.0]]
    d = direction_n([350.0, 330.0, 20.0, 30.0], [50.0, 10.0, 20.0, 5.0])
    assert occluded(d, [tri]).tolist() == [True, True, True, True]
    assert occluded(direction_n(320.0, 40.0), [tri]).item() is False
    with pytest.raises(ValueError, match="polygon"):
        occluded(d, [[[0.0, 0.0], [10.0, 0.0]]])


def test_clouds_depolarize_and_brighten():
    az, _ = azimuth_elevation_deg(SUN_N)
    cloud = CloudPatch(
        azimuth_deg=float(az) + 90.0,
        elevation_deg=50.0,
        radius_deg=15.0,
        depolarization=0.9,
        brightness=1.4,
    )
    clear = render_raw(CAM, SUN_N, ROT, epsilon=0.0, quantize=False)
    cloudy = render_raw(CAM, SUN_N, ROT, epsilon=0.0, quantize=False, clouds=[cloud])

    def dop_s0(raw):
        i = _channels(raw, CAM) / CAM.gain[:, None, None]
        s0 = 0.5 * i.sum(0)
        with np.errstate(invalid="ignore"):
            return np.hypot(i[0] - i[2], i[1] - i[3]) / s0, s0

    centre = np.degrees(
        np.arccos(
            np.clip(ROT.apply(pixel_rays_c(CAM)) @ direction_n(cloud.azimuth_deg, 50.0), -1, 1)
        )
    )
    core, away = centre < 8.0, (centre > 16.0) & _sky(CAM)
    (d0, s0), (d1, s1) = dop_s0(clear), dop_s0(cloudy)
    np.testing.assert_allclose(d1[core], 0.1 * d0[core], rtol=1e-9)
    np.testing.assert_allclose(s1[core], 1.4 * s0[core], rtol=1e-9)
    np.testing.assert_allclose(
        cloudy[np.repeat(np.repeat(away, 2, 0), 2, 1)],
        clear[np.repeat(np.repeat(away, 2, 0), 2, 1)],
    )
    with pytest.raises(ValueError, match="depolarization"):
        CloudPatch(0.0, 45.0, 10.0, depolarization=1.5)


def test_ifov_offsets_and_berry_option():
    # The four channel positions sit a quarter superpixel around the superpixel centre.
    cam = CAM
    centre = pixel_rays_c(cam)
    mean = sum(mosaic_rays_c(cam, r, c) for r in (0, 1) for c in (0, 1)) / 4
    sky = _sky(cam)
    ang = np.arccos(np.clip(np.sum(mean * centre, -1) / np.linalg.norm(mean, axis=-1), -1, 1))
    assert np.degrees(ang[sky]).max() < 0.01
    step = np.degrees(np.arccos(np.clip(np.sum(mosaic_rays_c(cam, 0, 0) * centre, -1), -1, 1)))
    assert 0.5 < np.median(step[sky]) < 2.0  # ~ half a (downscaled) pixel pitch in angle
    a = render_raw(cam, SUN_N, ROT, quantize=False, sun_disc_deg=0.0)
    b = render_raw(cam, SUN_N, ROT, quantize=False, sun_disc_deg=0.0, ifov=True)
    sky_full = np.repeat(np.repeat(sky, 2, 0), 2, 1)
    assert 0 < np.abs(a - b)[sky_full].max() < 20  # the IFOV mismatch: small but present
    # Berry sky with merged neutral points is the Rayleigh sky.
    berry0 = render_raw(
        cam, SUN_N, ROT, quantize=False, sun_disc_deg=0.0, sky="berry", neutral_sep=0.0
    )
    np.testing.assert_allclose(berry0, a, atol=1e-9)
    berry = render_raw(
        cam, SUN_N, ROT, quantize=False, sun_disc_deg=0.0, sky="berry", neutral_sep=np.radians(35)
    )
    assert np.abs(berry - a)[sky_full].max() > 1.0


def test_rayleigh_radiance_model_and_errors():
    const = render_raw(CAM, SUN_N, ROT, epsilon=0.0, quantize=False, sun_disc_deg=0)
    ray = render_raw(
        CAM, SUN_N, ROT, epsilon=0.0, quantize=False, sun_disc_deg=0, radiance_model="rayleigh"
    )
    cos_t = pixel_rays_c(CAM) @ ROT.inv().apply(SUN_N)
    sky = _sky(CAM)
    ratio = _channels(ray, CAM)[:, sky] / _channels(const, CAM)[:, sky]
    np.testing.assert_allclose(ratio, np.broadcast_to(1 + cos_t[sky] ** 2, ratio.shape), rtol=1e-12)
    with pytest.raises(ValueError, match="sun_n"):
        render_raw(CAM, [0.0, 1.0], ROT)
    with pytest.raises(ValueError, match="rot_nb"):
        render_raw(CAM, SUN_N, polins.rot_nb_from_euler([0.0, 1.0], 0.0, 0.0))
    with pytest.raises(ValueError, match="sky model"):
        render_raw(CAM, SUN_N, ROT, sky="mie")
    with pytest.raises(ValueError, match="dop_max"):
        render_raw(CAM, SUN_N, ROT, dop_max=2.0)
    with pytest.raises(TypeError, match="Generator"):
        render_raw(CAM, SUN_N, ROT, rng=42)
