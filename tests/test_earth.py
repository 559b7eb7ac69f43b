"""WGS-84 normal gravity and Earth rates against published values."""

import numpy as np
import pytest

from polins.ins.earth import (
    earth_rate_n,
    gravity_n,
    normal_gravity,
    normal_gravity_gradient,
    radii_of_curvature,
    transport_rate_n,
)


def test_somigliana_equator_and_pole():
    # NIMA TR8350.2 Table 3.4: gamma_e = 9.7803253359, gamma_p = 9.8321849378 m/s^2.
    assert normal_gravity(0.0) == pytest.approx(9.7803253359, abs=1e-10)
    assert normal_gravity(np.pi / 2) == pytest.approx(9.8321849378, abs=1e-10)
    assert normal_gravity(-np.pi / 2) == pytest.approx(9.8321849378, abs=1e-10)


def test_free_air_gradient_and_vector():
    # Normal free-air gradient ~ -3.086e-6 s^-2 at mid latitudes.
    lat = np.radians(45.0)
    grad = (normal_gravity(lat, 100.0) - normal_gravity(lat, 0.0)) / 100.0
    assert grad == pytest.approx(-3.086e-6, rel=2e-3)
    # gamma is quadratic in h: the central difference equals the analytic gradient
    lats, h = np.radians([0.0, 45.6, 90.0]), np.array([-300.0, 148.7, 8000.0])
    central = 0.5 * (normal_gravity(lats, h + 10.0) - normal_gravity(lats, h - 10.0)) / 10.0
    np.testing.assert_allclose(normal_gravity_gradient(lats, h), central, rtol=1e-7)
    assert normal_gravity_gradient(lat) == pytest.approx(-3.086e-6, rel=2e-3)
    np.testing.assert_allclose(gravity_n(lat, 0.0), [0, 0, -normal_gravity(lat)])


def test_radii_and_rates():
    r_m, r_n = radii_of_curvature(0.0)
    assert r_n == pytest.approx(6378137.0) and r_m == pytest.approx(6335439.327, abs=1e-3)
    w = earth_rate_n(np.radians(45.6234))
    assert np.linalg.norm(w) == pytest.approx(7.292115e-5) and w[0] == 0.0 and w[2] > 0
    # Driving East at 10 m/s on the equator turns the frame about North by v/R.
    rho = transport_rate_n(0.0, 0.0, [10.0, 0.0, 0.0])
    np.testing.assert_allclose(rho, [0.0, 10.0 / 6378137.0, 0.0], atol=1e-18)
