"""Per-pixel gain, angle and efficiency maps in the Stokes step (docs/measurement.md §1) and in CameraModel.downscaled."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_calibration_scenes import mosaic, response, small_camera

import polins
from polins.compass.pixels import mosaic_channels
from polins.compass.polarimetry import pixel_stokes, stokes_calibration, stokes_from_channels
from polins.sim.render import direction_n

SUN_N = direction_n(30.0, 50.0)
CAM = small_camera(8)  # 153 x 128 superpixels, ideal channels


def _spread_maps(cam, rng):
    """Smooth per-channel gain (+-4 % across the sensor) and angle (+-2 deg) fields with
    pixel-to-pixel noise (1 %, 0.3 deg): what a real sensor's maps look like."""
    hs, ws = cam.superpixel_shape
    v, u = np.mgrid[0:hs, 0:ws]
    x, y = (u / ws - 0.5)[..., None], (v / hs - 0.5)[..., None]
    gain = 1 + rng.uniform(-0.04, 0.04, 4) * x + rng.uniform(-0.04, 0.04, 4) * y
    gain = gain + 0.01 * rng.standard_normal((hs, ws, 4))
    offset_deg = rng.uniform(-2, 2, 4) * x + rng.uniform(-2, 2, 4) * y
    angle = np.radians(cam.nominal_angle_deg + offset_deg + 0.3 * rng.standard_normal((hs, ws, 4)))
    return gain, angle


def _scene_stokes(cam, rot):
    """Noise-free scene Stokes (Hs, Ws, 3) [DN] of a clear sky, through the ideal camera."""
    signal = polins.sim.render_raw(cam, SUN_N, rot, rng=None, quantize=False, sun_disc_deg=0.0)
    two_a = 2 * np.radians(cam.nominal_angle_deg)
    a = 0.5 * np.stack([np.ones(4), np.cos(two_a), np.sin(two_a)], -1)
    return mosaic_channels(signal, cam) @ np.linalg.pinv(a).T


def test_maps_equal_to_the_channel_values_change_nothing():
    rng = np.random.default_rng(0)
    cam = CAM.with_changes(gain=np.array([1.02, 0.99, 1.01, 0.98]))
    shape = (*cam.superpixel_shape, 4)
    mapped = cam.with_changes(
        gain_map=np.broadcast_to(cam.gain, shape).copy(),
        transmission_angle_map=np.full(shape, np.nan),  # NaN: the channel's value
        efficiency_map=np.broadcast_to(cam.efficiency, shape).copy(),
    )
    rot = Rotation.from_euler("z", 20, degrees=True)
    raw = polins.sim.render_raw(cam, SUN_N, rot, rng=rng)
    s0, nu0 = stokes_from_channels(mosaic_channels(raw, cam), cam)
    s1, nu1 = stokes_from_channels(mosaic_channels(raw, cam), mapped)
    np.testing.assert_allclose(s1, s0, atol=1e-9)
    np.testing.assert_allclose(nu1, nu0, atol=1e-9)
    m0 = polins.measure(raw, cam, sun_n=SUN_N, rot_nb_prior=rot)
    m1 = polins.measure(raw, mapped, sun_n=SUN_N, rot_nb_prior=rot)
    assert m1.ok and m1.yaw == pytest.approx(m0.yaw, abs=1e-7)
    assert m1.n_pixels == m0.n_pixels
    # Without maps, and without a pixel set, the calibration stays the one channel matrix.
    assert stokes_calibration(cam, True, None).pixel is None
    assert stokes_calibration(mapped).pixel is None


def test_per_pixel_rows_invert_the_response_and_null_it():
    rng = np.random.default_rng(1)
    gain, angle = _spread_maps(CAM, rng)
    eff = rng.uniform(0.9, 1.0, gain.shape)
    cam = CAM.with_changes(gain_map=gain, transmission_angle_map=angle, efficiency_map=eff)
    index = rng.choice(gain.shape[0] * gain.shape[1], 50, replace=False)
    rows = pixel_stokes(cam, index)
    g, a, e = (m.reshape(-1, 4)[index] for m in (gain, angle, eff))
    resp = (
        0.5 * g[..., None] * np.stack([np.ones_like(g), e * np.cos(2 * a), e * np.sin(2 * a)], -1)
    )
    matrix = rows.matrix.transpose(2, 0, 1)  # (n, 4, 4)
    np.testing.assert_allclose(matrix[:, :3] @ resp, np.broadcast_to(np.eye(3), (50, 3, 3)),
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(np.einsum("nk,nkj->nj", matrix[:, 3], resp), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(matrix[:, 3], axis=1), 1.0)
    assert np.all(matrix[:, 3, 0] > 0)
    np.testing.assert_allclose(rows.matrix[:3, :, 0], np.linalg.pinv(resp[0]), atol=1e-12)


def test_heading_with_the_maps_beats_the_channel_values():
    """An image rendered with per-pixel gain and angle spreads: the camera file's maps
    bring the heading error down to the noise; the channel values alone leave a bias."""
    rng = np.random.default_rng(5)
    gain, angle = _spread_maps(CAM, rng)
    true = CAM.with_changes(gain_map=gain, transmission_angle_map=angle)
    err = {"maps": [], "channels": []}
    for turn in np.linspace(0, 330, 12):
        rot = Rotation.from_euler("z", turn, degrees=True)
        raw = polins.sim.render_raw(true, SUN_N, rot, rng=rng, sun_disc_deg=0.0)  # the maps
        for key, cam in (("maps", true), ("channels", true.without_pixel_maps())):
            m = polins.measure(raw, cam, sun_n=SUN_N, rot_nb_prior=rot)
            assert m.ok, m.reason
            err[key].append(np.angle(np.exp(1j * (m.yaw - np.radians(turn)))))
    rms = {k: float(np.degrees(np.sqrt(np.mean(np.square(v))))) for k, v in err.items()}
    assert rms["maps"] < 0.05 and rms["channels"] > 0.3  # measured: 0.019 and 0.58 deg
    assert rms["maps"] < 0.1 * rms["channels"]


def test_the_renderer_responds_through_the_maps():
    """render_raw with per-pixel maps equals the independent forward model
    (tests/test_calibration_scenes.py) applied to the scene seen by an ideal camera."""
    rng = np.random.default_rng(6)
    gain, angle = _spread_maps(CAM, rng)
    eff = rng.uniform(0.9, 1.0, gain.shape)
    eff[::7, ::5] = np.nan  # NaN entries: the channel's value
    dark = np.array([12.0, 15.0, 9.0, 20.0])
    cam = CAM.with_changes(gain_map=gain, transmission_angle_map=angle, efficiency_map=eff,
                           efficiency=np.full(4, 0.97), dark_offset_dn=dark)  # fmt: skip
    rot = Rotation.from_euler("ZYX", [40, 3, -2], degrees=True)
    got = polins.sim.render_raw(cam, SUN_N, rot, rng=None, quantize=False, sun_disc_deg=0.0)
    expected = mosaic(
        response(_scene_stokes(CAM, rot), gain, np.where(np.isnan(eff), 0.97, eff), angle, dark),
        CAM,
    )
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9)
    plain = polins.sim.render_raw(cam.without_pixel_maps(), SUN_N, rot, rng=None, quantize=False,
                                  sun_disc_deg=0.0)  # fmt: skip
    assert np.abs(got - plain).max() > 5.0  # the maps matter: several DN


def test_stokes_from_channels_with_maps_needs_whole_images():
    cam = CAM.with_changes(gain_map=np.ones((*CAM.superpixel_shape, 4)))
    with pytest.raises(ValueError, match="whole superpixel images"):
        stokes_from_channels(np.ones((10, 4)), cam)
    stokes, nu = stokes_from_channels(np.ones((2, *CAM.superpixel_shape, 4)), cam)
    assert stokes.shape == (2, *CAM.superpixel_shape, 3) and nu.shape == stokes.shape[:-1]


def test_a_map_of_the_wrong_shape_is_refused():
    with pytest.raises(ValueError, match=r"gain_map has shape \(3, 4, 4\)"):
        CAM.with_changes(gain_map=np.ones((3, 4, 4)))


def test_downscaled_maps_average_the_response_rows():
    cam = small_camera(4)  # 306 x 256 superpixels
    rng = np.random.default_rng(2)
    shape = (*cam.superpixel_shape, 4)
    gain = 1 + 0.05 * rng.standard_normal(shape)
    gain[:2, :2] = np.nan  # one whole block of NaN: stays NaN
    small = cam.with_changes(gain_map=gain).downscaled(2)
    assert small.gain_map.shape == (*small.superpixel_shape, 4)
    assert small.transmission_angle_map is None and small.efficiency_map is None
    assert np.all(np.isnan(small.gain_map[0, 0]))
    block = gain[2:4, 6:8].mean(axis=(0, 1))
    np.testing.assert_allclose(small.gain_map[1, 3], block)
    # Angles that differ within a block depolarize: the binned efficiency says by how much.
    angle = np.radians(cam.nominal_angle_deg) + np.radians(10.0) * (rng.random(shape) > 0.5)
    small = cam.with_changes(transmission_angle_map=angle).downscaled(2)
    assert small.efficiency_map is not None and np.nanmin(small.efficiency_map) < 0.99
    two = 2 * angle[:2, :2]
    expected = np.hypot(np.cos(two).mean(axis=(0, 1)), np.sin(two).mean(axis=(0, 1)))
    np.testing.assert_allclose(small.efficiency_map[0, 0], expected)
