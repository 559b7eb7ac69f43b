"""Sky rotation on a narrow field about the zenith: a pinhole looking up, turned through a half
turn by unknown angles, rendered by the independent renderer (polins.sim.realsky) with the
channel-dependent radial shading of a real DoFP camera (docs/calibrate.md#sky-rotation)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_calibration_scenes import mosaic, perturbed_camera, response, small_camera
from test_sun_free import narrow_camera

import polins
from polins.calibration import fit_sky_rotation
from polins.calibration import sky_rotation as sky_rotation_module
from polins.calibration.turntable import score_turntable
from polins.cli.calibrate import summary_lines
from polins.errors import UserInputError
from polins.sim.realsky import RealSky, render_real_raw

SHADING = np.array([0.19, -0.02, -0.19, 0.03])  # per squared field angle, as measured
SUN_N = polins.sun_vector_n(np.radians(120.0), np.radians(45.0))
LOW_SUN_N = polins.sun_vector_n(np.radians(120.0), np.radians(82.0))  # the zenith at 90 deg
TURNS_DEG = np.arange(0.0, 181.0, 10.0)  # a turntable's half turn
HELD_OUT_DEG = np.arange(5.0, 180.0, 20.0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    narrow = narrow_camera(tmp_path_factory.mktemp("narrow"), factor=8)
    base = narrow.with_changes(gain=np.ones(4), efficiency=np.ones(4))  # ideal channels
    rng = np.random.default_rng(41)
    true = base.with_changes(
        transmission_angle=base.transmission_angle + np.radians(rng.uniform(-0.5, 0.5, 4))
    )
    gain = rng.uniform(-0.02, 0.02, 4)
    sky = RealSky(zenith_dn=150.0, gain_residual=gain, channel_shading=SHADING, ground=0.0)

    def render(zenith_dn, sun_n=SUN_N):
        return np.stack([
            render_real_raw(true, sun_n, Rotation.from_euler("z", a, degrees=True),
                            RealSky(**{**sky.__dict__, "zenith_dn": z}), rng)
            for a, z in zip(TURNS_DEG, zenith_dn, strict=True)
        ])  # fmt: skip

    jumps = 150.0 * rng.uniform(0.93, 1.07, TURNS_DEG.size)  # an automatic exposure
    sequences = {
        "fixed": render(np.full(TURNS_DEG.size, 150.0)),
        "jumping": render(jumps),
        "low sun, jumping": render(jumps, LOW_SUN_N),
        "held out": np.stack(
            [
                render_real_raw(true, SUN_N, Rotation.from_euler("z", a, degrees=True), sky, rng)
                for a in HELD_OUT_DEG
            ]
        ),
    }
    return base, true, 1.0 + gain, sequences


def _centre_gain_error(res, base, gain):
    """Largest error of the relative channel gains at the principal point [-]."""
    g = res.gain
    if res.gain_map is not None:  # at the principal point the map holds the channel gains
        g = res.gain_map[round(base.camera_matrix[1, 2]), round(base.camera_matrix[0, 2])]
    return float(np.abs(g / g.mean() - gain / gain.mean()).max())


def test_unknown_turns_on_a_narrow_half_turn(scene):
    """The turns and the channels come out of the ring means alone, the radial shading with
    them: the fit explains the images to the noise, and the shading's gain map is written."""
    base, true, gain, sequences = scene
    res = fit_sky_rotation(sequences["fixed"], base, ifov_correction=False)
    assert sky_rotation_module.degeneracy(res.gain, res.transmission_angle, res.efficiency,
                                          base) == ""  # fmt: skip
    dturn = np.angle(np.exp(2j * (res.turn - np.radians(TURNS_DEG)))) / 2
    assert np.degrees(np.abs(dturn)).max() < 0.2
    ref = res.radial_gain  # the fitted shading, per squared normalised radius (tan^2 theta)
    shading = SHADING - SHADING.mean()
    assert ref == pytest.approx(shading, abs=0.02)  # measured within 0.01
    assert res.gain_map is not None and res.noise_ratio < 1.5
    lines = summary_lines(res, base)  # what polins calibrate prints and writes as comments
    assert (
        f"gain_map: per-pixel, {base.superpixel_shape[0]} x {base.superpixel_shape[1]} x 4" in lines
    )
    assert _centre_gain_error(res, base, gain) < 2e-3  # measured 0.0006
    d = np.degrees(res.transmission_angle - true.transmission_angle)
    assert np.abs(d - d.mean()).max() < 0.1
    # Relative headings on held-out frames (sun-free, as polins calibrate check --turns-deg):
    # the shading's corners are 13 % apart in the 0/90 channels, which only the map corrects
    # (measured 0.015 deg, RMS(err/sigma) 0.63; without the map 0.61 deg; uncalibrated 1.8).
    calibrated = base.with_changes(**res.camera_changes())
    score = score_turntable(sequences["held out"], calibrated, np.radians(HELD_OUT_DEG))
    assert np.degrees(score.rmse) < 0.05 and 0.4 < score.rms_z < 1.5 and score.max_z < 4.0
    no_map = calibrated.with_changes(gain_map=None)
    worse = score_turntable(sequences["held out"], no_map, np.radians(HELD_OUT_DEG))
    assert worse.rmse > 10 * score.rmse


def test_no_degenerate_calibration_from_bad_starts_on_a_narrow_field(scene, monkeypatch):
    """Turn starts off by up to 40 deg, or an exposure that jumps from image to image: the fit
    returns the physical channels or refuses with the reason, never a degenerate array. (On
    these skies the rings differ enough for a free exposure per image: gains within 0.0006.)"""
    base, _, gain, sequences = scene
    for name in ("jumping", "low sun, jumping"):
        res = fit_sky_rotation(sequences[name], base, ifov_correction=False)
        assert "free exposure" in res.notes[0] and _centre_gain_error(res, base, gain) < 2e-3
    good = sky_rotation_module.polarization_turns
    rng = np.random.default_rng(7)
    for _ in range(3):
        offsets = np.radians(rng.uniform(-40.0, 40.0, TURNS_DEG.size))
        offsets[0] = 0.0
        monkeypatch.setattr(sky_rotation_module, "polarization_turns",
                            lambda y, cam, o=offsets: good(y, cam) + o)  # fmt: skip
        try:
            res = fit_sky_rotation(sequences["fixed"], base, ifov_correction=False,
                                   tilt_terms=False)  # fmt: skip
        except UserInputError as exc:
            assert "give the turns" in str(exc) or "span" in str(exc)
            continue
        assert _centre_gain_error(res, base, gain) < 2e-3


@pytest.mark.slow
def test_a_uniform_field_needs_a_fixed_exposure_or_the_turns():
    """A field of one polarization (every ring alike, as a narrow field with the zenith 90 deg
    from the sun nearly is): with the exposure fixed the turns and gains come out; with a free
    exposure per image a turn error uneven over the turn trades exactly against the gains'
    differential, and the fit refuses instead of returning one of them."""
    rng = np.random.default_rng(43)
    base = small_camera(8)
    true = perturbed_camera(base, rng, dark=(0.0, 0.0))
    turns = np.radians(TURNS_DEG[::2])
    v, u = np.mgrid[0 : base.superpixel_shape[0], 0 : base.superpixel_shape[1]]
    s0 = 200.0 * (1.0 - 0.3 * np.hypot(u - 76.0, v - 64.0) ** 2 / 100.0**2)  # vignetting

    def frames(exposure):
        out = []
        for phi, e in zip(turns, exposure, strict=True):
            lin = 0.7 * np.exp(-2j * phi)  # the pattern turns by -phi
            stokes = e * np.stack([s0, s0 * lin.real, s0 * lin.imag], -1)
            clean = mosaic(response(stokes, true.gain, true.efficiency,
                                    true.transmission_angle, 0.0), base)  # fmt: skip
            out.append(np.round(clean + rng.normal(0.0, 1.5, clean.shape)))
        return np.stack(out)

    res = fit_sky_rotation(frames(np.ones(turns.size)), base, n_rings=6, ifov_correction=False)
    rel = res.gain / res.gain.mean()
    assert np.abs(rel - true.gain / true.gain.mean()).max() < 2e-3
    with pytest.raises(UserInputError, match="give the turns"):
        fit_sky_rotation(frames(rng.uniform(0.93, 1.07, turns.size)), base, n_rings=6,
                         ifov_correction=False)  # fmt: skip


def test_the_residual_report_names_a_camera_fixed_polarization():
    """A residual that does not turn with the camera and differs between the 0 and 90 deg
    channels, growing with the ring radius (a shading beyond the fitted one): the report
    puts it at harmonic 0, as a camera-fixed polarization, growing ring by ring."""
    theta = -np.radians(TURNS_DEG)
    radius = np.linspace(0.0, 0.25, 6)
    residuals = np.zeros((theta.size, radius.size, 4))
    residuals[..., 0] = 10.0 * radius
    residuals[..., 2] = -10.0 * radius
    text = sky_rotation_module.residual_pattern(residuals, np.full(4, 0.1), theta, radius)
    assert "100 % at harmonic 0" in text and "100 % a camera-fixed polarization" in text
    by_ring = [float(v) for v in text.rsplit("[", 1)[1].split("]")[0].split(", ")]
    assert by_ring == sorted(by_ring) and by_ring[0] == 0.0
