"""Camera geometry (Kannala-Brandt via OpenCV, pinhole) and the lens polarization models."""

import numpy as np
import pytest

import polins
from polins.compass.camera import (
    doubled_aop_from_evector,
    evector_from_aop,
    fov_mask,
    kannala_brandt_theta_d,
    kannala_brandt_theta_max,
    pixel_rays_c,
    project,
    unproject,
)

CAM = polins.load_camera("paper-table1")


def _random_rays(rng, n, theta_max):
    theta = np.arccos(rng.uniform(np.cos(theta_max), 1.0, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def _angle(a, b):
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def test_kannala_brandt_round_trip():
    rays = _random_rays(np.random.default_rng(0), 200_000, np.radians(85.0))
    back = unproject(CAM, project(CAM, rays))
    assert _angle(back, rays).max() < 1e-12


def test_projection_matches_spec_formula():
    rng = np.random.default_rng(1)
    rays = _random_rays(rng, 1000, np.radians(80.0))
    theta = np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2])
    td = kannala_brandt_theta_d(theta, CAM.distortion)
    rho = np.hypot(rays[:, 0], rays[:, 1])
    u = 259.10 * td / rho * rays[:, 0] + 622.49
    v = 259.20 * td / rho * rays[:, 1] + 515.06
    np.testing.assert_allclose(project(CAM, rays), np.stack([u, v], -1), atol=1e-9)


def test_lens_polynomial_peak_and_90_degree_circle():
    # docs/errata.md §1 (Sec. 4.1): d theta_d / d theta = 0.20 at 90 deg, the 90 deg circle has radius ~388.9 px.
    # The polynomial peaks where its slope 1 + 3 k1 t^2 + ... + 9 k4 t^8 vanishes: 91.99 deg
    # (docs/errata.md rounds this to "about 91.6"; the slope at 91.6 deg is still +0.04).
    h = 1e-6
    slope = (
        kannala_brandt_theta_d(np.pi / 2 + h, CAM.distortion)
        - kannala_brandt_theta_d(np.pi / 2 - h, CAM.distortion)
    ) / (2 * h)
    assert slope == pytest.approx(0.197, abs=0.002)
    assert np.degrees(kannala_brandt_theta_max(CAM.distortion)) == pytest.approx(91.99, abs=0.01)
    uv = project(CAM, np.array([[1.0, 0.0, 1e-12]]))
    assert uv[0, 0] - 622.49 == pytest.approx(388.9, abs=0.1)


def test_pinhole_round_trip(tmp_path):
    text = CAM.path.read_text()
    text = text.replace('projection = "kannala-brandt"', 'projection = "pinhole"')
    text = text.replace(
        "[0.029274, -0.013300, 0.009758, -0.004919]", "[-0.2, 0.05, 0.001, -0.0005, 0.01]"
    )
    text = text.replace("fov_max_deg = 80.0", "fov_max_deg = 40.0")
    path = tmp_path / "pin.toml"
    path.write_text(text)
    cam = polins.load_camera(path)
    rays = _random_rays(np.random.default_rng(2), 50_000, np.radians(30.0))
    assert _angle(unproject(cam, project(cam, rays)), rays).max() < 1e-10


def test_pixel_rays_cached_and_fov():
    rays = pixel_rays_c(CAM)
    assert rays.shape == (1024, 1224, 3) and pixel_rays_c(CAM) is rays
    mask = fov_mask(CAM)
    theta = np.degrees(np.arccos(rays[mask][:, 2]))
    assert theta.max() <= 80.0
    # Principal point superpixel looks along the optical axis.
    assert rays[515, 622, 2] > np.cos(np.radians(0.2))
    # Superpixel (i, j) is (u, v) = (j, i): +u is +x_c.
    assert rays[515, 900, 0] > 0.5 and abs(rays[515, 900, 1]) < 0.01


def test_occlusion_polygons_masked(tmp_path):
    text = CAM.path.read_text().replace(
        "polygons_superpixel = []", "polygons_superpixel = [[[600, 500], [650, 500], [650, 530]]]"
    )
    path = tmp_path / "occ.toml"
    path.write_text(text)
    cam = polins.load_camera(path)
    assert not fov_mask(cam)[505, 640] and fov_mask(CAM)[505, 640]


@pytest.mark.parametrize("model", ["projection", "meridian"])
def test_lens_polarization_inverse(model):
    rng = np.random.default_rng(3)
    rays = _random_rays(rng, 5000, np.radians(80.0))
    aop = rng.uniform(-np.pi / 2, np.pi / 2, 5000)
    e = evector_from_aop(aop, rays, model)
    np.testing.assert_allclose(np.sum(e * rays, -1), 0.0, atol=1e-12)  # transverse
    c2, s2 = doubled_aop_from_evector(e, rays, model).T
    np.testing.assert_allclose(c2, np.cos(2 * aop), atol=1e-12)
    np.testing.assert_allclose(s2, np.sin(2 * aop), atol=1e-12)


def test_lens_models_differ_off_axis_and_agree_on_axis():
    # docs/errata.md §1, Eq. 28: at gamma = 60 deg an image AoP 45 deg off the meridian is an E-vector
    # 26.6 deg off the meridian under P (tan phi = cos gamma tan(zeta - alpha)), 45 deg under M.
    g = np.radians(60.0)
    ray = np.array([np.sin(g), 0.0, np.cos(g)])
    e = evector_from_aop(np.radians(45.0), ray, "projection")
    c2, s2 = doubled_aop_from_evector(e, ray, "meridian")
    assert np.degrees(0.5 * np.arctan2(s2, c2)) == pytest.approx(26.57, abs=0.01)
    axis = np.array([0.0, 0.0, 1.0])
    e0 = evector_from_aop(0.3, axis, "projection")
    np.testing.assert_allclose(
        doubled_aop_from_evector(e0, axis, "meridian"), [np.cos(0.6), np.sin(0.6)], atol=1e-12
    )


def test_downscaled_camera_sees_the_same_rays():
    small = CAM.downscaled(4)
    assert small.shape == (512, 612) and small.superpixel_shape == (256, 306)
    rays = _random_rays(np.random.default_rng(4), 100, np.radians(80.0))
    np.testing.assert_allclose(
        (project(small, rays) + 0.5) * 4 - 0.5, project(CAM, rays), atol=1e-9
    )


def test_a_camera_file_without_calibration_carries_the_channels_uncertainty(tmp_path):
    """The datasheet's channels (unit gains and efficiencies, the nominal angles), no
    [[calibration]] record and no stated instrumental_*_std: the channels as delivered,
    gains +-1 %, angles +-0.5 deg. Calibrated values (the shipped paper camera's Table 1), a
    record or a stated quality keep the file's values."""
    import dataclasses

    from polins.io.model_files import camera_model_toml
    from polins.models.camera import (
        UNCALIBRATED_ANGLE_STD_DEG,
        UNCALIBRATED_GAIN_STD,
        mixing_std,
    )

    paper = polins.load_camera("paper-table1")
    assert paper.instrumental_dop_std is None and paper.instrumental_mixing_std is None
    nominal = paper.with_changes(gain=np.ones(4), efficiency=np.ones(4),
                                 transmission_angle=np.radians(paper.nominal_angle_deg))  # fmt: skip

    def loaded(camera, name):
        path = tmp_path / f"{name}.toml"
        path.write_text(camera_model_toml(camera))
        return polins.load_camera(path)

    cam = loaded(nominal, "bare")
    assert cam.instrumental_dop_std == pytest.approx(UNCALIBRATED_GAIN_STD / np.sqrt(2.0))
    # The mixing of +-0.5 deg channel angles, against 20,000 drawn angle sets: the RMS of
    # the symmetric traceless part of the S1/S2 mixing matrix of the least-squares Stokes.
    rng = np.random.default_rng(0)
    alpha0 = nominal.transmission_angle
    std = np.radians(UNCALIBRATED_ANGLE_STD_DEG)
    alpha = alpha0 + std * rng.standard_normal((20_000, 4))
    rows = 0.5 * np.stack([np.ones(4), np.cos(2 * alpha0), np.sin(2 * alpha0)], -1)
    demod = np.linalg.pinv(rows)[1:]  # (2, 4)
    true_rows = 0.5 * np.stack([np.cos(2 * alpha), np.sin(2 * alpha)], -1)  # (N, 4, 2)
    mix = np.einsum("ik,nkj->nij", demod, true_rows)  # (N, 2, 2), identity when exact
    a, b = 0.5 * (mix[:, 0, 0] - mix[:, 1, 1]), 0.5 * (mix[:, 0, 1] + mix[:, 1, 0])
    drawn = np.sqrt(0.5 * (np.mean(a**2) + np.mean(b**2)))
    assert cam.instrumental_mixing_std == pytest.approx(drawn, rel=0.03)
    assert cam.instrumental_mixing_std == pytest.approx(
        mixing_std(np.ones(4), alpha0, np.ones(4), np.full(4, std), np.zeros(4))
    )
    dark = {"kind": "dark", "date": "2026-01-01T00:00:00+00:00", "n_images": 4,
            "method": "dark frames"}  # fmt: skip
    assert loaded(nominal.with_changes(calibration=(dark,)), "dark").instrumental_dop_std is None
    stated = loaded(dataclasses.replace(nominal, instrumental_dop_std=0.0), "stated")
    assert stated.instrumental_dop_std == 0.0 and stated.instrumental_mixing_std is None
    assert loaded(paper, "paper").instrumental_dop_std is None
