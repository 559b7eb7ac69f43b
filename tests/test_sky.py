"""Sky polarization models: Rayleigh invariants and the Berry four-neutral-point sky."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from polins.sky.scattering import (
    berry_dop,
    berry_evector,
    berry_neutral_points,
    berry_w,
    rayleigh_dop,
    rayleigh_evector,
    rayleigh_radiance,
)

UP = np.array([0.0, 0.0, 1.0])


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rays(rng, n, upper=True):
    p = _unit(rng.normal(size=(n, 3)))
    if upper:
        p[:, 2] = np.abs(p[:, 2])
    return p


def _axial_angle(a, b):
    """Angle [rad] between two axial (sign-free) vectors."""
    a, b = _unit(a), _unit(b)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.abs(np.sum(a * b, axis=-1)))


SUNS = [_unit([0.3, -0.5, 0.6]), _unit([-0.8, -0.3, 0.5]), np.array([0.0, 0.0, 1.0])]


# ------------------------------------------------------------------------- Rayleigh
@pytest.mark.parametrize("sun", SUNS)
def test_rayleigh_evector_perpendicular_to_sun_and_ray(sun):
    rays = _rays(np.random.default_rng(0), 5000)
    e = rayleigh_evector(sun, rays)
    np.testing.assert_allclose(np.linalg.norm(e, axis=-1), 1.0, atol=1e-12)
    assert np.abs(e @ sun).max() < 1e-12
    assert np.abs(np.sum(e * rays, axis=-1)).max() < 1e-12


def test_rayleigh_dop_zero_at_sun_and_antisun_max_at_90():
    sun = SUNS[0]
    perp = _unit(np.cross(sun, [1.0, 0.0, 0.0]))
    assert rayleigh_dop(sun, sun, 0.75) == pytest.approx(0.0, abs=1e-15)
    assert rayleigh_dop(sun, -sun, 0.75) == pytest.approx(0.0, abs=1e-15)
    assert rayleigh_dop(sun, perp, 0.75) == pytest.approx(0.75, abs=1e-15)
    # d = d_max sin^2 / (1 + cos^2) rises monotonically from the sun to 90 deg.
    theta = np.linspace(0.0, np.pi / 2, 91)
    rays = np.cos(theta)[:, None] * sun + np.sin(theta)[:, None] * perp
    d = rayleigh_dop(sun, rays, 0.6)
    assert np.all(np.diff(d) > 0) and d.max() == pytest.approx(0.6)
    np.testing.assert_allclose(d, 0.6 * np.sin(theta) ** 2 / (1 + np.cos(theta) ** 2), atol=1e-15)
    with pytest.raises(ValueError, match="dop_max"):
        rayleigh_dop(sun, perp, 1.2)


def test_rayleigh_radiance_one_plus_cos2():
    sun = SUNS[1]
    perp = _unit(np.cross(sun, [0.0, 0.0, 1.0]))
    assert rayleigh_radiance(sun, perp, 220.0) == pytest.approx(220.0)
    assert rayleigh_radiance(sun, sun, 220.0) == pytest.approx(440.0)


# ------------------------------------------------------------------------- Berry
@pytest.mark.parametrize("sun", SUNS)
def test_berry_reduces_to_rayleigh(sun):
    rays = _rays(np.random.default_rng(1), 20_000)
    eb, er = berry_evector(sun, rays, 0.0), rayleigh_evector(sun, rays)
    valid = np.isfinite(er).all(axis=-1)
    assert _axial_angle(eb[valid], er[valid]).max() < 1e-12
    np.testing.assert_allclose(
        berry_dop(sun, rays, 0.75, 0.0), rayleigh_dop(sun, rays, 0.75), atol=1e-14
    )
    # Continuity: merging the neutral points approaches Rayleigh smoothly away from the sun.
    far = np.abs(rays @ sun) < np.cos(np.radians(10.0))
    dev = [_axial_angle(berry_evector(sun, rays, s), er)[far].max() for s in (1e-2, 1e-3)]
    assert dev[1] < dev[0] / 50 and dev[1] < 1e-5


@pytest.mark.parametrize("sun", SUNS[:2])
def test_berry_evector_perpendicular_to_ray_and_covariant(sun):
    rng = np.random.default_rng(2)
    rays = _rays(rng, 5000)
    e = berry_evector(sun, rays, np.radians(35.0))
    np.testing.assert_allclose(np.linalg.norm(e, axis=-1), 1.0, atol=1e-12)
    assert np.abs(np.sum(e * rays, axis=-1)).max() < 1e-12
    # The field is geometric: rotating sun, rays and the vertical together rotates it.
    rot = Rotation.from_rotvec([0.4, -1.1, 0.7])
    e_rot = berry_evector(rot.apply(sun), rot.apply(rays), np.radians(35.0), up=rot.apply(UP))
    assert _axial_angle(e_rot, rot.apply(e)).max() < 1e-9


def test_berry_neutral_points_and_dop():
    sun = SUNS[0]
    sep = np.radians(40.0)
    pts = berry_neutral_points(sun, sep)
    # On the solar vertical, sep/2 above and below the sun; antipodal pairs.
    normal = _unit(np.cross(sun, UP))
    assert np.abs(pts @ normal).max() < 1e-12
    np.testing.assert_allclose(pts @ sun, [np.cos(sep / 2)] * 2 + [-np.cos(sep / 2)] * 2)
    assert pts[0, 2] > sun[2] > pts[1, 2]  # Babinet above, Brewster below the sun
    assert pts[2, 2] > -sun[2] > pts[3, 2]  # Arago above, fourth below the anti-sun
    np.testing.assert_allclose(berry_dop(sun, pts, 0.75, sep), 0.0, atol=1e-15)
    # The sun itself is polarized (between Babinet and Brewster), DoP <= d_max everywhere.
    assert berry_dop(sun, sun, 0.75, sep) > 0.005
    rays = _rays(np.random.default_rng(3), 20_000, upper=False)
    d = berry_dop(sun, rays, 0.75, sep)
    assert d.min() >= 0 and d.max() <= 0.75 + 1e-12
    np.testing.assert_allclose(np.abs(berry_w(sun, rays, sep)), (2 * d / 0.75) / (1 + d / 0.75))
    with pytest.raises(ValueError, match="neutral_sep"):
        berry_neutral_points(sun, -0.1)


def test_berry_neutral_point_has_index_one_half():
    # Around each neutral point the E-vector line turns by +pi (index +1/2) instead of the
    # 2 pi (index +1) of the Rayleigh singularity at the sun.
    sun = SUNS[0]
    sep = np.radians(40.0)
    for point, sep_used, expected in [(0, sep, 0.5), (1, sep, 0.5), (0, 0.0, 1.0)]:
        centre = berry_neutral_points(sun, sep_used)[point]
        a = _unit(np.cross(centre, UP))
        b = np.cross(centre, a)
        phi = np.linspace(0.0, 2 * np.pi, 721)
        r = np.radians(2.0)
        loop = np.cos(r) * centre + np.sin(r) * (
            np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b
        )
        e = berry_evector(sun, loop, sep_used)
        # Angle of the line in the local tangent basis (a_i, b_i) of each loop point.
        a_i = _unit(a - (loop @ a)[:, None] * loop)
        b_i = np.cross(loop, a_i)
        ang = np.unwrap(2 * np.arctan2(np.sum(e * b_i, -1), np.sum(e * a_i, -1))) / 2
        turn = (ang[-1] - ang[0]) / (2 * np.pi)
        assert turn == pytest.approx(expected, abs=1e-6)


def test_berry_symmetric_about_solar_meridian():
    # Mirror the rays in the solar vertical plane: the E-vector mirrors too, and the DoP is
    # unchanged (the model has no handedness).
    sun = SUNS[1]
    normal = _unit(np.cross(sun, UP))
    mirror = np.eye(3) - 2 * np.outer(normal, normal)
    rays = _rays(np.random.default_rng(4), 3000)
    sep = np.radians(30.0)
    e, e_m = berry_evector(sun, rays, sep), berry_evector(sun, rays @ mirror, sep)
    assert _axial_angle(e_m, e @ mirror).max() < 1e-9
    np.testing.assert_allclose(
        berry_dop(sun, rays @ mirror, 0.7, sep), berry_dop(sun, rays, 0.7, sep)
    )
