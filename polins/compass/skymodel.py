"""The joint ML's sky model: the predicted image-plane E-vector of the Berry four-neutral-point sky.

With ``sky_model="berry"`` the joint ML predicts the AoP of the Berry sky instead of the
Rayleigh sky: the Rayleigh E-vector ``e = s x p`` turned by ``dchi`` about the ray
(:mod:`polins.sky.neutral_points`, docs/model.md §6.3), ``e_B = cos dchi e + sin dchi
(p x e)``, with ``p x (s x p) = s - (p . s) p``. Both terms are linear in the sun, so
their image-plane directions come from the lens forward rows like the Rayleigh one
(docs/measurement.md §2): ``(x, y)`` from ``q_j . s`` and ``(x_perp, y_perp)`` from
``(q_j x p) . s``, which is ``s_j - (p . s) p_j`` for the projection model. The rotation
is held fixed in the Jacobian's sun columns (its own derivative is added by
:func:`berry_evector`'s caller through ``dchi_columns``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from polins.compass.prediction import PixelData, image_plane_evector
from polins.sky.neutral_points import berry_neutral_points_level

__all__ = ["SKY_MODELS", "SkyModel", "berry_evector", "sky_evector", "sky_model"]

SKY_MODELS = ("rayleigh", "berry")
_SEP_FLOOR = 1e-3  # [rad]: the separation's square is evaluated at least at this


@dataclass(frozen=True)
class SkyModel:
    """The joint ML's model beyond the Rayleigh sky, on one pixel set.

    The parameters are ``theta = (A_l[, Z_l][, neutral_sep^2][, delta_perp], eps)`` (the
    square of the separation [rad^2]: the sky is linear in it near zero).

    Attributes
    ----------
    rays : (3, n)
        Camera-frame unit rays of the pixel set (in the dtype of its Stokes rows).
    inv_1pz : (n,)
        ``1 / (1 + p_z)`` (the tangent basis of
        :func:`polins.sky.neutral_points.tangent_components`).
    berry : bool
        The Berry sky (else the Rayleigh sky).
    neutral_sep : float
        Separation of the Babinet and Brewster points [rad] when it is not fitted.
    fit_sep : bool
        ``neutral_sep`` is a parameter.
    fit_delta : bool
        The camera-fixed polarization across the sunlight direction, ``delta_perp``, is a
        parameter (residual term ``- delta_perp S0 (r_hat . w)``).
    """

    rays: NDArray
    inv_1pz: NDArray
    berry: bool = True
    neutral_sep: float = 0.0
    fit_sep: bool = False
    fit_delta: bool = False


def sky_model(
    rays: NDArray, berry: bool, neutral_sep: float, fit_sep: bool, fit_delta: bool
) -> SkyModel | None:
    """:class:`SkyModel` of camera-frame unit rays ``(3, n)``; None for the plain Rayleigh
    model."""
    if not (berry or fit_delta):
        return None
    inv = 1.0 / (rays[2] + rays.dtype.type(1.0))
    return SkyModel(rays, inv, berry, float(neutral_sep), fit_sep and berry, fit_delta)


def sky_evector(
    data: PixelData,
    sky: SkyModel,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    jacobian: bool,
) -> tuple[NDArray, NDArray, float]:
    """Camera-frame parameter columns ``(3, 1 + k)`` (the sun, then its derivatives by the
    sun angles and ``neutral_sep``), the image-plane E-vector rows ``(k + 1, 2n)`` (or
    ``(1, 2n)`` without ``jacobian``) and ``delta_perp``, at ``theta`` (:class:`SkyModel`)."""
    a = float(theta[0])
    k_sun = 1 if zenith is not None else 2
    z = float(zenith if zenith is not None else theta[1])
    # fitted: theta holds sep^2 [rad^2], in which the sky is linear near zero (dchi ~ sep^2)
    sep = float(np.sqrt(max(theta[k_sun], _SEP_FLOOR**2))) if sky.fit_sep else sky.neutral_sep
    delta = float(theta[-2]) if sky.fit_delta else 0.0
    sa, ca, sz, cz = np.sin(a), np.cos(a), np.sin(z), np.cos(z)
    sun_cols = [np.array([sz * ca, sz * sa, cz]), np.array([-sz * sa, sz * ca, 0.0])]
    if zenith is None:
        sun_cols.append(np.array([cz * ca, cz * sa, -sz]))
    if sky.fit_sep:
        sun_cols.append(np.zeros(3))
    cols = mat_cl @ np.column_stack(sun_cols)
    if not jacobian:
        cols = cols[:, :1]
    if not sky.berry:
        return cols, image_plane_evector(data, cols), delta
    babinet, brewster = berry_neutral_points_level(a, z, sep)
    babinet[:, 3] *= 0.5 / sep  # d/d(sep^2)
    brewster[:, 3] *= 0.5 / sep
    keep = [0, 1] + ([2] if zenith is None else []) + ([3] if sky.fit_sep else [])
    keep = keep[: cols.shape[1]]
    xy = berry_evector(data, sky, cols, mat_cl @ babinet[:, keep], mat_cl @ brewster[:, keep])
    return cols, xy, delta


def berry_evector(
    data: PixelData, sky: SkyModel, sun_cols: NDArray, babinet_cols: NDArray, brewster_cols: NDArray
) -> NDArray:
    """``(x, y)`` of the Berry E-vector in the image plane and its derivatives: (k, 2n) rows
    [x | y] like :func:`polins.compass.prediction.image_plane_evector`, for camera-frame
    columns (3, k) of the sun, the Babinet and the Brewster points (the points, then their
    derivatives by the parameters).

    A derivative row is ``c (x', y') + s (x_perp', y_perp') + dchi' (-s (x, y) + c
    (x_perp, y_perp))`` with ``(c, s)`` parallel to ``(cos dchi, sin dchi)``: the
    derivative of ``e_B`` up to a common scale, which leaves the angle's derivative exact;
    ``2 dchi' = Im(a_1'/a_1) + Im(a_2'/a_2) - 2 Im(a_s'/a_s)``. One compiled pass over the
    pixels (:func:`_berry_rows`, numba).
    """
    dt = data.s0.dtype
    n = data.s0.size
    points = np.stack([sun_cols, babinet_cols, brewster_cols]).astype(dt)
    out = np.empty((sun_cols.shape[1], 2 * n), dtype=dt)
    forward = data.forward if data.rays is None else np.empty(0, dtype=dt)
    _compiled()(sky.rays, sky.inv_1pz, points, forward, out)
    return out


def _tangent(px, py, inv, sx, sy, sz):  # pragma: no cover - compiled by numba
    """Tangent components of a point ``s`` at the ray ``p``
    (:func:`polins.sky.neutral_points.tangent_components`), ``inv = 1 / (1 + p_z)``."""
    kap = (px * sx + py * sy) * inv + sz
    return sx - px * kap, sy - py * kap


def _pair_projection(px, py, pz, sx, sy, sz):  # pragma: no cover - compiled by numba
    """Image-plane directions ``(x, y)`` of ``s x p`` and ``(x_perp, y_perp)`` of
    ``p x (s x p)`` for the projection lens model."""
    ps = px * sx + py * sy + pz * sz
    return sy * pz - sz * py, sz * px - sx * pz, sx - ps * px, sy - ps * py


def _pair_forward(forward, i, n, px, py, pz, sx, sy, sz):  # pragma: no cover - compiled by numba
    """:func:`_pair_projection` for any lens model: packed forward rows ``(3, 2n)``, pixel
    ``i``."""
    ex, ey, ez = sy * pz - sz * py, sz * px - sx * pz, sx * py - sy * px
    x = forward[0, i] * sx + forward[1, i] * sy + forward[2, i] * sz
    y = forward[0, n + i] * sx + forward[1, n + i] * sy + forward[2, n + i] * sz
    xp = -(forward[0, i] * ex + forward[1, i] * ey + forward[2, i] * ez)
    yp = -(forward[0, n + i] * ex + forward[1, n + i] * ey + forward[2, n + i] * ez)
    return x, y, xp, yp


def _base(px, py, pz, inv, points, pair):  # pragma: no cover - compiled by numba
    """The Berry E-vector's rotation at one pixel: ``(c, s)`` parallel to ``(cos dchi, sin
    dchi)``, the twist's factors and ``d e_B / d dchi``, from the sun's image-plane
    ``pair``; ``points`` (3, 3, 4) as in :func:`_berry_rows`."""
    tiny = points.dtype.type(1e-30)
    half = points.dtype.type(0.5)
    # tangent components of the sun (s), Babinet (a), Brewster (b)
    sr, si = _tangent(px, py, inv, points[0, 0, 0], points[0, 1, 0], points[0, 2, 0])
    ar, ai = _tangent(px, py, inv, points[1, 0, 0], points[1, 1, 0], points[1, 2, 0])
    br, bi = _tangent(px, py, inv, points[2, 0, 0], points[2, 1, 0], points[2, 2, 0])
    pr, pim = ar * br - ai * bi, ar * bi + ai * br
    qr, qi = sr * sr - si * si, -(sr * si + sr * si)
    wr, wi = pr * qr - pim * qi, pr * qi + pim * qr
    c = np.sqrt(wr * wr + wi * wi) + wr
    s = wi
    ns, na, nb = sr * sr + si * si, ar * ar + ai * ai, br * br + bi * bi
    ws, wa, wb = na * nb, half * ns * nb, half * ns * na  # the twist over one denominator
    inv_all = 1 / max(ns * na * nb, tiny)
    x0, y0, xp0, yp0 = pair
    tx, ty = c * xp0 - s * x0, c * yp0 - s * y0  # d e_B / d dchi
    return sr, si, ar, ai, br, bi, ws, wa, wb, inv_all, c, s, tx, ty


def _column(px, py, inv, points, j, pair, base):  # pragma: no cover - compiled by numba
    """``(x, y)`` of column ``j`` of :func:`_berry_rows` at one pixel, from the column's
    image-plane ``pair`` and the pixel's :func:`_base`: ``c (x, y) + s (x_perp, y_perp)``
    and for a derivative column the twist."""
    sr, si, ar, ai, br, bi, ws, wa, wb, inv_all, c, s, tx, ty = base
    x, y, xp, yp = pair
    if j == 0:
        return c * x + s * xp, c * y + s * yp
    dsr, dsi = _tangent(px, py, inv, points[0, 0, j], points[0, 1, j], points[0, 2, j])
    dar, dai = _tangent(px, py, inv, points[1, 0, j], points[1, 1, j], points[1, 2, j])
    dbr, dbi = _tangent(px, py, inv, points[2, 0, j], points[2, 1, j], points[2, 2, j])
    twist = ((ar * dai - ai * dar) * wa + (br * dbi - bi * dbr) * wb
             - (sr * dsi - si * dsr) * ws) * inv_all  # fmt: skip
    return c * x + s * xp + twist * tx, c * y + s * yp + twist * ty


def _berry_rows(rays, inv_1pz, points, forward, out):  # pragma: no cover - compiled by numba
    """The loop of :func:`berry_evector`: ``points`` (3, 3, k) = sun, Babinet, Brewster
    columns (in the dtype of ``rays``); ``forward`` the packed forward rows, 1-D for the
    projection lens model (the dimension chooses the compiled variant); ``out`` (k, 2n).
    One loop per column, which recomputes the rotation (two output rows and an unsigned
    pixel number per loop: it runs in vector lanes)."""
    n = rays.shape[1]
    ray_x, ray_y, ray_z = rays[0], rays[1], rays[2]
    sx, sy, sz = points[0, 0, 0], points[0, 1, 0], points[0, 2, 0]
    for j in range(points.shape[2]):
        out_x, out_y = out[j, :n], out[j, n:]
        jx, jy, jz = points[0, 0, j], points[0, 1, j], points[0, 2, j]
        for i in range(np.uintp(n)):
            px, py, pz, inv = ray_x[i], ray_y[i], ray_z[i], inv_1pz[i]
            if forward.ndim == 1:
                pair = _pair_projection(px, py, pz, sx, sy, sz)
                pair_j = _pair_projection(px, py, pz, jx, jy, jz)
            else:
                pair = _pair_forward(forward, i, n, px, py, pz, sx, sy, sz)
                pair_j = _pair_forward(forward, i, n, px, py, pz, jx, jy, jz)
            base = _base(px, py, pz, inv, points, pair)
            out_x[i], out_y[i] = _column(px, py, inv, points, j, pair_j, base)


@functools.cache
def _compiled() -> Any:
    """:func:`_berry_rows` compiled by numba (imported on first use, not with polins; the
    machine code is cached on disk next to this module; numpy's error model: no checks of
    the divisions, which keep the loop out of vector lanes)."""
    import numba

    for helper in ("_tangent", "_pair_projection", "_pair_forward", "_base", "_column"):
        globals()[helper] = numba.njit(cache=True, fastmath=True, inline="always")(
            globals()[helper]
        )
    return numba.njit(cache=True, fastmath=True, error_model="numpy")(_berry_rows)
