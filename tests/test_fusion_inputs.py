"""Validation of the fusion input tables: clear ValueErrors for bad IMU / measurement data."""

import numpy as np
import pandas as pd
import pytest

import polins
from polins.errors import UserInputError
from polins.fusion.inputs import validate_imu, validate_measurements
from polins.fusion.items import items_from_table


def _imu(n=400, rate=200.0):
    rng = np.random.default_rng(0)
    t = np.arange(n) / rate
    df = pd.DataFrame({"t": t})
    for c, v in zip(("gx", "gy", "gz"), (0.01, -0.02, 0.05), strict=True):
        df[c] = v + 1e-3 * rng.standard_normal(n)
    for c, v in zip(("ax", "ay", "az"), (0.1, -0.05, 9.81), strict=True):
        df[c] = v + 1e-2 * rng.standard_normal(n)
    return df


def test_valid_imu_passes():
    arrays = validate_imu(_imu())
    assert arrays.t.shape == (400,) and arrays.gyro_b.shape == (400, 3)
    assert arrays.dt == pytest.approx(0.005)


def test_missing_columns():
    with pytest.raises(ValueError, match=r"lacks columns \['gz'\]"):
        validate_imu(_imu().drop(columns="gz"))
    with pytest.raises(ValueError, match="DataFrame"):
        validate_imu(np.zeros((10, 7)))


def test_duplicated_and_non_monotonic_timestamps():
    df = _imu()
    df.loc[10, "t"] = df.loc[9, "t"]
    with pytest.raises(ValueError, match=r"duplicated timestamp.*rows 9 and 10"):
        validate_imu(df)
    df = _imu()
    df.loc[[20, 21], "t"] = df.loc[[21, 20], "t"].to_numpy()
    with pytest.raises(ValueError, match=r"not monotonic.*row 21"):
        validate_imu(df)


def test_nan_samples_are_dropped_and_reported():
    # a data fault (docs/faults.md): the sample is dropped with an event; a NaN time is not
    df = _imu()
    df.loc[33, "ay"] = np.nan
    arrays = validate_imu(df)
    assert arrays.t.size == 399 and 0.165 not in arrays.t
    assert [(e.t, e.kind) for e in arrays.events] == [(pytest.approx(0.165), "imu-nonfinite")]
    df = _imu()
    df.loc[5, "t"] = np.nan
    with pytest.raises(ValueError, match="t is NaN"):
        validate_imu(df)


def test_gaps_are_reported():
    # gaps longer than max_gap_s (default 5 intervals) are reported to the fusion, which
    # skips the measurements inside and inflates the covariance (tests/test_robustness.py)
    df = _imu().drop(index=range(100, 140)).reset_index(drop=True)
    arrays = validate_imu(df)
    assert arrays.gap_spans == ((arrays.t[99], arrays.t[100]),)
    assert arrays.t[100] - arrays.t[99] == pytest.approx(0.205)
    (gap,) = arrays.gaps  # the "gap" item at the sample after it, the gap's length as std
    assert gap.kind == "gap" and gap.t == arrays.t[100] and gap.std == pytest.approx(0.205)
    assert [e.kind for e in arrays.events] == ["imu-gap"]
    # an explicit, larger limit bridges it
    assert validate_imu(df, max_gap_s=0.5).gaps == ()


def test_unit_mistakes_detected():
    df = _imu()
    df[["gx", "gy", "gz"]] = np.degrees(df[["gx", "gy", "gz"]]) * 300.0  # a fast turn in deg/s
    with pytest.raises(ValueError, match="deg/s"):
        validate_imu(df)
    df = _imu()
    df[["ax", "ay", "az"]] /= 9.80665
    with pytest.raises(ValueError, match="looks like g"):
        validate_imu(df)
    df = _imu()
    df[["ax", "ay", "az"]] *= 1000.0 / 9.80665
    with pytest.raises(ValueError, match="looks like mg"):
        validate_imu(df)


def test_measurement_validation():
    good = pd.DataFrame({"t": [0.1, 0.3], "yaw": [0.2, np.nan], "yaw_std": [0.01, 0.01]})
    assert validate_measurements(good) is good
    assert len(validate_measurements(None)) == 0
    with pytest.raises(ValueError, match="lacks column 't'"):
        validate_measurements(good.drop(columns="t"))
    with pytest.raises(ValueError, match=r"incomplete yaw columns, missing \['yaw_std'\]"):
        validate_measurements(good.drop(columns="yaw_std"))
    with pytest.raises(ValueError, match="no measurement columns"):
        validate_measurements(pd.DataFrame({"t": [0.0], "foo": [1.0]}))
    with pytest.raises(ValueError, match="duplicated timestamp"):
        validate_measurements(pd.DataFrame({"t": [0.1, 0.1], "yaw": [0, 0], "yaw_std": [1, 1]}))
    with pytest.raises(ValueError, match="radians"):
        validate_measurements(pd.DataFrame({"t": [0.1], "yaw": [90.0], "yaw_std": [0.01]}))
    with pytest.raises(ValueError, match=r"yaw_std=10 at row 0 must be <= 3.142 \(radians"):
        validate_measurements(pd.DataFrame({"t": [0.1], "yaw": [0.1], "yaw_std": [10.0]}))
    # a non-positive or non-finite sigma is a data fault: its row is rejected, not the table
    bad = pd.DataFrame({"t": [0.1, 0.2], "yaw": [0.1, 0.1], "yaw_std": [0.0, np.inf]})
    items = items_from_table(validate_measurements(bad))
    assert [it.valid for it in items] == [False, False]
    assert items[1].reason == "invalid yaw_std=inf: a 1-sigma must be finite and > 0"
    sun = {f"sun_b{c}": [v] for c, v in zip("xyz", (0.0, 0.0, 2.0), strict=True)}
    sun |= {f"sun_n{c}": [v] for c, v in zip("xyz", (0.0, 0.6, 0.8), strict=True)}
    with pytest.raises(ValueError, match="sun_b at row 0 has norm 2"):
        validate_measurements(pd.DataFrame({"t": [0.0], **sun, "sun_std": [0.01]}))


def test_items_from_frame_rules():
    sun_b, sun_n = (0.3, 0.0, np.sqrt(0.91)), (0.0, 0.6, 0.8)
    df = pd.DataFrame(
        {
            "t": [0.0, 0.1, 0.2, 0.3],
            "yaw": [0.1, 0.2, np.nan, 0.4],
            "yaw_std": [0.01, 0.01, 0.01, 0.01],
            "sun_bx": [sun_b[0], np.nan, np.nan, sun_b[0]],
            "sun_by": [sun_b[1], np.nan, np.nan, sun_b[1]],
            "sun_bz": [sun_b[2], np.nan, np.nan, sun_b[2]],
            "sun_nx": [sun_n[0]] * 4,
            "sun_ny": [sun_n[1]] * 4,
            "sun_nz": [sun_n[2]] * 4,
            "sun_std": [0.002, np.nan, np.nan, 0.002],
            "zupt_std": [np.nan, 0.02, np.nan, np.nan],
        }
    )
    items = items_from_table(df)
    assert [(it.kind, it.valid) for it in items] == [
        ("sun", True),
        ("yaw", True),
        ("zupt", True),
        ("yaw", False),
        ("sun", True),
    ]
    # yaw instead of the sun vector when asked
    kinds = [it.kind for it in items_from_table(df, use_sun=False)]
    assert kinds == ["yaw", "yaw", "zupt", "yaw", "yaw"]
    # the streaming helper gives the same items row by row
    from polins.fusion.items import measurement_items

    row = df.iloc[0]
    one = measurement_items(
        0.0,
        yaw=row.yaw,
        yaw_std=row.yaw_std,
        sun_b=sun_b,
        sun_n=sun_n,
        sun_std=row.sun_std,
    )
    assert [it.kind for it in one] == ["sun"] and one[0].std == items[0].std


def test_fuse_reports_input_errors():
    imu = _imu()
    imu.loc[3, "t"] = np.nan
    with pytest.raises(ValueError, match="t is NaN"):
        polins.fuse(imu, None, rot_nb0=polins.rot_nb_from_euler(0, 0, 0), lat_deg=45.0, lon_deg=0)
    with pytest.raises(
        UserInputError, match=r"unknown filter option .nhc_sdt. \(did you mean .nhc_std.\?\)"
    ):
        polins.fuse(_imu(), None, lat_deg=45.0, lon_deg=0.0, nhc_sdt=0.1)
    with pytest.raises(ValueError, match="backend='kalman'"):
        polins.fuse(_imu(), None, backend="kalman")


def test_measurements_become_the_rows_fuse_takes():
    from scipy.spatial.transform import Rotation

    from polins.compass.measurement import Measurement

    sun_b = np.array([0.6, 0.0, 0.8])
    good = Measurement(ok=True, reason="", method="compensated", yaw=0.3, yaw_std=0.01,
                       yaw_std_meas=0.008, heading_deg=72.8, sun_b=sun_b, sun_l=sun_b,
                       sun_c=sun_b, sun_std=0.01, epsilon=np.nan, epsilon_std=np.nan,
                       n_pixels=5000, eigen_gap=0.9, residual_rms=1.0)  # fmt: skip
    refused = Measurement.refused("compensated", "too few valid pixels")
    prior = Rotation.from_euler("ZYX", [0.3, 0.02, -0.01])
    table = polins.measurement_table([good, refused], [1.0, 2.0], rot_nb_prior=prior)
    assert table["t"].tolist() == [1.0, 2.0] and table["yaw"].iloc[0] == 0.3
    assert "sun_bx" not in table  # no sun_n: yaw rows
    np.testing.assert_allclose(table[["prior_yaw", "prior_pitch", "prior_roll"]].iloc[1],
                               [0.3, 0.02, -0.01])  # fmt: skip
    items = items_from_table(validate_measurements(table), use_sun=False)
    yaws = [it for it in items if it.kind == "yaw"]
    assert [it.valid for it in yaws] == [True, False] and yaws[0].std == 0.01
    # with the sun vector each image was measured with: 2-DOF sun rows
    sun_n = [0.0, 0.6, 0.8]
    table = polins.measurement_table(good, 1.0, sun_n=sun_n)
    assert table[["sun_bx", "sun_by", "sun_bz", "sun_nx", "sun_ny", "sun_nz"]].iloc[0].tolist() == [
        0.6, 0.0, 0.8, *sun_n]  # fmt: skip
    (item,) = [it for it in items_from_table(validate_measurements(table)) if it.kind == "sun"]
    np.testing.assert_allclose(item.sun_b, sun_b)
    with pytest.raises(ValueError, match="2 measurements but 1 times"):
        polins.measurement_table([good, good], [1.0])
