"""Round trip of the intrinsics calibration (docs/calibrate.md#intrinsics) on rendered checkerboard images."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_calibration_scenes import dark_mosaic_of, mosaic, sensor, small_camera

from polins.calibration import apply_to_camera, calibrate_intrinsics
from polins.compass.camera import project
from polins.errors import UserInputError

BOARD = (9, 6)  # inner corners (columns, rows): 10 x 7 squares, no 180 deg symmetry
SQUARE_M = 0.04
SAMPLES_PER_SQUARE = 24


def _board_images(cam, poses, rng, samples_per_square=SAMPLES_PER_SQUARE):
    """Unpolarized checkerboard mosaics, rendered by splatting: a dense grid of board points
    is projected into the superpixel image and each superpixel takes the mean of the points
    that land in it (black squares 20 DN, white squares and a one-square margin 220 DN,
    background 20 DN)."""
    hs, ws = cam.superpixel_shape
    cols, rows = BOARD
    n = samples_per_square
    x = (np.arange((cols + 3) * n) + 0.5) / n - 2.0  # board coordinates [squares]
    y = (np.arange((rows + 3) * n) + 0.5) / n - 2.0
    bx, by = np.meshgrid(x, y)
    black = (
        ((np.floor(bx) + np.floor(by)) % 2 == 0) & (bx > -1) & (bx < cols) & (by > -1) & (by < rows)
    )
    value = np.where(black, 20.0, 220.0).ravel()
    pts_b = np.stack([bx.ravel(), by.ravel(), np.zeros(bx.size)], -1) * SQUARE_M
    dark = dark_mosaic_of(cam)
    out = []
    for rotvec, t in poses:
        pts_c = pts_b @ Rotation.from_rotvec(rotvec).as_matrix().T + t
        uv = project(cam, pts_c / np.linalg.norm(pts_c, axis=-1, keepdims=True))
        j, i = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        ok = (i >= 0) & (i < hs) & (j >= 0) & (j < ws)
        index = i[ok] * ws + j[ok]
        total = np.bincount(index, value[ok], hs * ws)
        count = np.bincount(index, minlength=hs * ws)
        s0 = np.where(count > 0, total / np.maximum(count, 1), 20.0).reshape(hs, ws)
        ch = cam.gain * s0[..., None] / 2.0 + cam.dark_offset_dn
        out.append(sensor(mosaic(ch, cam), dark, cam, rng, read_noise_dn=1.0))
    return np.stack(out)


def _poses(rng, n, field_max_deg=55.0):
    """Board poses (rotation vector, translation) [m]: centres spread out to
    ``field_max_deg`` from the optical axis at 0.2-0.3 m, boards facing the camera within
    +-30 deg."""
    poses = []
    for i in range(n):
        field = np.radians(field_max_deg) * np.sqrt((i + rng.uniform()) / n)
        azimuth = rng.uniform(0.0, 2.0 * np.pi)
        direction = np.array(
            [np.sin(field) * np.cos(azimuth), np.sin(field) * np.sin(azimuth), np.cos(field)]
        )
        facing = Rotation.align_vectors([direction], [[0.0, 0.0, 1.0]])[0]
        rot = facing * Rotation.from_euler(
            "xyz", [*rng.uniform(-0.5, 0.5, 2), rng.uniform(-1.0, 1.0)]
        )
        half = rot.apply([(BOARD[0] - 1) * SQUARE_M / 2, (BOARD[1] - 1) * SQUARE_M / 2, 0.0])
        poses.append((rot.as_rotvec(), rng.uniform(0.2, 0.3) * direction - half))
    return poses


def test_fisheye_intrinsics_round_trip_under_half_a_pixel():
    cam = small_camera(2, dark_offset_dn=np.full(4, 12.0))  # 612 x 512 superpixels
    rng = np.random.default_rng(31)
    raws = _board_images(cam, _poses(rng, 8), rng)
    scale = [[1.05, 1.0, 0.98], [1.0, 0.96, 1.02], [1.0, 1.0, 1.0]]
    start = replace(cam, camera_matrix=cam.camera_matrix * scale, distortion=np.zeros(4))
    res = calibrate_intrinsics(raws, start, board=BOARD, square_m=SQUARE_M)
    assert res.used.sum() >= 7
    assert res.reprojection_rms_px < 0.5
    k_true, k = cam.camera_matrix, res.camera_matrix
    assert np.diag(k)[:2] == pytest.approx(np.diag(k_true)[:2], rel=5e-3)
    assert k[:2, 2] == pytest.approx(k_true[:2, 2], abs=1.0)
    # The fitted lens projects rays out to 60 deg within a superpixel of the true one.
    theta, phi = np.meshgrid(np.radians(np.linspace(0, 60, 7)), np.linspace(0, 2 * np.pi, 13))
    rays = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    fitted = apply_to_camera(start, res)
    assert np.abs(project(fitted, rays) - project(cam, rays)).max() < 1.0
    assert res.provenance["kind"] == "intrinsics" and res.provenance["n_images"] == res.used.sum()


def test_intrinsics_refuses_images_without_a_board():
    cam = small_camera(8)
    flat = np.full((3, *cam.shape), 100, dtype=np.uint16)
    with pytest.raises(UserInputError, match="found in 0 of 3"):
        calibrate_intrinsics(flat, cam, board=BOARD, square_m=SQUARE_M)


@pytest.mark.slow  # the denser board rendering a pinhole's magnification needs takes seconds
def test_pinhole_intrinsics_round_trip():
    cam = small_camera(
        2,
        projection="pinhole",
        distortion=np.array([-0.05, 0.01, 0.0005, -0.0003, 0.0]),
        fov_max=np.radians(60.0),
        dark_offset_dn=np.full(4, 12.0),
    )
    rng = np.random.default_rng(32)
    raws = _board_images(cam, _poses(rng, 8, field_max_deg=35.0), rng, samples_per_square=60)
    start = replace(cam, distortion=np.zeros(5))
    res = calibrate_intrinsics(raws, start, board=BOARD, square_m=SQUARE_M)
    assert res.reprojection_rms_px < 0.5
    assert np.diag(res.camera_matrix)[:2] == pytest.approx(np.diag(cam.camera_matrix)[:2], rel=5e-3)
    assert res.distortion.shape == (5,)
    assert "calibrateCamera" in res.provenance["method"]
