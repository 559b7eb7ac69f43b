"""The compiled passes of the per-image chain give the numbers of the numpy expressions they
replace: bit for bit where they decide the pixel selection, to float64 rounding for the
float64 sums, to float32 rounding for the joint ML's normal equations (docs/measurement.md
§5, §10); the Stokes pass is tested in tests/test_polarimetry.py."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from polins.compass.eigen import eigen_level_rows, weighted_residuals
from polins.compass.image import fill_invalid
from polins.compass.kernels import compiled, dot_rows, moment
from polins.compass.lens import evector_rows, lens_basis_rows
from polins.compass.prediction import doubled_prediction, image_plane_evector, pixel_data
from polins.compass.sectors import SectorRuns, eigen_sandwich_sums
from polins.compass.selection import Selection, select_pixels, selection_mask
from polins.compass.zenith import MIRROR_SECTORS


def _numpy_selection(data, select, sun_c, n1, n2, e2):
    """docs/measurement.md §4, written out with numpy."""
    along = n1 * data.s1
    along += n2 * data.s2
    mask = along >= (select.dop_min * e2) * data.s0
    if np.any(select.p_min):
        mask &= along >= e2 * select.p_min
    mask &= select.valid
    mask &= dot_rows(sun_c.astype(data.s0.dtype), select.rays) <= select.cos_exclusion
    return mask


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("p_min", ["per pixel", "common", "none"])
def test_compiled_selection_is_bit_identical(dtype, p_min):
    rng = np.random.default_rng(3)
    n = 20_000
    s0 = rng.uniform(50.0, 500.0, n).astype(dtype)
    dop = rng.uniform(0.0, 0.3, n)
    aop = rng.uniform(0.0, np.pi, n)
    s1 = (s0 * dop * np.cos(2 * aop)).astype(dtype)
    s2 = (s0 * dop * np.sin(2 * aop)).astype(dtype)
    rays = rng.normal(size=(3, n))
    rays[2] = np.abs(rays[2])
    rays = (rays / np.linalg.norm(rays, axis=0)).astype(dtype)
    sun_c = np.array([0.3, -0.5, 0.8])
    sun_c /= np.linalg.norm(sun_c)
    x = np.ascontiguousarray(sun_c[1] * rays[2] - sun_c[2] * rays[1])  # s x p, image plane
    y = np.ascontiguousarray(sun_c[2] * rays[0] - sun_c[0] * rays[2])
    n1, n2, e2 = doubled_prediction(x.astype(dtype), y.astype(dtype))
    threshold = {"per pixel": rng.uniform(0.0, 20.0, n).astype(dtype), "common": 7.5, "none": 0.0}
    select = Selection(rng.random(n) < 0.9, rays, float(np.cos(np.radians(10.0))), 0.03,
                       threshold[p_min])  # fmt: skip
    data = pixel_data(s0, s1, s2, None, 1.0, rays=rays)
    got = select_pixels(data, select, sun_c, n1, n2, e2)
    want = _numpy_selection(data, select, sun_c, n1, n2, e2)
    np.testing.assert_array_equal(got, want)
    assert 0.2 < want.mean() < 0.9
    # With the prediction in the same pass (the projection lens model's rays).
    xy = image_plane_evector(data, sun_c[:, None])
    n1, n2, e2 = doubled_prediction(xy[0, :n], xy[0, n:])
    want = _numpy_selection(data, select, sun_c, n1, n2, e2)
    np.testing.assert_array_equal(selection_mask(data, select, sun_c), want)
    assert 0.2 < want.mean() < 0.9


def test_compiled_float64_sums_match_numpy():
    # The float64 reductions (moment, the eigen jackknife's run sums) are summed in another
    # order than numpy's: its numbers to float64 rounding.
    rng = np.random.default_rng(5)
    n = 50_000
    e = rng.normal(size=(3, n))
    omega = rng.uniform(0.0, 2.0, n)
    want = np.einsum("in,jn->ij", e * omega, e)
    np.testing.assert_allclose(moment(e, omega), want, rtol=1e-12)
    np.testing.assert_allclose(moment(np.ascontiguousarray(e.T).T, omega), want, rtol=1e-12)
    assert moment(e.astype(np.float32), omega.astype(np.float32)).dtype == np.float64
    starts = np.r_[0, np.cumsum(rng.integers(1, 300, 400))]
    starts = starts[starts < n]
    wr = rng.normal(size=n)
    got = np.empty((starts.size, 4))
    compiled("eigen_run_sums")(e, wr, omega, starts, got)
    rows = np.vstack([e * wr, omega])
    np.testing.assert_allclose(got.T, np.add.reduceat(rows, starts, axis=1), rtol=1e-9, atol=1e-9)


def _sky_pixels(rng, n, dtype, weighted):
    """Pixel data of a tilted hemisphere of rays (projection lens model) with random
    polarization, and the rays."""
    rays = rng.normal(size=(3, n))
    rays[2] = np.abs(rays[2]) + 0.3
    rays = (rays / np.linalg.norm(rays, axis=0)).astype(dtype)
    s0 = rng.uniform(50.0, 500.0, n)
    dop, aop = rng.uniform(0.0, 0.4, n), rng.uniform(0.0, np.pi, n)
    s1, s2 = (s0 * dop * np.cos(2 * aop)).astype(dtype), (s0 * dop * np.sin(2 * aop)).astype(dtype)
    inv_sigma = rng.uniform(0.5, 2.0, n).astype(dtype) if weighted else 1.0
    return pixel_data(s0.astype(dtype), s1, s2, None, inv_sigma, rays=rays), rays


@pytest.mark.parametrize(
    ("zenith", "sky", "weighted", "p_min"),
    [
        (0.7, None, False, "per pixel"),  # the full-set step of the default chain
        (None, None, True, "common"),  # zenith free, per-pixel sigma
        (0.7, "berry", True, "none"),  # E-vector rows from the Berry pass, separation fitted
        (None, "berry", False, "mask"),  # four parameters, the mask given
    ],
)
def test_compiled_normal_equations_match_numpy(zenith, sky, weighted, p_min):
    # The one-pass residual, Jacobian and group sums (polins.compass.selection_kernels.ml_pass) give
    # the normal equations of ml_evaluate's rows (float32 rows, float64 sums: to float32
    # rounding) and the same pixel selection, bit for bit.
    from polins.compass.normal import (
        normal_equations,
        sector_normal_equations,
        sums_normal_equations,
        sums_sector_normal_equations,
    )
    from polins.compass.residual import ml_evaluate, ml_pass_sums
    from polins.compass.sectors import SectorRuns
    from polins.compass.skymodel import sky_model

    rng = np.random.default_rng(7)
    n = 30_000
    data, rays = _sky_pixels(rng, n, np.float32, weighted)
    mat_cl = Rotation.from_euler("XYZ", [0.05, -0.03, 1.2]).as_matrix()
    model = None if sky is None else sky_model(rays, True, 0.5, True, False)
    theta = np.array([0.4, *([] if zenith is not None else [0.8])]
                     + ([0.3] if model is not None else []) + [0.012])  # fmt: skip
    threshold = {"per pixel": rng.uniform(0.0, 20.0, n).astype(np.float32), "common": 7.5}
    select = Selection(rng.random(n) < 0.95, rays, float(np.cos(np.radians(10.0))), 0.03,
                       threshold.get(p_min, 0.0))  # fmt: skip
    if p_min == "mask":
        data, select = dataclasses.replace(data, mask=rng.random(n) < 0.8), None
    starts = np.r_[0, np.cumsum(rng.integers(1, 120, 800))]
    starts = starts[starts < n]
    runs = SectorRuns(starts, rng.integers(0, 64, starts.size), 64,
                      np.linspace(-np.pi, np.pi, 64, endpoint=False) + np.pi / 64,
                      np.arange(64) // 32)  # fmt: skip
    r, jac, _, mask = ml_evaluate(data, theta, zenith, mat_cl, True, select, model)
    group_sums, mask_pass = ml_pass_sums(data, theta, zenith, mat_cl, select, model, runs)
    np.testing.assert_array_equal(mask_pass, mask)
    assert 0.3 < mask.mean() < 0.95
    k = theta.size
    want, got = normal_equations(r, jac, None), sums_normal_equations(group_sums, k)
    scale = np.sqrt(np.diag(want[0]))
    np.testing.assert_allclose(got[0] / np.outer(scale, scale), want[0] / np.outer(scale, scale),
                               rtol=0, atol=2e-6)  # fmt: skip
    np.testing.assert_allclose(
        got[1] / scale, want[1] / scale, rtol=0, atol=2e-6 * np.sqrt(want[2])
    )
    assert got[2] == pytest.approx(want[2], rel=2e-6)
    z = zenith if zenith is not None else theta[1]
    sun_c = mat_cl @ np.array([np.sin(z) * np.cos(0.4), np.sin(z) * np.sin(0.4), np.cos(z)])
    h_want, b_want = sector_normal_equations(r, jac, None, runs, sun_c, None)
    h_got, b_got = sums_sector_normal_equations(group_sums, k, None)
    np.testing.assert_allclose(h_got, h_want, rtol=1e-4, atol=1e-5 * np.max(want[0]))
    np.testing.assert_allclose(b_got, b_want, rtol=1e-4, atol=1e-5 * np.max(np.abs(want[1])))
    assert sums_sector_normal_equations(group_sums, k, h_want)[0] is h_want
    # without sectors: one group, the same sums
    one, _ = ml_pass_sums(data, theta, zenith, mat_cl, select, model, None)
    np.testing.assert_allclose(one[0], group_sums.sum(axis=0), rtol=1e-9)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("model", ["projection", "meridian"])
@pytest.mark.parametrize("weights", ["per pixel", "common", "equal"])
def test_compiled_evectors_are_bit_identical(dtype, model, weights):
    """The eigen solution's E-vectors and weights (one compiled pass) are numpy's, bit for
    bit, with zero-polarization and negative-S1 pixels; the moment is their float64 sum."""
    rng = np.random.default_rng(11)
    n = 20_000
    s1 = rng.normal(0.0, 30.0, n).astype(dtype)
    s2 = rng.normal(0.0, 30.0, n).astype(dtype)
    s1[::97], s2[::97] = 0.0, 0.0
    rays = rng.normal(size=(3, n))
    rays[2] = np.abs(rays[2]) + 0.5
    rays /= np.linalg.norm(rays, axis=0)
    basis = np.ascontiguousarray(lens_basis_rows(rays, model), dtype=dtype)
    inv = {"per pixel": rng.uniform(0.5, 2.0, n).astype(dtype), "common": 0.37, "equal": 1.0}
    mask = rng.random(n) < 0.8
    weighted = weights != "equal"
    e = evector_rows(s1, s2, basis, model == "projection")
    norm2 = e[0] * e[0]
    norm2 += e[1] * e[1]
    norm2 += e[2] * e[2]
    norm2 += e.dtype.type(1e-30)
    omega = (s1 * s1 + s2 * s2) * inv[weights] / norm2 if weighted else 1.0 / norm2
    omega *= mask
    mat_lc = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    sol, e_got, omega_got = eigen_level_rows(s1, s2, inv[weights], basis, model == "projection",
                                             mat_lc, weighted, mask=mask)  # fmt: skip
    assert e_got.dtype == dtype and omega_got.dtype == dtype
    np.testing.assert_array_equal(e_got, e)
    np.testing.assert_array_equal(omega_got, omega)
    assert sol.n == np.count_nonzero(omega)
    e64, omega64 = e.astype(np.float64), omega.astype(np.float64)
    want = np.einsum("in,jn->ij", e64 * omega64, e64)
    np.testing.assert_allclose(moment(e_got, omega_got), want, rtol=1e-12)
    np.testing.assert_allclose(sol.weight_sum, np.trace(want), rtol=1e-12)


def test_compiled_mirror_groups_match_angles():
    """The mirror-pair jackknife's groups (signs of cross products) are those of the
    angle between each horizontal level ray and the sun's azimuth, in sectors of pi/8; the
    pixels outside the mask add nothing."""
    rng = np.random.default_rng(12)
    k = 5000
    contrib = rng.normal(size=(2, k))
    rays = rng.normal(size=(3, k))
    mask = rng.random(k) < 0.7
    contrib[:, ~mask] = 0.0  # as the zenith pass writes them
    mat_lc = Rotation.from_rotvec([0.05, -0.1, 0.8]).as_matrix()
    ray_l = mat_lc @ rays
    azimuth = 0.7
    c, s = np.cos(azimuth), np.sin(azimuth)
    rel = np.abs(np.arctan2(c * ray_l[1] - s * ray_l[0], c * ray_l[0] + s * ray_l[1]))
    group = np.minimum((rel * (MIRROR_SECTORS / np.pi)).astype(np.intp), MIRROR_SECTORS - 1)
    want = np.stack([np.bincount(group[mask], w[mask], MIRROR_SECTORS) for w in contrib])
    b = np.arange(1, MIRROR_SECTORS) * np.pi / MIRROR_SECTORS
    got = np.zeros((3, MIRROR_SECTORS))
    compiled("mirror_pass")(contrib, rays, mask, mat_lc, np.array([c, s]),
                            np.array([np.cos(b), np.sin(b)]), got)  # fmt: skip
    np.testing.assert_allclose(got[:2], want, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(got[2], np.bincount(group[mask], minlength=MIRROR_SECTORS))


def _zenith_reference(est, inv, basis, rays, valid, mat_lc, cos_edge):
    """The zenith cone's mask, sums and contributions with numpy (docs/measurement.md §13)."""
    mask = valid & (mat_lc[2] @ rays > cos_edge)
    h = np.einsum("ij,jkn->ikn", mat_lc[:2], basis.astype(np.float64))  # (2, 2, n): h1, h2
    (h1x, h2x), (h1y, h2y) = h
    inv_norm = 2.0 / (h1x**2 + h1y**2 + h2x**2 + h2y**2)
    q1 = np.array([0.5 * (h1x**2 - h1y**2 - h2x**2 + h2y**2), h1x * h1y - h2x * h2y]) * inv_norm
    q2 = np.array([h1x * h2x - h1y * h2y, h1x * h2y + h2x * h1y]) * inv_norm
    s0, s1, s2 = est.astype(np.float64)
    w = np.broadcast_to(np.asarray(inv, dtype=np.float64), s0.shape) * mask
    c = w * (q1 * s1 + q2 * s2)
    sums = np.concatenate([
        c.sum(axis=1),
        [np.sum(w * (q1[0] ** 2 + q2[0] ** 2)), np.sum(w * (q1[0] * q1[1] + q2[0] * q2[1])),
         np.sum(w * (q1[1] ** 2 + q2[1] ** 2))],
        (w * s0 * q1).sum(axis=1), (w * s0 * q2).sum(axis=1),
        (w * (q1 * s1 - q2 * s2)).sum(axis=1), (w * (q1 * s2 + q2 * s1)).sum(axis=1),
    ])  # fmt: skip
    return mask, sums, c


@pytest.mark.parametrize("model", ["projection", "meridian"])
@pytest.mark.parametrize("weights", ["per pixel", "common"])
def test_compiled_zenith_sums_match_numpy(model, weights):
    """The zenith cone's mask (bit for bit), sums and per-pixel contributions (to float64
    rounding) of one compiled pass are those of the numpy expressions, for either lens
    model's basis (the projection model's passed as its third row)."""
    rng = np.random.default_rng(15)
    n = 20_000
    rays = rng.normal(size=(3, n))
    rays[2] = np.abs(rays[2]) + 1.0
    rays /= np.linalg.norm(rays, axis=0)
    rays = rays.astype(np.float32)
    basis = np.ascontiguousarray(lens_basis_rows(rays.astype(np.float64), model), np.float32)
    est = rng.normal(50.0, 20.0, (3, n)).astype(np.float32)
    inv = {"per pixel": rng.uniform(0.5, 2.0, n).astype(np.float32),
           "common": np.full((1, 1), 0.37, np.float32)}[weights]  # fmt: skip
    valid = rng.random(n) < 0.8
    mat_lc = Rotation.from_rotvec([0.03, -0.02, 0.4]).as_matrix()
    cos_edge = 0.9
    mask, sums, contrib = np.empty(n, bool), np.empty(13), np.empty((2, n))
    compiled("zenith_pass")(est, inv, basis[2] if model == "projection" else basis, rays,
                            valid, mat_lc, cos_edge, mask, sums, contrib)  # fmt: skip
    want_mask, want_sums, want_contrib = _zenith_reference(est, inv.reshape(-1), basis,
                                                           rays.astype(np.float64), valid,
                                                           mat_lc, cos_edge)  # fmt: skip
    assert 0 < np.count_nonzero(want_mask) < n
    np.testing.assert_array_equal(mask, want_mask)
    np.testing.assert_allclose(contrib, want_contrib, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sums, want_sums, rtol=1e-10)


def test_compiled_sandwich_sums_match_numpy():
    """The sandwich middle and the jackknife run sums of one compiled pass are those of the
    weighted residuals, the moment and the run sums computed apart, to float64 rounding."""
    rng = np.random.default_rng(13)
    n = 30_000
    e = rng.normal(size=(3, n)).astype(np.float32)
    omega = rng.uniform(0.0, 2.0, n).astype(np.float32)
    sun_c = np.array([0.3, -0.4, 0.866])
    starts = np.r_[0, np.cumsum(rng.integers(1, 200, 300))]
    starts = starts[starts < n]
    runs = SectorRuns(starts, np.zeros(starts.size, dtype=np.intp), 1, np.zeros(1),
                      np.zeros(1, dtype=np.intp))  # fmt: skip
    middle, run_sums = eigen_sandwich_sums(e, omega, sun_c, runs)
    e64, omega64 = e.astype(np.float64), omega.astype(np.float64)
    wr = weighted_residuals(e, omega, sun_c)
    np.testing.assert_allclose(middle, np.einsum("in,jn->ij", e64 * wr * wr, e64), rtol=1e-11)
    want = np.add.reduceat(np.vstack([e64 * wr, omega64]), starts, axis=1).T
    np.testing.assert_allclose(run_sums, want, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_fill_matches_numpy(dtype):
    """The invalid pixels' harmless data (one compiled pass) are numpy's masked copies."""
    rng = np.random.default_rng(14)
    n = 10_000
    rows = rng.normal(size=(4, n)).astype(dtype)
    inv = rng.uniform(0.5, 2.0, n).astype(dtype)
    valid = rng.random(n) < 0.7
    want_rows, want_inv, three = rows.copy(), inv.copy(), rows[:3].copy()
    np.copyto(want_rows[:3], np.array([[1.0], [0.0], [0.0]], dtype=dtype), where=~valid)
    np.copyto(want_rows[3], dtype(0.0), where=~valid)
    np.copyto(want_inv, dtype(1.0), where=~valid)
    fill_invalid(rows, inv, valid)
    np.testing.assert_array_equal(rows, want_rows)
    np.testing.assert_array_equal(inv, want_inv)
    fill_invalid(three, 1.0, valid)  # three rows, a common weight
    np.testing.assert_array_equal(three, want_rows[:3])


def test_compiled_counts_and_noise_sum_match_numpy():
    """The moment pass counts the non-zero weights; the noise estimate's masked sum of
    squares is numpy's, to float64 rounding; PixelData's S0^2 - |L|^2 is computed once for
    the copies with another mask."""
    rng = np.random.default_rng(16)
    n = 20_000
    e = rng.normal(size=(3, n)).astype(np.float32)
    omega = rng.uniform(0.0, 2.0, n).astype(np.float32)
    omega[rng.random(n) < 0.3] = 0.0
    out = np.empty((3, 3))
    assert compiled("moment_pass")(e, omega, out) == np.count_nonzero(omega)
    np.testing.assert_allclose(out, moment(e, omega), rtol=1e-12)
    nu = rng.normal(0.0, 3.0, n).astype(np.float32)
    mask = rng.random(n) < 0.6
    want = float(np.sum(nu.astype(np.float64)[mask] ** 2))
    np.testing.assert_allclose(compiled("square_sum_pass")(nu, mask), want, rtol=1e-12)
    s = rng.normal(10.0, 1.0, (3, n)).astype(np.float32)
    data = pixel_data(s[0], s[1], s[2], None, 1.0, rays=np.ones((3, n), np.float32))
    np.testing.assert_array_equal(data.c, s[0] * s[0] - s[1] * s[1] - s[2] * s[2])
    assert dataclasses.replace(data, mask=mask).c is data.c
