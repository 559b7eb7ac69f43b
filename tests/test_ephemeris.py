"""Sun position against published NREL SPA values and the paper's Table 1 sun."""

import datetime as dt

import numpy as np
import pandas as pd
import pytest

import polins
from polins.sky.ephemeris import sun_azimuth_zenith


def test_nrel_spa_worked_example():
    # Reda & Andreas (2004), NREL/TP-560-34302, Table A5.1 / A5.2: Golden, CO.
    sun = polins.sun_position(
        "2003-10-17T12:30:30-07:00",
        39.742476,
        -105.1786,
        1830.14,
        pressure_pa=82000.0,
        temperature_c=11.0,
        delta_t_s=67.0,
    )
    assert np.degrees(sun.zenith) == pytest.approx(50.11162, abs=1e-3)
    assert np.degrees(sun.azimuth) == pytest.approx(194.34024, abs=1e-3)


def test_paper_table1_sun_is_harbin_at_1506():
    # Paper Table 1: azimuth 247.11 deg, zenith 60.21 deg; Harbin on 2023-09-05 (Table 3).
    t = pd.date_range("2023-09-05 15:05", "2023-09-05 15:08", freq="1s", tz="Asia/Shanghai")
    sun = polins.sun_position(t, 45.6234, 126.7264, 148.74)
    i = int(np.argmin(np.abs(np.degrees(sun.azimuth) - 247.11)))
    assert np.degrees(sun.azimuth[i]) == pytest.approx(247.11, abs=0.01)
    assert np.degrees(sun.zenith[i]) == pytest.approx(60.21, abs=0.1)
    assert t[i].strftime("%H:%M") == "15:06"


def test_naive_datetime_is_an_error():
    with pytest.raises(ValueError, match="naive datetime"):
        polins.sun_position(dt.datetime(2023, 9, 5, 15, 6), 45.6, 126.7)
    with pytest.raises(ValueError, match="naive datetime"):
        polins.sun_position(["2023-09-05T07:00Z", "2023-09-05T07:01"], 45.6, 126.7)


def test_degrees_are_checked():
    with pytest.raises(ValueError, match="lat_deg"):
        polins.sun_position("2023-09-05T07:00Z", 95.0, 126.7)


def test_vectorised_and_time_zones_agree():
    times = pd.date_range("2023-09-05 03:00", periods=5, freq="1h", tz="UTC")
    sun = polins.sun_position(times, 45.6234, 126.7264)
    assert sun.azimuth.shape == (5,)
    local = [x.tz_convert("Asia/Shanghai").to_pydatetime() for x in times]
    sun_local = polins.sun_position(local, 45.6234, 126.7264)
    np.testing.assert_allclose(sun_local.azimuth, sun.azimuth, atol=1e-12)
    one = polins.sun_position(local[2], 45.6234, 126.7264)
    assert np.ndim(one.azimuth) == 0 and one.zenith == pytest.approx(sun.zenith[2])


def test_sun_vector_enu_and_inverse():
    # Sun due East on the horizon is +x_n; due North at 60 deg zenith has no East component.
    np.testing.assert_allclose(polins.sun_vector_n(np.pi / 2, np.pi / 2), [1, 0, 0], atol=1e-15)
    s = polins.sun_vector_n(0.0, np.radians(60.0))
    np.testing.assert_allclose(s, [0, np.sin(np.radians(60)), 0.5], atol=1e-15)
    rng = np.random.default_rng(1)
    az, zen = rng.uniform(0, 2 * np.pi, 50), rng.uniform(0.01, np.pi - 0.01, 50)
    back = sun_azimuth_zenith(polins.sun_vector_n(az, zen))
    np.testing.assert_allclose(back.azimuth, az, atol=1e-12)
    np.testing.assert_allclose(back.zenith, zen, atol=1e-12)
