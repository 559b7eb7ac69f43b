"""Round trip of the rotating-polarizer calibration (docs/calibrate.md#polarizer): angles, efficiencies, gains, per-pixel maps."""

from dataclasses import replace

import numpy as np
import pytest
from test_calibration_scenes import (
    dark_mosaic_of,
    mosaic,
    perturbed_camera,
    response,
    sensor,
    small_camera,
)

from polins.calibration import apply_to_camera, calibrate_polarizer
from polins.errors import UserInputError

CAM = small_camera(8)
STEPS = np.radians(np.arange(12) * 15.0)  # a 12-step rotation over 180 deg


def _polarizer_frames(true, rng, angles, *, pixel_angle_deg=0.0, level=2400.0):
    hs, ws = true.superpixel_shape
    v, u = np.mgrid[0:hs, 0:ws]
    s0 = level * (1.0 - 0.3 * (((u - ws / 2) / ws) ** 2 + ((v - hs / 2) / hs) ** 2))
    angle = true.transmission_angle + np.radians(rng.normal(0.0, pixel_angle_deg, (hs, ws, 4)))
    dark = dark_mosaic_of(true)
    frames = []
    for theta in angles:
        stokes = s0[..., None] * np.array([1.0, np.cos(2 * theta), np.sin(2 * theta)])
        ch = response(stokes, true.gain, true.efficiency, angle, true.dark_offset_dn)
        frames.append(
            sensor(mosaic(ch, true), dark, true, rng, read_noise_dn=2.0, conversion_gain=4.0)
        )
    return np.stack(frames), angle


def _relative(x):
    return x / x.mean()


@pytest.mark.parametrize("known", [True, False], ids=["known-angles", "fitted-angles"])
def test_polarizer_round_trip_angles_efficiencies_gains(known):
    rng = np.random.default_rng(11)
    true = perturbed_camera(CAM, rng, eff=(0.95, 0.99))
    frames, _ = _polarizer_frames(true, rng, STEPS + 0.1)
    base = replace(CAM, dark_offset_dn=true.dark_offset_dn)
    res = calibrate_polarizer(frames, base, STEPS + 0.1 if known else None)
    offset = res.transmission_angle - true.transmission_angle
    if not known:  # the common offset is the base camera's: compare channel to channel
        kept = (np.radians(base.nominal_angle_deg) - true.transmission_angle).mean()
        assert np.degrees(abs(offset.mean() - kept)) < 0.01
        offset -= offset.mean()
        turn = np.angle(np.exp(2j * (res.polarizer_angle - (STEPS + 0.1)))) / 2
        assert np.degrees(np.ptp(turn)) < 0.05  # the fitted angles, up to their common offset
    assert np.degrees(np.abs(offset)).max() < 0.1
    assert np.abs(res.efficiency / true.efficiency - 1).max() < 5e-3
    assert np.abs(_relative(res.gain) / _relative(true.gain) - 1).max() < 1e-3
    assert np.degrees(res.transmission_angle_std).max() < 0.05
    cam = apply_to_camera(base, res)
    np.testing.assert_array_equal(cam.efficiency, res.efficiency)


def test_polarizer_pixel_maps_follow_the_pixels():
    rng = np.random.default_rng(12)
    true = perturbed_camera(CAM, rng, eff=(0.95, 0.99))
    frames, angle_map = _polarizer_frames(true, rng, STEPS, pixel_angle_deg=0.5)
    res = calibrate_polarizer(
        frames, replace(CAM, dark_offset_dn=true.dark_offset_dn), STEPS, pixel_maps=True
    )
    err = np.degrees(res.angle_map - angle_map)
    # The 0.5 deg pixel-to-pixel spread is recovered down to the shot noise of 12 frames
    # (about 15 DN on a 1000 DN modulation: 0.18 deg).
    assert np.sqrt(np.nanmean(err**2)) < 0.25
    assert np.sqrt(np.nanmean((res.efficiency_map / true.efficiency - 1) ** 2)) < 6e-3
    assert res.pixel_residual_rms_dn == pytest.approx(np.sqrt(4 + 1200 / 4), rel=0.2)


def test_polarizer_refuses_too_few_frames_and_mismatched_angles():
    rng = np.random.default_rng(13)
    frames, _ = _polarizer_frames(CAM, rng, STEPS[:6])
    with pytest.raises(UserInputError, match="at least 6"):
        calibrate_polarizer(frames[:5], CAM)
    with pytest.raises(UserInputError, match="5 angles for 6 frames"):
        calibrate_polarizer(frames, CAM, STEPS[:5])
