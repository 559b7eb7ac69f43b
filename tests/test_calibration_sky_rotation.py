"""Round trip of the sky-rotation calibration (docs/calibrate.md#sky-rotation), scored split-half on held-out images."""

import warnings
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_calibration_scenes import dark_mosaic_of, perturbed_camera, sensor, small_camera

import polins
from polins.calibration import (
    SkyRotationResult,
    apply_to_camera,
    calibrate_dark,
    calibrate_sky_rotation,
    check,
    fit_sky_rotation,
)
from polins.compass.measure import NoiseModelWarning
from polins.errors import UserInputError
from polins.sim.render import direction_n

SUN_N = direction_n(30.0, 50.0)  # compass azimuth 30 deg, elevation 50 deg


def _sequence(cam, turns_deg, rng, radiance=None, ifov=True):
    """Clear-sky images of a zenith-looking camera turned about the vertical (= optical) axis,
    each channel seeing from its own pixel (the DoFP IFOV error, as in a real camera)."""
    radiance = np.full(len(turns_deg), 220.0) if radiance is None else radiance
    return np.stack(
        [
            polins.sim.render_raw(
                cam, SUN_N, Rotation.from_euler("z", a, degrees=True), radiance=r, rng=rng,
                ifov=ifov,
            )
            for a, r in zip(turns_deg, radiance, strict=True)
        ]
    )  # fmt: skip


def _relative_heading_rms_deg(raws, turns_deg, cam):
    """RMS heading error [deg] after removing the mean (the unidentifiable common offset)."""
    err = []
    for raw, a in zip(raws, turns_deg, strict=True):
        rot = Rotation.from_euler("z", a, degrees=True)
        with warnings.catch_warnings():  # an uncalibrated camera's noise check disagrees: expected
            warnings.simplefilter("ignore", NoiseModelWarning)
            m = polins.measure(raw, cam, sun_n=SUN_N, rot_nb_prior=rot)
        assert m.ok, m.reason
        err.append(np.angle(np.exp(1j * (m.yaw - np.radians(a)))))
    e = np.degrees(np.array(err))
    return float(np.sqrt(np.mean((e - e.mean()) ** 2)))


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(21)
    true = perturbed_camera(small_camera(8), rng)  # gains +-3%, angles +-1 deg, dark 10-40 DN
    turns = np.concatenate([[0.0], np.sort(rng.uniform(0.0, 360.0, 23))])  # unknown to the fit
    radiance = 220.0 * rng.uniform(0.9, 1.1, 24)  # exposure changes between images
    raws = _sequence(true, turns, rng, radiance)
    # The dark offsets come from dark frames (rendered with the independent forward model).
    dark = dark_mosaic_of(true)
    darks = np.stack([sensor(dark, dark, true, rng, read_noise_dn=1.5) for _ in range(4)])
    base = apply_to_camera(small_camera(8), calibrate_dark(darks, small_camera(8)))
    return true, base, turns, radiance, raws


def test_sky_rotation_recovers_relative_gains_and_angles_split_half(scene):
    true, base, turns, radiance, raws = scene
    fit, held_out = slice(0, None, 2), slice(1, None, 2)  # 12 images each
    res = fit_sky_rotation(raws[fit], base)
    assert isinstance(res, SkyRotationResult)

    def rel_gain(g):
        return g / g.mean()

    def rel_angle_deg(a):
        d = a - np.radians(true.nominal_angle_deg)
        return np.degrees(d - d.mean())

    assert np.abs(rel_gain(res.gain) / rel_gain(true.gain) - 1).max() <= 3e-3
    assert (
        np.abs(rel_angle_deg(res.transmission_angle) - rel_angle_deg(true.transmission_angle)).max()
        <= 0.2
    )
    # Conventions: the base camera's mean gain, mean angle offset and largest efficiency.
    assert res.gain.mean() == pytest.approx(base.gain.mean())
    assert rel_angle_deg(res.transmission_angle).mean() == pytest.approx(0.0, abs=1e-9)
    assert res.efficiency.max() == pytest.approx(base.efficiency.max())
    # The turns (modulo 180 deg) and the exposure changes are recovered on the way.
    dturn = np.angle(np.exp(2j * (res.turn - np.radians(turns[fit] - turns[0])))) / 2
    assert np.degrees(np.abs(dturn)).max() < 1.5  # up to the unidentifiable common offset
    aligned = fit_sky_rotation(raws[fit], base, tilt_terms=False)  # the axis is aligned here
    assert aligned.scale == pytest.approx(radiance[fit] / radiance[0], rel=2e-3)
    assert res.scale == pytest.approx(radiance[fit] / radiance[0], rel=0.03)  # up to a wobble
    assert res.noise_ratio < 1.5
    assert res.provenance["kind"] == "sky-rotation" and res.provenance["n_images"] == 12
    assert all(type(v) in (str, int, float) for v in res.provenance.values())  # TOML-ready

    # Headings on the held-out images: calibrated as good as perfect, uncalibrated far worse.
    calibrated = apply_to_camera(base, res)
    perfect = _relative_heading_rms_deg(raws[held_out], turns[held_out], true)
    after = _relative_heading_rms_deg(raws[held_out], turns[held_out], calibrated)
    before = _relative_heading_rms_deg(raws[held_out], turns[held_out], base)
    assert after <= 1.5 * perfect
    assert before > 5 * after


def test_calibrate_sky_rotation_returns_a_camera_that_explains_the_images(scene):
    true, base, _, _, raws = scene
    cam = calibrate_sky_rotation(raws[::2], base)
    assert isinstance(cam, polins.CameraModel)
    assert cam.shape == base.shape and cam.dark_offset_dn is base.dark_offset_dn
    held_out = raws[1:8:2]
    good, bad = check(cam, held_out), check(base, held_out)
    assert good.noise_ratio == pytest.approx(check(true, held_out).noise_ratio, rel=0.05)
    assert bad.noise_ratio > 1.5 * good.noise_ratio


def test_sky_rotation_with_a_tilted_turn_axis(scene):
    true, base, turns, _, _ = scene
    tilted = replace(true, mat_bc=Rotation.from_euler("x", 1.0, degrees=True).as_matrix())
    raws = _sequence(tilted, turns[::2], np.random.default_rng(23))
    res = fit_sky_rotation(raws, base)  # the tilt terms absorb the precession of the view
    d = res.transmission_angle - true.transmission_angle
    assert np.degrees(np.abs(d - d.mean())).max() <= 0.2
    assert np.abs(res.gain / res.gain.mean() / (true.gain / true.gain.mean()) - 1).max() <= 3e-3
    assert res.noise_ratio < 1.5
    with pytest.warns(
        sky_rotation_warning(), match="does not explain"
    ):  # without: biased, and it shows
        naive = fit_sky_rotation(raws, base, tilt_terms=False)
    d = naive.transmission_angle - true.transmission_angle
    assert np.degrees(np.abs(d - d.mean())).max() > 0.2
    assert naive.noise_ratio > 2.0


def test_sky_rotation_refuses_a_small_turn(scene):
    true, base, *_ = scene
    raws = _sequence(true, [0.0, 15.0, 30.0, 45.0, 60.0], np.random.default_rng(22))
    with pytest.raises(UserInputError, match="span only 60 deg"):
        fit_sky_rotation(raws, base, tilt_terms=False)
    with pytest.raises(UserInputError, match="at least 4 images"):
        fit_sky_rotation(raws[:3], base)
    raws = _sequence(true, [0.0, 22.0, 45.0, 67.0, 90.0], np.random.default_rng(24))
    res = fit_sky_rotation(raws, base)  # too few turns to tell a tilt from the channels
    assert "cannot tell a tilt" in res.notes[-1] and "tilt" not in res.provenance["method"]
    d = res.transmission_angle - true.transmission_angle
    assert np.degrees(np.abs(d - d.mean())).max() <= 0.2  # the axis is aligned: it holds
    raws = _sequence(true, [0.0, 45.0, 90.0, 135.0], np.random.default_rng(25))
    with pytest.raises(UserInputError, match="cannot fix the channel angles"):
        fit_sky_rotation(raws, base, tilt_terms=False)  # 4 evenly spaced turns: degenerate


def moving_sun_scene(point=None):
    """12 images over 20 minutes of a morning at Harbin (the sun climbs 2.7 deg and moves
    5.5 deg in azimuth), a camera with perturbed channels turning about its optical axis,
    which is the vertical or ``point`` applied to it: ``(true, base, raws, times, site)``."""
    point = Rotation.identity() if point is None else point
    import pandas as pd

    from polins.sky.ephemeris import sun_position, sun_vector_n

    rng = np.random.default_rng(26)
    true = perturbed_camera(small_camera(8), rng)
    base = small_camera(8).with_changes(dark_offset_dn=true.dark_offset_dn)  # dark known
    turns = rng.permutation(np.concatenate([[0.0], np.sort(rng.uniform(0.0, 360.0, 11))]))
    times = pd.Timestamp("2023-09-05T01:00:00Z") + pd.to_timedelta(np.linspace(0, 20, 12), "min")
    site = polins.Site(45.6234, 126.7264, 150.0)
    sun = sun_position(times, site.lat_deg, site.lon_deg, site.alt_m)
    sun_n = sun_vector_n(sun.azimuth, sun.zenith)
    raws = np.stack(
        [
            polins.sim.render_raw(
                true, s, point * Rotation.from_euler("z", a, degrees=True), rng=rng, ifov=True
            )
            for s, a in zip(sun_n, turns, strict=True)
        ]
    )
    return true, base, raws, times, site


def test_sky_rotation_with_the_sun_moving_for_20_minutes():
    """Without the clock the channel angles come out biased and the residual shows it; with
    the image times and the site the ephemeris takes the sun's motion out."""
    true, base, raws, times, site = moving_sun_scene()

    def angle_err_deg(res):
        d = res.transmission_angle - true.transmission_angle
        return float(np.degrees(np.abs(d - d.mean())).max())

    def gain_err(res):
        return float(np.abs(res.gain / res.gain.mean() / (true.gain / true.gain.mean()) - 1).max())

    with pytest.warns(sky_rotation_warning(), match="does not explain"):
        blind = fit_sky_rotation(raws, base)
    assert angle_err_deg(blind) > 0.2 and blind.noise_ratio > 3.0  # measured: 0.41 deg, 5.3
    clock = fit_sky_rotation(raws, base, times_utc=times, site=site)
    assert angle_err_deg(clock) <= 0.2 and gain_err(clock) <= 3e-3  # measured: 0.046 deg, 0.006%
    assert clock.noise_ratio < 1.5  # measured: 0.88
    assert "ephemeris" in clock.provenance["method"]
    with pytest.raises(UserInputError, match="needs both times_utc and site"):
        fit_sky_rotation(raws, base, times_utc=times)
    with pytest.raises(UserInputError, match="12 timezone-aware times"):
        fit_sky_rotation(raws, base, times_utc=times[:5], site=site)


@pytest.mark.slow
def test_sky_rotation_clock_with_a_tilted_turn_axis():
    """The same 20 minutes with the optical (turn) axis tilted 30 deg from the zenith: the
    ephemeris correction needs the axis (``axis_n``); taken as the zenith it corrects only
    part of the bias."""
    point = Rotation.from_euler("ZY", [200.0, 30.0], degrees=True)
    true, base, raws, times, site = moving_sun_scene(point)

    def angle_err_deg(res):
        d = res.transmission_angle - true.transmission_angle
        return float(np.degrees(np.abs(d - d.mean())).max())

    blind = fit_sky_rotation(raws, base)
    wrong_axis = fit_sky_rotation(raws, base, times_utc=times, site=site)
    right = fit_sky_rotation(raws, base, times_utc=times, site=site, axis_n=point.apply([0, 0, 1]))
    assert angle_err_deg(blind) > 0.3 and blind.noise_ratio > 4  # measured: 0.49 deg, 8.2
    assert wrong_axis.noise_ratio > 1.5  # measured: 0.18 deg, 2.1
    assert angle_err_deg(right) <= 0.1 and right.noise_ratio < 1.2  # measured: 0.07 deg, 0.84


@pytest.mark.slow
def test_sky_rotation_ifov_correction():
    """The DoFP IFOV error (each channel sees from its own pixel) biases the channel angles
    and efficiencies, and the noise ratio shows it; the channels interpolated to the
    superpixel centres (default) remove it. Over four turn sets the bias was 0.05-0.38 deg
    (efficiencies 0.5-1.8%, noise ratio 3-4) and 0.01-0.04 deg corrected (noise ratio
    0.8-0.9). The correction applied to images free of the error (a simulator without it)
    biases them alike: it belongs to real images."""
    rng = np.random.default_rng(21)
    true = perturbed_camera(small_camera(8), rng)
    base = small_camera(8).with_changes(dark_offset_dn=true.dark_offset_dn)  # dark known
    turns = np.concatenate([[0.0], np.sort(rng.uniform(0.0, 360.0, 11))])

    def errors(res):
        d = res.transmission_angle - true.transmission_angle
        e = res.efficiency / res.efficiency.max() - true.efficiency / true.efficiency.max()
        return float(np.degrees(np.abs(d - d.mean())).max()), float(np.abs(e).max())

    raws = _sequence(true, turns, np.random.default_rng(0))  # with the IFOV error
    fixed = fit_sky_rotation(raws, base)
    angle, eff = errors(fixed)
    assert angle <= 0.1 and eff <= 3e-3 and fixed.noise_ratio < 1.2  # 0.029 deg, 0.19%, 0.90
    assert "interpolated" in fixed.provenance["method"]
    raw_fit = fit_sky_rotation(raws, base, ifov_correction=False)
    angle, eff = errors(raw_fit)
    assert angle > 0.2 and eff > 0.01 and raw_fit.noise_ratio > 3.0  # 0.38 deg, 1.77%, 4.0
    clean = _sequence(true, turns, np.random.default_rng(0), ifov=False)
    assert fit_sky_rotation(clean, base).noise_ratio > 3.0  # the correction where none is due
    assert fit_sky_rotation(clean, base, ifov_correction=False).noise_ratio < 1.2


def _channel_errors(res, true):
    """Largest relative-gain error [-] and channel-angle error about the mean [deg]."""
    d = res.transmission_angle - true.transmission_angle
    g = res.gain / res.gain.mean() / (true.gain / true.gain.mean()) - 1
    return float(np.abs(g).max()), float(np.degrees(np.abs(d - d.mean())).max())


def test_sky_rotation_with_known_turns_and_a_wrong_sign(scene):
    """Turntable angles given: the same channels as the free fit; turns of the wrong sign
    (or unrelated ones) are refused, naming the convention."""
    true, base, turns, _, raws = scene
    res = fit_sky_rotation(raws[::2], base, turns=np.radians(turns[::2]))
    gain_err, angle_err = _channel_errors(res, true)
    assert gain_err <= 3e-3 and angle_err <= 0.1  # as without the angles
    assert "turns known" in res.provenance["method"] and res.noise_ratio < 1.5
    with pytest.raises(UserInputError, match=r"run against the images' polarization.*negate"):
        fit_sky_rotation(raws[::2], base, turns=-np.radians(turns[::2]))
    with pytest.raises(UserInputError, match="disagree with the images' polarization"):
        fit_sky_rotation(raws[::2], base, turns=np.radians(np.sort(turns[::2]) * 0.5))
    with pytest.raises(UserInputError, match="turns needs 12 finite angles"):
        fit_sky_rotation(raws[::2], base, turns=np.radians(turns[:5]))


def test_sky_rotation_half_turn_with_known_angles():
    """A turntable's half turn (0:20:180 deg, the angles known, the axis tilted 0.3 deg):
    not refused; the fit says whether the tilt terms were identified, and the channels come
    out within a few tenths of a degree."""
    rng = np.random.default_rng(31)
    true = perturbed_camera(small_camera(8), rng)
    base = small_camera(8).with_changes(dark_offset_dn=true.dark_offset_dn)
    turns = np.arange(0.0, 181.0, 20.0)
    tilted = replace(true, mat_bc=Rotation.from_euler("x", 0.3, degrees=True).as_matrix())
    raws = _sequence(tilted, turns, rng)
    res = fit_sky_rotation(raws, base, turns=np.radians(turns))
    assert res.notes and "turns known (180 deg)" in res.notes[0]
    gain_err, angle_err = _channel_errors(res, true)
    assert gain_err <= 5e-3 and angle_err <= 0.6


def test_no_degenerate_calibration_from_bad_starts(scene, monkeypatch):
    """The fit starts from the ring-mean AoP; started instead from turns off by up to 40 deg,
    it still returns the physical channels or refuses: a degenerate array (channels pairing
    up, gains far from 1) is never returned."""
    import polins.calibration.sky_rotation as sky_rotation

    true, base, _, _, raws = scene
    good = sky_rotation.polarization_turns
    rng = np.random.default_rng(5)
    for _ in range(3):
        offsets = np.radians(rng.uniform(-40.0, 40.0, 12))
        offsets[0] = 0.0
        monkeypatch.setattr(sky_rotation, "polarization_turns",
                            lambda y, cam, o=offsets: good(y, cam) + o)  # fmt: skip
        try:
            res = fit_sky_rotation(raws[::2], base, tilt_terms=False)
        except UserInputError as exc:
            assert any(w in str(exc) for w in ("physical", "span", "cannot be fitted"))
            continue
        assert sky_rotation.degeneracy(res.gain, res.transmission_angle, res.efficiency, base) == ""
        gain_err, angle_err = _channel_errors(res, true)
        assert gain_err <= 3e-3 and angle_err <= 0.1
    # The degenerate array a free joint fit finds on a real half-turn sequence is named.
    deg = sky_rotation.degeneracy(np.array([1.0, 0.30, 0.98, 1.72]),
                                  np.radians([-21.5, -22.5, 156.5, 157.5]), np.ones(4), base)  # fmt: skip
    assert "gains" in deg
    deg = sky_rotation.degeneracy(np.ones(4), np.radians([-21.5, -22.5, 156.5, 157.5]),
                                  np.ones(4), base)  # fmt: skip
    assert "pairing up" in deg


def test_a_residual_above_the_noise_is_described(scene):
    """A tilted turn axis fitted without the tilt terms: the fit warns, and describes the
    residual by harmonics of the turn (shares of its power, at most 100 % together) and by
    ring."""
    true, base, turns, _, _ = scene
    tilted = replace(true, mat_bc=Rotation.from_euler("x", 2.0, degrees=True).as_matrix())
    raws = _sequence(tilted, turns[::2], np.random.default_rng(23))
    with pytest.warns(sky_rotation_warning(), match="harmonic 1"):
        res = fit_sky_rotation(raws, base, tilt_terms=False)
    shares = [float(p.split(" % at harmonic")[0].rsplit(" ", 1)[-1])
              for p in res.residual_pattern.split(", ")[:5]]  # fmt: skip
    assert 0.0 <= min(shares) and sum(shares) <= 100.5 and res.noise_ratio > 3.0
    assert "by ring radius" in res.residual_pattern


def sky_rotation_warning():
    from polins.calibration import SkyRotationResidualWarning

    return SkyRotationResidualWarning


def test_check_finds_a_wrong_mosaic_layout(scene):
    """Sky frames tell which mosaic positions hold orthogonal channels: the file's layout
    passes, one with the 45 and 90 deg positions swapped is named (its residual is the
    polarized signal, the right pairing's about the channel noise)."""
    _, base, _, _, raws = scene
    assert check(base, raws[:3]).layout_note == ""
    at = np.array(base.channel_at)
    swapped = np.where(at == 1, 2, np.where(at == 2, 1, at))  # 45 <-> 90 deg positions
    note = check(base.with_changes(channel_at=swapped), raws[:3]).layout_note
    assert "labelled 0 and 45 deg (and 90, 135) as orthogonal" in note
    ratio = float(note.split("residual ")[1].split(" DN")[0]) / float(
        note.split("against ")[1].split(" DN")[0]
    )
    assert ratio < 0.4  # measured 0.33 (the channels differ by +-3 % in gain)
