"""Sun-vector estimation from per-pixel polarization: the weighted eigen solution (SPEC 9.1)
with its eigen-gap covariance (SPEC 10.2), and the joint maximum-likelihood estimate of the
sun direction and the direct-sunlight coefficient epsilon (SPEC 9.2).

Lens polarization models (SPEC 6.1) enter through two per-pixel constants, both built in
the camera frame from the pixel ray ``p``:

* the *inverse basis* ``T = [t1 t2]`` ``(..., 3, 2)``: the E-vector of image-plane AoP zeta
  is ``e ~ t1 cos zeta + t2 sin zeta`` (P: ``t1 = (1, 0, -p_x/p_z)``, ``t2 = (0, 1, -p_y/p_z)``;
  M: the meridian basis turned by the ray azimuth, orthonormal);
* the *forward rows* ``Q = [q1; q2]`` ``(..., 2, 3)``: the Rayleigh E-vector ``s x p`` of a
  sun ``s`` appears in the image plane along ``(x, y) = (q1 . s, q2 . s)``, i.e. the AoP is
  ``atan2(y, x)`` (P: ``q_j = p x f_j`` with ``f1 = (1, 0, 0)``, ``f2 = (0, 1, 0)``; M:
  ``q_j = p x t_j``). ``(x, y)`` is linear in ``s``, which makes the Jacobians of the joint ML
  cheap and exact.

Leading-underscore functions work on component-first arrays (``(3, n)``) for speed; the
public functions use the library's trailing-component layout.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

from polins.compass.polarimetry import _sunlight_unpolarized, sunlight_direction
from polins.frames import wrap_angle

FloatArray = NDArray[np.float64]

__all__ = [
    "EigenSolution",
    "MLSolution",
    "eigen_gap",
    "eigen_sun_covariance",
    "evectors_from_stokes",
    "lens_basis",
    "lens_forward",
    "ml_residuals",
    "sun_eigen",
    "sun_joint_ml",
    "sun_level_from_angles",
    "yaw_from_sun_level",
    "yaw_variance_from_sun_covariance",
]

LOSSES = ("linear", "huber", "cauchy")
_HUBER_K = 1.345
_CAUCHY_C = 2.3849


# ----------------------------------------------------------------------------- lens constants
def _ray_azimuth(rays: NDArray) -> tuple[NDArray, NDArray]:
    px, py = rays[0], rays[1]
    rho = np.hypot(px, py)
    safe = rho > 1e-15
    cos_a = np.where(safe, px / np.where(safe, rho, 1.0), 1.0)
    sin_a = np.where(safe, py / np.where(safe, rho, 1.0), 0.0)
    return cos_a, sin_a


def _lens_basis_rows(rays: NDArray, model: str) -> NDArray:
    """Inverse basis ``(3, 2, n)`` of component-first rays ``(3, n)``."""
    px, py, pz = rays
    if model == "projection":
        one, zero = np.ones_like(px), np.zeros_like(px)
        return np.array([[one, zero], [zero, one], [-px / pz, -py / pz]])
    if model == "meridian":
        ca, sa = _ray_azimuth(rays)
        rho = np.hypot(px, py)
        e_gamma = np.array([pz * ca, pz * sa, -rho])
        e_alpha = np.array([-sa, ca, np.zeros_like(ca)])
        t1 = ca * e_gamma - sa * e_alpha
        t2 = sa * e_gamma + ca * e_alpha
        return np.stack([t1, t2], axis=1)
    raise ValueError(f"unknown lens polarization model {model!r}")


def _lens_forward_rows(rays: NDArray, model: str) -> NDArray:
    """Forward rows ``(2, 3, n)``: ``q_j = p x f_j``."""
    if model == "projection":
        f = np.zeros((2, 3, rays.shape[1]))
        f[0, 0] = 1.0
        f[1, 1] = 1.0
    else:
        f = np.moveaxis(_lens_basis_rows(rays, model), 1, 0)  # (2, 3, n): t1, t2
    return np.stack([np.cross(rays, f[j], axis=0) for j in range(2)])


def lens_basis(rays_c: ArrayLike, model: str) -> FloatArray:
    """Inverse lens basis ``(..., 3, 2)``: ``e ~ T @ (cos zeta, sin zeta)`` (SPEC 6.1)."""
    rays = np.moveaxis(np.asarray(rays_c, dtype=float), -1, 0)
    return np.moveaxis(_lens_basis_rows(rays, model), (0, 1), (-2, -1))


def lens_forward(rays_c: ArrayLike, model: str) -> FloatArray:
    """Forward lens rows ``(..., 2, 3)``: the AoP of the Rayleigh E-vector ``s x p`` is
    ``atan2(q2 . s, q1 . s)`` (SPEC 6.1)."""
    rays = np.moveaxis(np.asarray(rays_c, dtype=float), -1, 0)
    return np.moveaxis(_lens_forward_rows(rays, model), (0, 1), (-2, -1))


# ----------------------------------------------------------------------------- products
# Thin products use einsum (numpy's own loops), not BLAS: OpenBLAS threads stall for tens of
# milliseconds on a busy machine for these shapes, and single-threaded they are no faster.
def _dot(a: NDArray, b: NDArray) -> float:
    """``a . b`` of two vectors, without BLAS."""
    return float(np.einsum("i,i->", a, b))


def _dot_rows(v: NDArray, rows: NDArray) -> NDArray:
    """``v @ rows`` for a (k,) vector and (k, n) rows, without BLAS."""
    return np.einsum("i,in->n", v, rows)


# ----------------------------------------------------------------------------- E-vectors
def _evector_rows(s1: NDArray, s2: NDArray, basis: NDArray, projection: bool) -> NDArray:
    """Unnormalised camera-frame E-vectors ``(3, n)`` from (S1, S2), without trigonometry.

    ``h`` is a vector along (cos zeta, sin zeta) from the half-angle identities
    ``(p + S1, S2) = 2p cos zeta (cos zeta, sin zeta)`` and
    ``(S2, p - S1) = 2p sin zeta (cos zeta, sin zeta)``, using the better-conditioned one.
    """
    p = np.sqrt(s1 * s1 + s2 * s2)
    pos = s1 >= 0
    h1 = np.where(pos, p + s1, s2)
    h2 = np.where(pos, s2, p - s1)
    if projection:
        return np.stack([h1, h2, basis[2, 0] * h1 + basis[2, 1] * h2])
    return basis[:, 0] * h1 + basis[:, 1] * h2


def evectors_from_stokes(stokes: ArrayLike, basis: ArrayLike) -> FloatArray:
    """Unit camera-frame E-vectors ``(..., 3)`` of Stokes vectors ``(..., 3)`` (SPEC 9.1).

    Parameters
    ----------
    stokes : array_like, (..., 3)
        (S0, S1, S2); only the AoP ``atan2(S2, S1)/2`` is used.
    basis : array_like, (..., 3, 2)
        Inverse lens basis, :func:`lens_basis` of the pixel rays.
    """
    s = np.moveaxis(np.asarray(stokes, dtype=float), -1, 0)
    t = np.moveaxis(np.asarray(basis, dtype=float), (-2, -1), (0, 1))
    e = _evector_rows(s[1], s[2], t, projection=False)
    e = e / np.linalg.norm(e, axis=0)
    return np.moveaxis(e, 0, -1)


# ----------------------------------------------------------------------------- eigen
@dataclass(frozen=True)
class EigenSolution:
    """Weighted eigen solution of SPEC 9.1 in the frame of the E-vectors.

    ``sun`` is the eigenvector of the smallest eigenvalue, sign chosen with ``sun_z >= 0``.
    """

    sun: FloatArray  # (3,)
    eigenvalues: FloatArray  # (3,) ascending
    eigenvectors: FloatArray  # (3, 3) columns
    weight_sum: float
    n: int


def _eigen_from_moment(moment: NDArray, weight_sum: float, n: int) -> EigenSolution:
    lam, vec = np.linalg.eigh(0.5 * (moment + moment.T))
    sun = vec[:, 0] * (1.0 if vec[2, 0] >= 0 else -1.0)
    vec = vec.copy()
    vec[:, 0] = sun
    return EigenSolution(sun, lam, vec, weight_sum, n)


def _moment(e: NDArray, omega: NDArray) -> NDArray:
    """``sum_i omega_i e_i e_i^T`` of component-first ``e`` (3, n), in float64."""
    return np.asarray(np.einsum("in,jn->ij", e * omega, e), dtype=float)


def sun_eigen(evec: ArrayLike, weights: ArrayLike | None = None) -> EigenSolution:
    """Sun vector as the minimum-eigenvalue eigenvector of ``M = sum_i w_i e_i e_i^T``
    (SPEC 9.1, the paper's Eq. 31 with optional weights ``w_i = p_i^2/sigma_L,i^2``).

    Parameters
    ----------
    evec : array_like, (n, 3)
        Unit E-vectors, in the frame wanted for the sun (level frame for the heading).
    weights : array_like, (n,), optional
        Pixel weights; None = equal weights (the paper).
    """
    e = np.asarray(evec, dtype=float)
    if e.ndim != 2 or e.shape[1] != 3 or e.shape[0] < 3:
        raise ValueError(f"evec must have shape (n >= 3, 3), got {e.shape}")
    w = np.ones(e.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    return _eigen_from_moment(_moment(e.T, w), float(w.sum()), e.shape[0])


def _sandwich_middle(e: NDArray, omega: NDArray, sun: NDArray) -> NDArray:
    """``sum_i (w_i r_i)^2 u_i u_i^T`` for unit E-vectors ``u_i = e_i/|e_i|`` and residuals
    ``r_i = u_i . s`` (SPEC 10.2), from unnormalised ``e`` (3, n) and ``omega = w_i/|e_i|^2``:
    the summand equals ``(omega_i (e_i . s))^2 e_i e_i^T``."""
    proj = sun[0] * e[0] + sun[1] * e[1] + sun[2] * e[2]
    wr = omega * proj
    return _moment(e, wr * wr)


def eigen_sun_covariance(
    evec: ArrayLike, weights: ArrayLike | None, solution: EigenSolution
) -> FloatArray:
    """First-order (sandwich) covariance of the eigen sun vector (SPEC 10.2)::

        A+ = sum_{j=2,3} v_j v_j^T / (lambda_j - lambda_1),  r_i = e_i . s
        Cov(s) = A+ (sum_i w_i^2 r_i^2 e_i e_i^T) A+

    Parameters
    ----------
    evec, weights : as for :func:`sun_eigen` (unit E-vectors ``(n, 3)``).
    """
    e = np.asarray(evec, dtype=float)
    w = np.ones(e.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    wr = w * (e @ solution.sun)
    return _sandwich(solution, _moment(e.T, wr * wr))


def _sandwich(solution: EigenSolution, middle: NDArray) -> FloatArray:
    lam, vec = solution.eigenvalues, solution.eigenvectors
    a_plus = sum(np.outer(vec[:, j], vec[:, j]) / (lam[j] - lam[0]) for j in (1, 2))
    return np.asarray(a_plus @ middle @ a_plus, dtype=float)


def eigen_gap(solution: EigenSolution) -> float:
    """Normalised eigen-gap ``(lambda_perp - lambda_1)/lambda_perp`` (SPEC 10.1), with
    lambda_perp the eigenvalue whose eigenvector is closest to the horizontal direction
    perpendicular to the solar vertical plane (``z x s``; the solution must be in a level
    frame)."""
    s = solution.sun
    perp = np.array([-s[1], s[0], 0.0])
    norm = np.linalg.norm(perp)
    if norm < 1e-12:
        return float("nan")
    j = 1 + int(np.argmax(np.abs(solution.eigenvectors[:, 1:].T @ (perp / norm))))
    lam = solution.eigenvalues
    return float((lam[j] - lam[0]) / lam[j]) if lam[j] > 0 else float("nan")


# ----------------------------------------------------------------------------- angles
def sun_level_from_angles(azimuth_l: float, zenith_l: float) -> FloatArray:
    """Level-frame sun ``(sin Z cos A, sin Z sin A, cos Z)``, A counter-clockwise from x_l."""
    return np.array(
        [
            np.sin(zenith_l) * np.cos(azimuth_l),
            np.sin(zenith_l) * np.sin(azimuth_l),
            np.cos(zenith_l),
        ]
    )


def yaw_from_sun_level(sun_l: ArrayLike, sun_n: ArrayLike) -> float:
    """Yaw [rad] of body x from the sun in the level and navigation frames (SPEC 10.1):
    ``wrap(atan2(s_n_y, s_n_x) - atan2(s_l_y, s_l_x))``."""
    sl, sn = np.asarray(sun_l, dtype=float), np.asarray(sun_n, dtype=float)
    return float(wrap_angle(np.arctan2(sn[1], sn[0]) - np.arctan2(sl[1], sl[0])))


def yaw_variance_from_sun_covariance(sun_l: ArrayLike, cov_sun_l: ArrayLike) -> float:
    """Yaw variance ``h^T Cov(s) h``, ``h = (-s_y, s_x, 0)/(s_x^2 + s_y^2)`` (SPEC 10.2)."""
    s = np.asarray(sun_l, dtype=float)
    h = np.array([-s[1], s[0], 0.0]) / (s[0] ** 2 + s[1] ** 2)
    return float(h @ np.asarray(cov_sun_l, dtype=float) @ h)


# ----------------------------------------------------------------------------- joint ML
@dataclass(frozen=True)
class _MLData:
    """Component-first pixel data of the joint ML (one dtype, n pixels).

    The lens enters as ``rays`` (3, n) for the projection model (P), whose forward rows
    ``q1 = p x (1, 0, 0)``, ``q2 = p x (0, 1, 0)`` need no storage, or as packed forward rows
    ``forward`` (3, 2n) = [q1 | q2] for any model. ``mask`` (optional) marks the pixels that
    count: the others are evaluated and zeroed, cheaper than compressing the arrays when
    nearly all pixels are valid; their data must be finite.
    """

    s0: NDArray
    s1: NDArray
    s2: NDArray
    c: NDArray  # S0^2 - |L|^2
    forward: NDArray | None  # (3, 2n): [q1 | q2] columns
    rays: NDArray | None  # (3, n), projection model only
    inv_sigma: NDArray | float  # 1/sigma_L per pixel, or one value
    mask: NDArray | None = None

    @property
    def n(self) -> int:
        return int(self.s0.size) if self.mask is None else int(np.count_nonzero(self.mask))


def _pack_forward(forward: NDArray, dtype: DTypeLike) -> NDArray:
    """Forward rows ``(2, 3, n)`` packed as ``(3, 2n)`` = [q1 | q2]."""
    return np.ascontiguousarray(np.concatenate([forward[0], forward[1]], axis=1), dtype=dtype)


def _ml_data(
    s0: NDArray,
    s1: NDArray,
    s2: NDArray,
    forward: NDArray | None,
    inv_sigma: NDArray | float,
    mask: NDArray | None = None,
    packed: bool = False,
    rays: NDArray | None = None,
) -> _MLData:
    """``forward``: (2, 3, n) forward rows, or already packed (3, 2n) with ``packed``; or
    None with ``rays`` (3, n) for the projection lens model."""
    fwd = forward if (packed or forward is None) else _pack_forward(forward, s0.dtype)
    if fwd is None and rays is None:
        raise ValueError("need the forward lens rows or (projection model) the rays")
    c = s0 * s0
    c -= s1 * s1
    c -= s2 * s2
    return _MLData(s0, s1, s2, c, fwd, rays, inv_sigma, mask)


def _ml_data_of(stokes: NDArray, forward: ArrayLike, sigma_l: ArrayLike | float) -> _MLData:
    """:func:`_ml_data` from the public functions' arguments: Stokes ``(n, 3)``, forward
    rows ``(n, 2, 3)`` and a per-pixel or common ``sigma_L``."""
    inv_sigma = 1.0 / np.asarray(sigma_l, dtype=float)
    return _ml_data(
        stokes[:, 0],
        stokes[:, 1],
        stokes[:, 2],
        np.moveaxis(np.asarray(forward, dtype=float), 0, -1),
        float(inv_sigma) if inv_sigma.ndim == 0 else inv_sigma,
    )


def _image_plane_evector(data: _MLData, sun_cols: NDArray) -> NDArray:
    """``(x, y)`` of ``s x p`` in the image plane for each column of ``sun_cols`` (3, k):
    returns (k, 2n) rows [x | y]."""
    dt = data.s0.dtype
    cols = sun_cols.astype(dt)
    if data.rays is None:
        assert data.forward is not None
        return np.einsum("ik,in->kn", cols, data.forward)
    px, py, pz = data.rays
    n = px.size
    out = np.empty((cols.shape[1], 2 * n), dtype=dt)
    for j in range(cols.shape[1]):
        sx, sy, sz = cols[:, j]
        x, y = out[j, :n], out[j, n:]
        np.multiply(pz, sy, out=x)  # x = (s x p)_x = s_y p_z - s_z p_y
        x -= sz * py
        np.multiply(px, sz, out=y)  # y = (s x p)_y = s_z p_x - s_x p_z
        y -= sx * pz
    return out


def _sun_derivatives(theta: NDArray, zenith: float | None) -> tuple[NDArray, list[NDArray]]:
    """Level-frame sun and its derivatives w.r.t. the sun parameters (A[, Z])."""
    a = theta[0]
    z = zenith if zenith is not None else theta[1]
    sa, ca, sz, cz = np.sin(a), np.cos(a), np.sin(z), np.cos(z)
    sun = np.array([sz * ca, sz * sa, cz])
    derivs = [np.array([-sz * sa, sz * ca, 0.0])]
    if zenith is None:
        derivs.append(np.array([cz * ca, cz * sa, -sz]))
    return sun, derivs


@dataclass(frozen=True)
class _Selection:
    """Final pixel selection made inside the full-set evaluation (it shares the predicted
    AoP): base validity, sun exclusion and the DoP cut along the predicted direction."""

    valid: NDArray  # (n,) bool, all criteria that do not depend on the sun
    rays: NDArray  # (3, n)
    cos_exclusion: float
    dop_min: float
    p_min: NDArray | float = 0.0  # minimum polarized intensity [DN] (snr_min sigma_L)


def _doubled_prediction(x: NDArray, y: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """``E^2 (cos 2zeta_R, sin 2zeta_R)`` and ``E^2 = x^2 + y^2`` (+1e-30: the sun's own
    direction, always masked, must not give 0/0) of image-plane E-vectors (x, y)."""
    xx, yy, xy0 = x * x, y * y, x * y
    e2 = xx + yy
    e2 += e2.dtype.type(1e-30)
    n1 = np.subtract(xx, yy, out=xx)
    n2 = np.add(xy0, xy0, out=xy0)
    return n1, n2, e2


def _select(
    data: _MLData, select: _Selection, sun_c: NDArray, n1: NDArray, n2: NDArray, e2: NDArray
) -> NDArray:
    """Final pixel mask: valid, outside the sun circle, and DoP >= d_min and polarized
    intensity >= p_min, both *along the predicted direction*: that component's noise is
    independent of the residual's, so the cut selects no noise (a cut on |L| would, and
    bias epsilon near the sun)."""
    along = n1 * data.s1
    along += n2 * data.s2
    mask = along >= (select.dop_min * e2) * data.s0
    if np.any(select.p_min):
        mask &= along >= e2 * select.p_min
    mask &= select.valid
    mask &= _dot_rows(sun_c.astype(data.s0.dtype), select.rays) <= select.cos_exclusion
    return mask


def _selection_mask(data: _MLData, select: _Selection, sun_c: NDArray) -> NDArray:
    """:func:`_select` for a given camera-frame sun (no residuals)."""
    n = data.s0.size
    xy = _image_plane_evector(data, np.asarray(sun_c, dtype=float)[:, None])
    n1, n2, e2 = _doubled_prediction(xy[0, :n], xy[0, n:])
    return _select(data, select, sun_c, n1, n2, e2)


def _ml_evaluate(
    data: _MLData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    jacobian: bool,
    select: _Selection | None = None,
) -> tuple[NDArray, NDArray | None, NDArray, NDArray | None]:
    """Residuals ``r`` (n,), Jacobian ``(k, n)``, exact unpolarized intensities ``u`` and the
    mask in force, at ``theta = (A[, Z], eps)`` (SPEC 9.2).

    ``r_i = n_i . (L_i - eps u_i w)`` with ``n_i = (-sin 2zeta_R, cos 2zeta_R)``, NOT yet
    divided by sigma_L when sigma_L is one number (the caller scales the normal equations);
    per-pixel sigma_L is applied here. Masked pixels get ``r = 0`` and a zero Jacobian.
    """
    n = data.s0.size
    dt = data.s0.dtype
    eps = float(theta[-1])
    sun_l, dsun_l = _sun_derivatives(theta, zenith)
    cols = mat_cl @ np.column_stack([sun_l, *dsun_l])  # camera frame, (3, 1 + k_sun)
    sun_c = cols[:, 0]
    w = sunlight_direction(sun_c)
    xy = _image_plane_evector(data, cols if jacobian else cols[:, :1])
    x, y = xy[0, :n], xy[0, n:]
    n1, n2, e2 = _doubled_prediction(x, y)
    mask = data.mask
    if select is not None:
        mask = _select(data, select, sun_c, n1, n2, e2)
    inv_e = np.divide(1.0, e2, out=e2)
    if mask is not None:
        inv_e *= mask  # zeroes (cos, sin 2zeta_R), hence r and the Jacobian, of masked pixels
    u = _sunlight_unpolarized(
        data.s0, data.s1, data.s2, data.c, dt.type(eps), w.astype(dt), finite=mask is None
    )
    c2 = np.multiply(n1, inv_e, out=n1)  # (cos 2zeta_R, sin 2zeta_R)
    s2 = np.multiply(n2, inv_e, out=n2)
    # r = n . (L - eps u w) = (c2 S2 - s2 S1) - eps u (n . w),  n . w = c2 w1 - s2 w0
    n_dot_w = c2 * dt.type(w[1])
    n_dot_w -= s2 * dt.type(w[0])
    u_nw = np.multiply(u, n_dot_w, out=n_dot_w)
    r = c2 * data.s2
    r -= s2 * data.s1
    r -= dt.type(eps) * u_nw
    weight = data.inv_sigma if isinstance(data.inv_sigma, np.ndarray) else None
    if weight is not None:
        r *= weight
    if not jacobian:
        return r, None, u, mask
    # Jacobian. d r / d theta_sun = -d(2 zeta_R) (r_hat . L): the O(eps u / p) terms (through
    # w and u) are left out, so the Jacobian is exact for eps = 0 and within ~1% otherwise;
    # the residual, hence the estimate, is exact. d r / d eps = -u (n . w).
    proj = c2 * data.s1
    proj += s2 * data.s2
    proj *= inv_e
    proj *= -2.0
    jac = np.empty((cols.shape[1], n), dtype=dt)
    for j in range(1, cols.shape[1]):
        xj, yj = xy[j, :n], xy[j, n:]
        d2zeta = np.multiply(x, yj, out=jac[j - 1])
        d2zeta -= y * xj
        d2zeta *= proj
    np.negative(u_nw, out=jac[-1])
    if weight is not None:
        jac *= weight
    return r, jac, u, mask


def _normal_equations(
    r: NDArray, jac: NDArray, weights: NDArray | None
) -> tuple[FloatArray, FloatArray, float]:
    """``J^T W J``, ``J^T W r`` and ``r^T W r`` in float64 (row dot products: BLAS gemm is
    slow for these thin shapes)."""
    k = jac.shape[0]
    jw = jac if weights is None else jac * weights
    jtj = np.empty((k, k))
    for a in range(k):
        for b in range(a, k):
            jtj[a, b] = jtj[b, a] = _dot(jw[a], jac[b])
    jtr = np.array([_dot(jw[a], r) for a in range(k)])
    rss = _dot(r, r) if weights is None else _dot(r * weights, r)
    return jtj, jtr, rss


def _loss_weights(r: NDArray, loss: str, n: int) -> tuple[NDArray | None, float]:
    """IRLS weights of the robust loss and the residual scale (MAD of the n counted
    residuals; zeros from masked pixels are left out) used for them."""
    if loss == "linear":
        return None, 1.0
    a = np.abs(r)
    if n < r.size:
        a_used = np.sort(a)[r.size - n :]  # masked pixels have r = 0 exactly
    else:
        a_used = a
    scale = max(1.4826 * float(np.median(a_used)), 1e-12)
    t = a / scale
    if loss == "huber":
        return np.minimum(1.0, _HUBER_K / np.maximum(t, 1e-30)).astype(r.dtype), scale
    if loss == "cauchy":
        return (1.0 / (1.0 + (t / _CAUCHY_C) ** 2)).astype(r.dtype), scale
    raise ValueError(f"loss={loss!r}: expected one of {LOSSES}")


def _robust_variance_factor(r: NDArray, loss: str, scale: float, n: int, dof: int) -> float:
    """``sigma^2`` of ``Cov = sigma^2 (J^T J)^-1`` (Huber's M-estimator sandwich)."""
    t = r.astype(float) / scale
    if loss == "huber":
        psi = np.clip(t, -_HUBER_K, _HUBER_K)
        dpsi_sum = float(np.count_nonzero(np.abs(t) <= _HUBER_K)) - (r.size - n)
    else:
        q = 1.0 + (t / _CAUCHY_C) ** 2
        psi = t / q
        dpsi_sum = float(np.sum((1.0 - (t / _CAUCHY_C) ** 2) / (q * q))) - (r.size - n)
    mean_dpsi = max(dpsi_sum / max(n, 1), 1e-12)
    return scale**2 * _dot(psi, psi) / max(n - dof, 1) / mean_dpsi**2


@dataclass(frozen=True)
class MLSolution:
    """Joint ML estimate of SPEC 9.2.

    Attributes
    ----------
    theta : (k,)
        (A_l[, Z_l], eps); A_l counter-clockwise from x_l [rad].
    covariance : (k, k)
        ``sigma_hat^2 (J^T J)^-1`` (robust sandwich for Huber/Cauchy).
    sun_l : (3,)
        Level-frame unit sun vector.
    residual_rms : float
        RMS of the normalised residuals (about 1 when the noise model holds).
    iterations : int
    converged : bool
    n : int
        Pixels used.
    """

    theta: FloatArray
    covariance: FloatArray
    sun_l: FloatArray
    residual_rms: float
    iterations: int
    converged: bool
    n: int = 0


def _gauss_newton(
    data: _MLData,
    theta0: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    *,
    loss: str,
    max_iterations: int,
    tol: float = 1e-9,
    tol_sigma: float = 1e-2,
    select: _Selection | None = None,
) -> tuple[MLSolution, NDArray | None]:
    """Gauss-Newton (IRLS for robust losses) on ``data``; with ``max_iterations=1`` it is the
    single full-set step of the subsample-then-full scheme (docs/measurement.md). ``select``
    makes the pixel selection at the first evaluation (then fixed); returns it as the mask."""
    theta = np.asarray(theta0, dtype=float).copy()
    converged = False
    it = 0
    k_sun = 1 if zenith is not None else 2
    r = np.zeros(0)
    jtj = np.eye(theta.size)
    jtr = np.zeros(theta.size)
    scale, rss, n = 1.0, 0.0, data.n
    r_scale = 1.0 if isinstance(data.inv_sigma, np.ndarray) else float(data.inv_sigma)
    if loss == "linear" and r_scale != 1.0:
        # Scale the normal equations instead of every residual.
        data = dataclasses.replace(data, inv_sigma=1.0)
        post_scale, r_scale = r_scale, 1.0
    else:
        post_scale = 1.0
    mask = data.mask
    for it in range(1, max_iterations + 1):  # noqa: B007
        r, jac, _, mask = _ml_evaluate(data, theta, zenith, mat_cl, True, select)
        if select is not None:
            data = dataclasses.replace(data, mask=mask)
            select = None
            n = data.n
        assert jac is not None
        if r_scale != 1.0:
            r = r * r.dtype.type(r_scale)  # a common 1/sigma_L, for the robust weights
            jac = jac * jac.dtype.type(r_scale)
        weights, scale = _loss_weights(r, loss, n)
        jtj, jtr, rss = _normal_equations(r, jac, weights)
        jtj *= post_scale**2
        jtr *= post_scale**2
        rss *= post_scale**2
        try:
            step = -np.linalg.solve(jtj, jtr)
            jtj_inv = np.linalg.inv(jtj)
        except np.linalg.LinAlgError:
            break
        theta = theta + step
        # Converged when the sun step is below tol [rad], or negligible (tol_sigma sigma)
        # against the statistical uncertainty (e.g. the float32 floor of noise-free data).
        sigma_sun = np.sqrt(rss / max(n - theta.size, 1) * np.abs(np.diag(jtj_inv)[:k_sun]))
        if np.all(np.abs(step[:k_sun]) <= np.maximum(tol, tol_sigma * sigma_sun)):
            converged = True
            break
    dof = theta.size
    if loss == "linear":
        # Residual sum of squares after the last step, to second order.
        try:
            rss_after = max(rss - float(jtr @ np.linalg.solve(jtj, jtr)), 0.0)
        except np.linalg.LinAlgError:
            rss_after = rss
        var = rss_after / max(n - dof, 1)
        rms = float(np.sqrt(rss_after / max(n, 1)))
    else:
        var = _robust_variance_factor(r, loss, scale, n, dof)
        rms = float(np.sqrt(_dot(r, r) / max(n, 1)))
    try:
        cov = var * np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        cov = np.full((dof, dof), np.nan)
    sun_l, _ = _sun_derivatives(theta, zenith)
    theta[0] = float(wrap_angle(theta[0]))
    return MLSolution(theta, np.asarray(cov, dtype=np.float64), sun_l, rms, it, converged, n), mask


def ml_residuals(
    stokes: ArrayLike,
    forward: ArrayLike,
    mat_cl: ArrayLike,
    sun_l: ArrayLike,
    epsilon: float,
    sigma_l: ArrayLike | float = 1.0,
) -> FloatArray:
    """Normalised AoP-orthogonal residuals of SPEC 9.2, ``(n,)``, at a given sun and epsilon.

    ``r_i = n_i . (L_i - eps u_i w) / sigma_L,i`` = ``p_i sin(2 (zeta_corr - zeta_R))/sigma_L``.

    Parameters
    ----------
    stokes : (n, 3) measured Stokes [DN]. forward : (n, 2, 3) :func:`lens_forward` rows.
    mat_cl : (3, 3) level -> camera rotation matrix. sun_l : (3,) unit level-frame sun.
    sigma_l : per-pixel or common sigma_L [DN].
    """
    s = np.asarray(stokes, dtype=float)
    sl = np.asarray(sun_l, dtype=float)
    sl = sl / np.linalg.norm(sl)
    theta = np.array([np.arctan2(sl[1], sl[0]), np.arccos(np.clip(sl[2], -1, 1)), epsilon])
    data = _ml_data_of(s, forward, sigma_l)
    r, _, _, _ = _ml_evaluate(data, theta, None, np.asarray(mat_cl, dtype=float), False)
    return r if isinstance(data.inv_sigma, np.ndarray) else r * data.inv_sigma


def sun_joint_ml(
    stokes: ArrayLike,
    forward: ArrayLike,
    mat_cl: ArrayLike,
    sun_l0: ArrayLike,
    *,
    epsilon0: float = 0.0,
    sigma_l: ArrayLike | float = 1.0,
    zenith: float | None = None,
    loss: str = "linear",
    max_iterations: int = 10,
) -> MLSolution:
    """Joint maximum-likelihood sun vector and direct-sunlight coefficient (SPEC 9.2).

    Minimises ``sum_i rho(r_i)`` over theta = (A_l, Z_l, eps), or (A_l, eps) with the zenith
    fixed to ``zenith`` (the ephemeris' apparent zenith: the fixed-zenith variant), by
    Gauss-Newton from ``sun_l0`` (e.g. the eigen solution).

    Parameters
    ----------
    stokes : (n, 3) measured Stokes [DN]. forward : (n, 2, 3) :func:`lens_forward` rows.
    mat_cl : (3, 3) level -> camera rotation matrix.
    sun_l0 : (3,) starting level-frame sun. epsilon0 : starting epsilon.
    sigma_l : per-pixel or common sigma_L [DN] (only relative values matter for the estimate;
        the covariance is rescaled by the residual variance).
    zenith : fixed sun zenith [rad] or None (estimated).
    loss : {"linear", "huber", "cauchy"}
    """
    if loss not in LOSSES:
        raise ValueError(f"loss={loss!r}: expected one of {LOSSES}")
    s = np.asarray(stokes, dtype=float)
    if s.ndim != 2 or s.shape[1] != 3:
        raise ValueError(f"stokes must have shape (n, 3), got {s.shape}")
    sl = np.asarray(sun_l0, dtype=float)
    sl = sl / np.linalg.norm(sl)
    a0 = np.arctan2(sl[1], sl[0])
    theta0 = [a0, epsilon0] if zenith is not None else [a0, np.arccos(sl[2]), epsilon0]
    data = _ml_data_of(s, forward, sigma_l)
    solution, _ = _gauss_newton(
        data,
        np.asarray(theta0),
        zenith,
        np.asarray(mat_cl, dtype=float),
        loss=loss,
        max_iterations=max_iterations,
    )
    return solution
