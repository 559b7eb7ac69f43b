"""The IMU's mounting pitch and yaw errors and the lever arm's error as states of both
backends (docs/filter.md §5.6): the shared model's columns, simulate-and-recover on the UGV
drives of tests/test_vehicle.py, the manifest keys."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import gtsam
import numpy as np
import pandas as pd
import pytest
from gtsam.symbol_shorthand import V, X
from scipy.spatial.transform import Rotation
from test_graph_states import numeric_jacobians
from test_vehicle import (
    MEMS,
    MOUNT,
    SITE,
    UGV_LEVER_ARM_B,
    Drive,
    attitude_scores,
    fast_and_per_sample,
)

from polins.errors import UserInputError
from polins.fusion.config import FuseConfig
from polins.fusion.graph.states import GraphStates
from polins.fusion.items import LEVER_STATE, MOUNT_STATES, MeasurementItem, item_model
from polins.fusion.measurement import lever_jacobian, mount_jacobian
from polins.fusion.vehicle import mat_vb_from_mount
from polins.io.log import read_log, write_log
from polins.io.manifest import ManifestError

# the configured mounting: the true one (MOUNT) off by -1 deg in pitch and +1.5 deg in yaw
CONFIGURED = (MOUNT[0], MOUNT[1] + math.radians(1.0), MOUNT[2] - math.radians(1.5))
MOUNT_STD = math.radians(2.0)
# the states' truth: the rotation from the configured mounting to the true one (y, z)
TRUTH = Rotation.from_matrix(
    mat_vb_from_mount(MOUNT) @ mat_vb_from_mount(CONFIGURED).T
).as_rotvec()[1:3]


def fuse(drive: Drive, backend: str, mount_std: float | str):
    return drive.fuse(backend=backend, vehicle="ground", mount_rpy=CONFIGURED,
                      lever_arm_b=UGV_LEVER_ARM_B, mount_std=mount_std)  # fmt: skip


def fuse_lever(drive: Drive, backend: str, lever_std: float | str):
    """The true mounting, the lever arm configured as zero (truth UGV_LEVER_ARM_B), the
    odometer."""
    return drive.fuse(odometry=True, backend=backend, vehicle="ground", mount_rpy=MOUNT,
                      lever_std=lever_std)  # fmt: skip


def mount_estimate(sol: pd.DataFrame, names=MOUNT_STATES) -> tuple[np.ndarray, np.ndarray]:
    """The last row's estimates and 1-sigmas of the columns ``names`` (default:
    mount_pitch, mount_yaw [rad])."""
    last = sol.iloc[-1]
    return (np.array([last[n] for n in names]),
            np.array([last[f"{n}_std"] for n in names]))  # fmt: skip


LEVER_COLUMNS = tuple(f"{LEVER_STATE}{a}" for a in "xyz")


def pooled(results: list[tuple[Drive, pd.DataFrame]]) -> dict[str, tuple[float, float]]:
    """Per angle over several drives: RMS(err/sigma) and the fraction within 3 sigma (the
    drives' equal-length scores combined)."""
    scores = [attitude_scores(d.traj, sol) for d, sol in results]
    return {name: (math.sqrt(np.mean([s[name][1] ** 2 for s in scores])),
                   float(np.mean([s[name][2] for s in scores])))
            for name in ("yaw", "pitch", "roll")}  # fmt: skip


# ----------------------------------------------------------------------------- model
def test_mount_columns_match_differences():
    # d h / d (pitch, yaw) of the NHC and the odometer, with a mounting and a lever arm,
    # against central differences of the shared model in the estimates: exact at zero,
    # first order elsewhere (the additive state: exp([(e + d) x]) = exp([J_l(e) d x])
    # exp([e x]), J_l = I + O(|e|), 0.4 % at |e| = 0.008 rad)
    rot = Rotation.from_euler("ZYX", [0.4, 0.03, -0.02]).as_matrix()
    vel_n = np.array([3.0, -2.0, 0.2])
    mat_vb = mat_vb_from_mount((0.01, -0.02, 0.035))
    lever = np.cross([0.1, -0.05, 0.3], UGV_LEVER_ARM_B)
    for kind, base in (
        ("nhc", np.zeros(2)),
        ("odo", np.zeros(2)),
        ("nhc", np.array([0.004, -0.007])),
    ):
        item = MeasurementItem(0.0, kind, 0.05, speed=3.5, mat_vb=mat_vb, lever_vel_b=lever)

        def residual(e: np.ndarray, item: MeasurementItem = item) -> np.ndarray:
            states = {n: e[i : i + 1] for i, n in enumerate(MOUNT_STATES)}
            return item_model(item, rot, vel_n, False, states).residual

        lin = item_model(item, rot, vel_n, False, {n: base[i : i + 1]
                                                    for i, n in enumerate(MOUNT_STATES)})  # fmt: skip
        step = 1e-6
        numeric = np.column_stack([(residual(base - step * d) - residual(base + step * d))
                                   / (2 * step) for d in np.eye(2)])  # fmt: skip
        tol = 1e-8 + np.linalg.norm(base) * np.abs(numeric).max()
        np.testing.assert_allclose(mount_jacobian(lin), numeric, rtol=0, atol=tol)
    # the model turns the configured mounting: zero estimates leave the item's model alone
    zero = {n: np.zeros(1) for n in MOUNT_STATES}
    plain = item_model(item, rot, vel_n, False)
    np.testing.assert_array_equal(item_model(item, rot, vel_n, False, zero).residual,
                                  plain.residual)  # fmt: skip


def test_lever_columns_match_differences():
    # the models are linear in the lever arm: the columns equal differences anywhere
    rot = Rotation.from_euler("ZYX", [0.4, 0.03, -0.02]).as_matrix()
    vel_n = np.array([3.0, -2.0, 0.2])
    mat_vb = mat_vb_from_mount((0.01, -0.02, 0.035))
    gyro_b = np.array([0.02, -0.03, 0.3])
    base = np.array([0.2, -0.1, 0.05])
    for kind in ("nhc", "odo"):
        item = MeasurementItem(0.0, kind, 0.05, speed=3.5, mat_vb=mat_vb,
                               lever_vel_b=np.cross(gyro_b, UGV_LEVER_ARM_B), gyro_b=gyro_b)  # fmt: skip

        def residual(e: np.ndarray, item: MeasurementItem = item) -> np.ndarray:
            return item_model(item, rot, vel_n, False, {LEVER_STATE: e}).residual

        lin = item_model(item, rot, vel_n, False, {LEVER_STATE: base})
        numeric = np.column_stack([(residual(base - 0.1 * d) - residual(base + 0.1 * d)) / 0.2
                                   for d in np.eye(3)])  # fmt: skip
        np.testing.assert_allclose(lever_jacobian(lin, mat_vb, gyro_b), numeric, atol=1e-12)


def test_graph_nhc_factor_with_the_mounting_matches_differences():
    cfg = FuseConfig.from_options(None, **SITE, mount_std=MOUNT_STD, lever_std=0.3,
                                  heading_bias_std="off")  # fmt: skip
    states = GraphStates(cfg, np.array([0.0, 1.0]))
    rot = gtsam.Rot3.RzRyRx(0.02, -0.03, 0.7)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(rot, np.zeros(3)))
    values.insert(V(0), np.array([2.0, 2.5, 0.1]))
    values.insert(gtsam.symbol("m", 0), np.zeros(2))  # exact there (the test above)
    values.insert(gtsam.symbol("r", 0), np.array([0.1, -0.2, 0.05]))
    item = MeasurementItem(0.0, "nhc", 0.05, mat_vb=mat_vb_from_mount(MOUNT),
                           lever_vel_b=np.array([0.01, -0.02, 0.03]),
                           gyro_b=np.array([0.02, -0.03, 0.3]))  # fmt: skip
    factor = states.factor(item, 0, X(0), V(0), tilt=False)
    assert factor.dim() == 2
    keys = list(factor.keys())
    analytic = factor.linearize(values).jacobian()[0]
    numeric = np.hstack(numeric_jacobians(factor, values, keys, [6, 3, 2, 3]))
    np.testing.assert_allclose(analytic, numeric, atol=1e-5 * np.abs(numeric).max())


# ----------------------------------------------------------------------------- ESKF
@pytest.fixture(scope="module")
def drive() -> Drive:
    return Drive(seed=3, duration_s=200.0)


def check_needed(drive: Drive, sol: pd.DataFrame, sol_without: pd.DataFrame) -> None:
    """``sol`` (with the states) consistent: yaw / pitch / roll RMS(err/sigma) in [0.7, 1.3],
    >= 98 % within 3 sigma; ``sol_without`` over-confident in tilt (> 2, < 90 %)."""
    scores = attitude_scores(drive.traj, sol)
    for name, (_, ratio, within) in scores.items():
        assert 0.7 <= ratio <= 1.3 and within >= 0.98, (name, scores)
    wrong = attitude_scores(drive.traj, sol_without)
    assert max(wrong["pitch"][1], wrong["roll"][1]) > 2.0, wrong
    assert min(wrong["pitch"][2], wrong["roll"][2]) < 0.9, wrong


def test_eskf_estimates_the_mounting_and_stays_consistent(drive: Drive):
    # 200 s MEMS UGV drive (measured: pitch -1.003 +- 0.030 deg, yaw 1.491 +- 0.076 deg;
    # yaw / pitch / roll RMS(err/sigma) 1.26 / 0.83 / 0.87, 100 % within 3 sigma, as with
    # the true mounting configured: 1.26 / 0.83 / 0.88)
    sol = fuse(drive, "eskf", MOUNT_STD).solution
    est, std = mount_estimate(sol)
    assert np.all(np.abs(est - TRUTH) < 3 * std), (np.degrees(est), np.degrees(std))
    assert np.all(std < math.radians(0.3)), np.degrees(std)
    # without the states the NHC pulls the tilt off and the sigmas do not cover it
    # (measured: pitch / roll 3.4 / 2.1, 80 / 82 % within 3 sigma)
    check_needed(drive, sol, fuse(drive, "eskf", "off").solution)
    # off is spelled "off": a zero sigma is refused, not read as off
    with pytest.raises(UserInputError, match=r"mount_std=0\.0: expected a number > 0, 'off'"):
        FuseConfig(mount_std=0.0)


def test_eskf_estimates_the_lever_arm_and_stays_consistent(drive: Drive):
    # the lever arm (-0.6, 0.1, -0.3) m configured as zero, with the odometer (measured:
    # -0.604 +- 0.013, 0.106 +- 0.013, -0.228 +- 0.228 m; yaw / pitch / roll RMS(err/sigma)
    # 1.27 / 0.75 / 0.74, 100 % within 3 sigma). x is seen by the turns through the
    # lateral NHC, y through the odometer, z hardly (the roll and pitch rates are small)
    sol = fuse_lever(drive, "eskf", 0.5).solution
    est, std = mount_estimate(sol, LEVER_COLUMNS)
    assert np.all(np.abs(est - UGV_LEVER_ARM_B) < 3 * std), (est, std)
    assert np.all(std[:2] < 0.03) and 0.1 < std[2] < 0.4, std
    # without the states (measured: pitch / roll 9.9 / 4.8, 12 / 47 % within 3 sigma)
    check_needed(drive, sol, fuse_lever(drive, "eskf", "off").solution)


def test_per_sample_filter_estimates_the_mounting_as_the_fast_path(drive: Drive):
    # the streaming path (ESKF.propagate per sample, as NavigationStream) and run_fusion's
    # fast path apply the same updates to the mounting and lever-arm states
    cfg = FuseConfig.from_options(imu_model=MEMS, **SITE, vehicle="ground", mount_rpy=CONFIGURED,
                                  mount_std=MOUNT_STD, lever_std=0.5)  # fmt: skip
    fast, filt = fast_and_per_sample(drive, cfg)
    ref = fast.solution.iloc[-1]
    nav = filt.state()
    for name in MOUNT_STATES:
        assert abs(float(nav.errors[name][0]) - ref[name]) < 1e-6, name
        assert abs(float(nav.sigma[name][0]) - ref[f"{name}_std"]) < 1e-6, name
    np.testing.assert_allclose(nav.errors[LEVER_STATE], ref[list(LEVER_COLUMNS)].to_numpy(float),
                               atol=1e-6)  # fmt: skip
    assert float(nav.sigma[LEVER_STATE][0]) < 0.5  # the NHC has seen x (the prior: 0.5 m)
    assert abs(ref["mount_yaw"] - TRUTH[1]) < abs(TRUTH[1]) / 2  # moving after 15 s


# ----------------------------------------------------------------------------- graph
def test_graph_estimates_the_mounting_fast():
    # 60 s drive, batch solver (measured: pitch -0.997 +- 0.040 deg, yaw 1.480 +- 0.127 deg;
    # pitch / roll RMS(err/sigma) 0.59 / 0.79, 100 % within 3 sigma; with the true
    # mounting configured 0.64 / 0.81; without the states 2.75 / 2.81, 79 / 70 %)
    drive = Drive(seed=0, duration_s=60.0)
    sol = fuse(drive, "graph", MOUNT_STD).solution
    est, std = mount_estimate(sol)
    assert np.all(np.abs(est - TRUTH) < 3 * std), (np.degrees(est), np.degrees(std))
    assert np.all(std < math.radians(0.3)), np.degrees(std)
    scores = attitude_scores(drive.traj, sol)
    for name in ("pitch", "roll"):
        assert 0.4 <= scores[name][1] <= 1.3 and scores[name][2] >= 0.98, scores
    # a constant: the same estimate at every keyframe
    assert float(np.ptp(sol["mount_yaw"])) < 0.05 * std[1]


@pytest.mark.slow
def test_graph_estimates_the_lever_arm_fast():
    # 60 s drive with the odometer, batch solver (the ESKF: -0.599 +- 0.029, 0.104 +- 0.034,
    # 0.048 +- 0.442 m)
    drive = Drive(seed=1, duration_s=60.0)
    sol = fuse_lever(drive, "graph", 0.5).solution
    est, std = mount_estimate(sol, LEVER_COLUMNS)
    assert np.all(np.abs(est - UGV_LEVER_ARM_B) < 3 * std), (est, std)
    assert np.all(std[:2] < 0.05), std
    scores = attitude_scores(drive.traj, sol)
    for name in ("pitch", "roll"):
        assert 0.4 <= scores[name][1] <= 1.3 and scores[name][2] >= 0.98, scores


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["eskf", "graph"])
@pytest.mark.parametrize("state", ["mount", "lever"])
def test_mounting_states_are_consistent_over_drives(backend: str, state: str):
    # 3 drives of 200 s; measured (yaw / pitch / roll RMS(err/sigma), within 3 sigma):
    # see docs/filter.md §5.6
    drives = [Drive(seed=s, duration_s=200.0) for s in range(3)]
    if state == "mount":
        on = [(d, fuse(d, backend, MOUNT_STD).solution) for d in drives]
        off = pooled([(d, fuse(d, backend, "off").solution) for d in drives])
    else:
        on = [(d, fuse_lever(d, backend, 0.5).solution) for d in drives]
        off = pooled([(d, fuse_lever(d, backend, "off").solution) for d in drives])
    for _, sol in on:
        if state == "mount":
            est, std = mount_estimate(sol)
            assert np.all(np.abs(est - TRUTH) < 3 * std) and np.all(std < math.radians(0.3))
        else:
            est, std = mount_estimate(sol, LEVER_COLUMNS)
            assert np.all(np.abs(est - UGV_LEVER_ARM_B) < 3 * std) and np.all(std[:2] < 0.03)
    scores = pooled(on)
    for name, (ratio, within) in scores.items():
        assert 0.6 <= ratio <= 1.3 and within >= 0.98, (name, scores)
    assert max(off["pitch"][0], off["roll"][0]) > 2.0, off


# ----------------------------------------------------------------------------- manifest
def test_manifest_mount_std_deg_and_lever_std(tmp_path: Path):
    imu = pd.DataFrame({"t": np.arange(0, 2, 0.01), "gx": 0.0, "gy": 0.0, "gz": 0.0,
                        "ax": 0.0, "ay": 0.0, "az": 9.8})  # fmt: skip

    def written(name: str, vehicle: dict) -> tuple[Path, FuseConfig]:
        manifest = write_log(tmp_path / name, epoch_utc="2023-09-05T07:00:00Z",
                             camera="paper-table1", imu_model="mems-typical", lat_deg=45.0,
                             lon_deg=126.0, alt_m=0.0, imu=imu, images=[],
                             vehicle=vehicle)  # fmt: skip
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return Path(manifest), FuseConfig.from_log(read_log(manifest))

    manifest, cfg = written(
        "log", {"kind": "ground", "mount_rpy_deg": [0.5, -1.0, 2.0], "mount_std_deg": 2.0}
    )
    assert cfg.aiding.mount_std == pytest.approx(math.radians(2.0), rel=1e-15)
    assert cfg.mount_sigma == cfg.aiding.mount_std
    assert FuseConfig(mount_std="off").mount_sigma is None and FuseConfig().mount_sigma is None
    with pytest.raises(UserInputError, match="mount_std"):
        FuseConfig(mount_std=-0.01)
    text = manifest.read_text().replace("mount_std_deg = 2.0", "mount_std_deg = -1.0")
    manifest.write_text(text)
    with pytest.raises(ManifestError, match=r"vehicle\.mount_std_deg"):
        read_log(manifest)
    _, cfg = written("log2", {"kind": "ground", "lever_arm_b": [-0.6, 0.1, -0.3], "lever_std": 0.3})
    assert cfg.aiding.lever_std == 0.3 and cfg.lever_sigma == 0.3 and cfg.mount_sigma is None
    assert FuseConfig(lever_std="off").lever_sigma is None
    with pytest.raises(UserInputError, match="lever_std"):
        FuseConfig(lever_std=math.nan)
