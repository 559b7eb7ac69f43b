"""Round trips of the sensor calibrations (dark, flat, noise) and of the calibration check (docs/calibrate.md)."""

from dataclasses import replace

import numpy as np
import pytest
from test_calibration_scenes import dark_mosaic_of, mosaic, perturbed_camera, sensor, small_camera

from polins.calibration import (
    apply_to_camera,
    calibrate_dark,
    calibrate_flat,
    calibrate_noise,
    check,
    load_pixel_map,
    save_pixel_map,
)
from polins.errors import UserInputError

CAM = small_camera(8)


def _flat_frames(cam, rng, levels, *, read_noise=2.0, conversion_gain=2.0, prnu=None):
    """Unpolarized flats: S0 with vignetting, level per frame, optional per-pixel gain map."""
    hs, ws = cam.superpixel_shape
    v, u = np.mgrid[0:hs, 0:ws]
    vignetting = 1.0 - 0.3 * (((u - ws / 2) / ws) ** 2 + ((v - hs / 2) / hs) ** 2)
    gain = cam.gain if prnu is None else cam.gain * prnu
    dark = dark_mosaic_of(cam)
    frames = []
    for level in levels:
        ch = gain * (level * vignetting)[..., None] / 2.0 + cam.dark_offset_dn
        frames.append(
            sensor(
                mosaic(ch, cam),
                dark,
                cam,
                rng,
                read_noise_dn=read_noise,
                conversion_gain=conversion_gain,
            )
        )
    return np.stack(frames)


def test_dark_offsets_and_read_noise_within_5_percent():
    rng = np.random.default_rng(1)
    true_offset = np.array([12.0, 15.5, 9.3, 20.1])
    dsnu = rng.normal(0.0, 0.6, (*CAM.superpixel_shape, 4))
    clean = mosaic(true_offset + dsnu, CAM)
    frames = np.stack([sensor(clean, clean, CAM, rng, read_noise_dn=1.8) for _ in range(8)])
    res = calibrate_dark(frames, CAM, pixel_map=True)
    np.testing.assert_allclose(res.dark_offset_dn, true_offset + dsnu.mean(axis=(0, 1)), rtol=0.05)
    assert res.dark_offset_dn == pytest.approx(true_offset, abs=0.1)
    assert res.read_noise_dn == pytest.approx(1.8, rel=0.05)
    assert res.dsnu_dn == pytest.approx(np.full(4, 0.6), rel=0.1)
    assert res.dark_map_dn.shape == (*CAM.superpixel_shape, 4)
    cam = apply_to_camera(CAM, res)
    assert cam.read_noise_dn == res.read_noise_dn and cam.gain is not res.dark_offset_dn
    assert res.provenance["kind"] == "dark" and res.provenance["n_images"] == 8


def test_dark_refuses_one_frame_and_clipped_frames():
    rng = np.random.default_rng(2)
    zero = np.zeros(CAM.shape)
    with pytest.raises(UserInputError, match="at least 2"):
        calibrate_dark(sensor(zero + 20, zero, CAM, rng, read_noise_dn=1.0), CAM)
    clipped = np.stack([sensor(zero, zero, CAM, rng, read_noise_dn=1.0) for _ in range(2)])
    with pytest.raises(UserInputError, match="black level"):
        calibrate_dark(clipped, CAM)


def test_flat_gains_within_0p1_percent_from_20_frames(tmp_path):
    rng = np.random.default_rng(3)
    true = perturbed_camera(CAM, rng)
    prnu = 1.0 + rng.normal(0.0, 0.01, (*CAM.superpixel_shape, 4))
    prnu /= prnu.mean(axis=(0, 1))  # the channel gain is the mean of the pixel gains
    frames = _flat_frames(true, rng, rng.uniform(1200, 1600, 20), prnu=prnu, conversion_gain=20.0)
    base = replace(CAM, dark_offset_dn=true.dark_offset_dn)
    res = calibrate_flat(frames, base, pixel_map=True)
    rel = res.gain / res.gain.mean()
    truth = true.gain / true.gain.mean()
    assert np.abs(rel / truth - 1).max() < 1e-3
    assert np.all(res.gain_std < 5e-4)
    # The per-pixel map holds the pixel gains (and the flat's vignetting, common to channels).
    ratio = res.gain_map / (true.gain * prnu)
    ratio /= ratio.mean(axis=-1, keepdims=True)
    assert np.nanstd(ratio) < 3e-3  # 1% PRNU recovered to the shot noise, ~0.2% per pixel
    path = save_pixel_map(tmp_path / "gain_map", res.gain_map)
    assert path.suffix == ".npy"
    np.testing.assert_allclose(load_pixel_map(path, base), res.gain_map, rtol=1e-6)
    with pytest.raises(UserInputError, match="per-pixel map"):
        load_pixel_map(path, small_camera(4))


def test_check_sees_the_gain_error_on_flats():
    rng = np.random.default_rng(4)
    true = perturbed_camera(CAM, rng, angle_deg=0.0, eff=(1.0, 1.0))
    true = replace(true, read_noise_dn=2.0, conversion_gain_e_per_dn=2.0)
    frames = _flat_frames(true, rng, [1500.0] * 4)
    base = replace(true, gain=np.ones(4))
    calibrated = apply_to_camera(base, calibrate_flat(frames, base))
    good, bad = check(calibrated, frames, unpolarized=True), check(base, frames, unpolarized=True)
    assert good.residual_dop < 2e-4
    assert bad.residual_dop > 5e-3  # gains +-3% fake about 1% of polarization

    assert good.noise_ratio == pytest.approx(1.0, abs=0.1)
    assert bad.noise_ratio > 1.5  # shot noise (19 DN) hides part of the 3% gain error
    assert "ratio" in good.summary()


def test_the_calibrated_file_states_the_polarization_its_gains_leave():
    # instrumental_dop_std (the measurement sigma's camera-fixed part, docs/measurement.md
    # §12) from the fitted gains' standard errors, against the true gain errors' spurious
    # polarization (e_0 - e_90)/2, (e_45 - e_135)/2 over 6 calibrations: measured RMS 1.1
    ratios = []
    for seed in range(4, 10):
        rng = np.random.default_rng(seed)
        true = perturbed_camera(CAM, rng, angle_deg=0.0, eff=(1.0, 1.0))
        true = replace(true, read_noise_dn=2.0, conversion_gain_e_per_dn=2.0)
        base = replace(true, gain=np.ones(4))
        cal = apply_to_camera(base, calibrate_flat(_flat_frames(true, rng, [1500.0] * 4), base))
        e = (cal.gain / cal.gain.mean()) / (true.gain / true.gain.mean()) - 1.0
        assert cal.instrumental_dop_std is not None and cal.instrumental_dop_std < 2e-4
        ratios += [(e[0] - e[2]) / 2.0 / cal.instrumental_dop_std,
                   (e[1] - e[3]) / 2.0 / cal.instrumental_dop_std]  # fmt: skip
    assert 0.5 < float(np.sqrt(np.mean(np.square(ratios)))) < 2.0


def test_photon_transfer_read_noise_and_conversion_gain_within_5_percent():
    rng = np.random.default_rng(5)
    true = perturbed_camera(CAM, rng)
    levels = np.repeat([0.0, 100.0, 400.0, 1000.0, 2000.0, 3500.0], 2)
    frames = _flat_frames(true, rng, levels, read_noise=2.5, conversion_gain=1.6)
    res = calibrate_noise(frames, replace(CAM, dark_offset_dn=true.dark_offset_dn))
    assert res.read_noise_dn == pytest.approx(2.5, rel=0.05)
    assert res.conversion_gain_e_per_dn == pytest.approx(1.6, rel=0.05)
    assert np.abs(res.residuals).max() < 0.1
    with pytest.raises(UserInputError, match="pairs"):
        calibrate_noise(frames[:7], CAM)
