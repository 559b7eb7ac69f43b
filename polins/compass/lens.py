"""Lens constants: the per-pixel vectors that carry the lens polarization model into the estimators.

Lens polarization models (docs/model.md §6.1) enter the estimators through two per-pixel
constants, both built in the camera frame from the pixel ray ``p``
(docs/measurement.md §2):

* the *inverse basis* ``T = [t1 t2]`` ``(..., 3, 2)``: the E-vector of image-plane AoP zeta
  is ``e ~ t1 cos zeta + t2 sin zeta`` (P: ``t1 = (1, 0, -p_x/p_z)``, ``t2 = (0, 1, -p_y/p_z)``;
  M: the meridian basis turned by the ray azimuth, orthonormal);
* the *forward rows* ``Q = [q1; q2]`` ``(..., 2, 3)``: the Rayleigh E-vector ``s x p`` of a
  sun ``s`` appears in the image plane along ``(x, y) = (q1 . s, q2 . s)``, i.e. the AoP is
  ``atan2(y, x)`` (P: ``q_j = p x f_j`` with ``f1 = (1, 0, 0)``, ``f2 = (0, 1, 0)``; M:
  ``q_j = p x t_j``). ``(x, y)`` is linear in ``s``, which makes the Jacobians of the joint
  ML cheap and exact.

The ``*_rows`` functions are the component-first row kernels (``(3, n)`` rays) of the
per-image chain; :func:`camera_constants` caches them per camera for the field of view, and
:func:`subsample` for every ``stride``-th pixel of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

from polins.compass.camera import pixel_rays_c
from polins.compass.pixels import PixelSet, pixel_set
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = [
    "CameraConstants",
    "camera_constants",
    "evector_rows",
    "evectors_from_stokes",
    "lens_basis",
    "lens_basis_rows",
    "lens_forward",
    "lens_forward_rows",
    "pack_forward",
    "subsample",
]


# ----------------------------------------------------------------------------- row kernels
def _ray_azimuth(rays: NDArray) -> tuple[NDArray, NDArray]:
    px, py = rays[0], rays[1]
    rho = np.hypot(px, py)
    safe = rho > 1e-15
    cos_a = np.where(safe, px / np.where(safe, rho, 1.0), 1.0)
    sin_a = np.where(safe, py / np.where(safe, rho, 1.0), 0.0)
    return cos_a, sin_a


def lens_basis_rows(rays: NDArray, model: str) -> NDArray:
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


def lens_forward_rows(rays: NDArray, model: str) -> NDArray:
    """Forward rows ``(2, 3, n)`` of component-first rays ``(3, n)``: ``q_j = p x f_j``."""
    if model == "projection":
        f = np.zeros((2, 3, rays.shape[1]))
        f[0, 0] = 1.0
        f[1, 1] = 1.0
    else:
        f = np.moveaxis(lens_basis_rows(rays, model), 1, 0)  # (2, 3, n): t1, t2
    return np.stack([np.cross(rays, f[j], axis=0) for j in range(2)])


def pack_forward(forward: NDArray, dtype: DTypeLike) -> NDArray:
    """Forward rows ``(2, 3, n)`` packed as ``(3, 2n)`` = [q1 | q2]."""
    return np.ascontiguousarray(np.concatenate([forward[0], forward[1]], axis=1), dtype=dtype)


def evector_rows(s1: NDArray, s2: NDArray, basis: NDArray, projection: bool) -> NDArray:
    """Unnormalised camera-frame E-vectors ``(3, n)`` from (S1, S2) rows, without
    trigonometry; ``basis`` is the inverse basis ``(3, 2, n)``, ``projection`` says that it
    is the projection model's (whose first two rows are the identity).

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


# ----------------------------------------------------------------------------- public layout
def lens_basis(rays_c: ArrayLike, model: str) -> FloatArray:
    """Inverse lens basis ``(..., 3, 2)``: ``e ~ T @ (cos zeta, sin zeta)`` (docs/model.md
    §6.1)."""
    rays = np.moveaxis(np.asarray(rays_c, dtype=float), -1, 0)
    return np.moveaxis(lens_basis_rows(rays, model), (0, 1), (-2, -1))


def lens_forward(rays_c: ArrayLike, model: str) -> FloatArray:
    """Forward lens rows ``(..., 2, 3)``: the AoP of the Rayleigh E-vector ``s x p`` is
    ``atan2(q2 . s, q1 . s)`` (docs/model.md §6.1)."""
    rays = np.moveaxis(np.asarray(rays_c, dtype=float), -1, 0)
    return np.moveaxis(lens_forward_rows(rays, model), (0, 1), (-2, -1))


def evectors_from_stokes(stokes: ArrayLike, basis: ArrayLike) -> FloatArray:
    """Unit camera-frame E-vectors ``(..., 3)`` of Stokes vectors ``(..., 3)`` (docs/model.md
    §9.1).

    Parameters
    ----------
    stokes : array_like, (..., 3)
        (S0, S1, S2); only the AoP ``atan2(S2, S1)/2`` is used.
    basis : array_like, (..., 3, 2)
        Inverse lens basis, :func:`lens_basis` of the pixel rays.
    """
    s = np.moveaxis(np.asarray(stokes, dtype=float), -1, 0)
    t = np.moveaxis(np.asarray(basis, dtype=float), (-2, -1), (0, 1))
    e = evector_rows(s[1], s[2], t, projection=False)
    e = e / np.linalg.norm(e, axis=0)
    return np.moveaxis(e, 0, -1)


# ----------------------------------------------------------------------------- per camera
@dataclass(frozen=True, eq=False)
class CameraConstants:
    """Lens constants of a set of pixels of one camera, component-first, in one dtype.

    Attributes
    ----------
    pixels : PixelSet
        The field-of-view pixel set.
    index : (n,) int
        Positions of these pixels in ``pixels`` (all of them, or a subsample).
    rays : (3, n)
        Camera-frame unit rays.
    basis : (3, 2, n)
        Inverse lens basis (:func:`lens_basis_rows`).
    forward : (3, 2n)
        Packed forward rows [q1 | q2] (:func:`pack_forward`).
    projection : bool
        The lens polarization model is the projection model.
    """

    pixels: PixelSet
    index: NDArray
    rays: NDArray
    basis: NDArray
    forward: NDArray
    projection: bool

    @property
    def lens_rays(self) -> NDArray | None:
        """Rays for the joint ML's closed-form forward model (projection model only)."""
        return self.rays if self.projection else None


@lru_cache(maxsize=8)
def _camera_constants64(cam: CameraModel) -> CameraConstants:
    pixels = pixel_set(cam)
    rays = np.ascontiguousarray(pixel_rays_c(cam).reshape(-1, 3)[pixels.index].T)
    basis = lens_basis_rows(rays, cam.polarization_model)
    forward = pack_forward(lens_forward_rows(rays, cam.polarization_model), np.float64)
    index = np.arange(pixels.size)
    return CameraConstants(
        pixels, index, rays, basis, forward, cam.polarization_model == "projection"
    )


@lru_cache(maxsize=8)
def _camera_constants32(cam: CameraModel) -> CameraConstants:
    c = _camera_constants64(cam)
    return CameraConstants(
        c.pixels,
        c.index,
        np.ascontiguousarray(c.rays, dtype=np.float32),
        np.ascontiguousarray(c.basis, dtype=np.float32),
        np.ascontiguousarray(c.forward, dtype=np.float32),
        c.projection,
    )


def camera_constants(cam: CameraModel, dtype: type = np.float64) -> CameraConstants:
    """Lens constants of the camera's field-of-view pixel set, cached (float32 or float64)."""
    return _camera_constants32(cam) if dtype == np.float32 else _camera_constants64(cam)


@lru_cache(maxsize=16)
def _subsample(cam: CameraModel, dtype_name: str, stride: int) -> CameraConstants:
    c = camera_constants(cam, np.dtype(dtype_name).type)
    idx = np.arange(0, c.pixels.size, stride)
    n = c.pixels.size
    fwd = np.concatenate([c.forward[:, idx], c.forward[:, n + idx]], axis=1)
    return CameraConstants(
        c.pixels,
        idx,
        np.ascontiguousarray(c.rays[:, idx]),
        np.ascontiguousarray(c.basis[..., idx]),
        np.ascontiguousarray(fwd),
        c.projection,
    )


def subsample(cam: CameraModel, dtype: type, stride: int) -> CameraConstants:
    """Lens constants of every ``stride``-th pixel of the field-of-view set, cached."""
    return _subsample(cam, np.dtype(dtype).name, stride)
