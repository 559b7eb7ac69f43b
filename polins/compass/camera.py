"""Camera geometry (OpenCV) and the lens polarization models of docs/model.md §5 and §6.1.

Pixel coordinates are superpixel coordinates: superpixel (i, j) sits at (u, v) = (j, i).
Projection uses OpenCV (``cv2.fisheye`` Kannala-Brandt, or the standard pinhole model with
distortion). The Kannala-Brandt inverse is the Newton iteration of docs/model.md §5 in numpy
(OpenCV's ``cv2.fisheye.undistortPoints`` flags a few converged points near 80 deg as failed,
and its normalised coordinates ``tan(theta)`` break down at 90 deg); the pinhole inverse is
``cv2.undistortPoints`` with a tight termination criterion (without distortion, the
normalised coordinates directly: the iteration cost about 1 s for a 640 x 360 superpixel
camera's first image).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.models import CameraModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_NEWTON_MAX_ITER = 30
_NEWTON_TOL = 1e-13  # [rad]


def kannala_brandt_theta_d(theta: ArrayLike, k: ArrayLike) -> FloatArray:
    """Distorted angle ``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)`` [rad]."""
    t = np.asarray(theta, dtype=float)
    k1, k2, k3, k4 = np.asarray(k, dtype=float)
    t2 = t * t
    return t * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def kannala_brandt_theta_max(k: ArrayLike) -> float:
    """Largest ray angle [rad] up to which ``theta_d(theta)`` is increasing (invertible)."""
    theta = np.linspace(0.0, np.pi, 100_001)
    increasing = np.diff(kannala_brandt_theta_d(theta, k)) > 0
    stop = np.flatnonzero(~increasing)
    return float(theta[stop[0]] if stop.size else theta[-1])


def kannala_brandt_theta(theta_d: ArrayLike, k: ArrayLike) -> FloatArray:
    """Invert ``theta_d(theta)`` by Newton's method from ``theta_0 = theta_d`` (docs/model.md §5).

    Inputs beyond the invertible range (see :func:`kannala_brandt_theta_max`) give NaN.
    """
    td = np.asarray(theta_d, dtype=float)
    k1, k2, k3, k4 = np.asarray(k, dtype=float)
    theta_max = kannala_brandt_theta_max(k)
    inside = td <= kannala_brandt_theta_d(theta_max, k)
    theta = np.where(inside, td, np.nan)
    for _ in range(_NEWTON_MAX_ITER):
        t2 = theta * theta
        residual = kannala_brandt_theta_d(theta, k) - td
        slope = 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        step = residual / slope
        theta = theta - step
        if not np.nanmax(np.abs(step), initial=0.0) > _NEWTON_TOL:
            break
    return theta


def project(cam: CameraModel, rays_c: ArrayLike) -> FloatArray:
    """Project camera-frame rays ``(..., 3)`` to superpixel coordinates ``(..., 2)`` (u, v)."""
    rays = np.asarray(rays_c, dtype=float)
    pts = np.ascontiguousarray(rays.reshape(-1, 1, 3))
    zero = np.zeros(3)
    if cam.projection == "kannala-brandt":
        uv, _ = cv2.fisheye.projectPoints(pts, zero, zero, cam.camera_matrix, cam.distortion)
    else:
        uv, _ = cv2.projectPoints(pts, zero, zero, cam.camera_matrix, cam.distortion)
    return np.asarray(uv, dtype=float).reshape(*rays.shape[:-1], 2)


def unproject(cam: CameraModel, uv: ArrayLike) -> FloatArray:
    """Unit camera-frame rays ``(..., 3)`` of superpixel coordinates ``(..., 2)``.

    Fisheye pixels outside the invertible range of the lens polynomial give NaN rays.
    """
    uv = np.asarray(uv, dtype=float)
    fx, fy = cam.camera_matrix[0, 0], cam.camera_matrix[1, 1]
    cx, cy = cam.camera_matrix[0, 2], cam.camera_matrix[1, 2]
    if cam.projection == "kannala-brandt":
        x = (uv[..., 0] - cx) / fx
        y = (uv[..., 1] - cy) / fy
        theta = kannala_brandt_theta(np.hypot(x, y), cam.distortion)
        phi = np.arctan2(y, x)
        return np.stack(
            [np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1
        )
    if not np.any(cam.distortion):  # an ideal pinhole: the normalised coordinates themselves
        xy = np.stack([(uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy], axis=-1)
    else:
        pts = np.ascontiguousarray(uv.reshape(-1, 1, 2))
        criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)
        xy = cv2.undistortPoints(pts, cam.camera_matrix, cam.distortion, None, None,
                                 criteria=criteria)  # fmt: skip
        xy = np.asarray(xy, dtype=float).reshape(*uv.shape[:-1], 2)
    rays = np.concatenate([xy, np.ones((*xy.shape[:-1], 1))], axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def superpixel_uv(cam: CameraModel) -> FloatArray:
    """Superpixel coordinates ``(Hs, Ws, 2)``: (u, v) = (j, i)."""
    hs, ws = cam.superpixel_shape
    v, u = np.mgrid[0:hs, 0:ws].astype(float)
    return np.stack([u, v], axis=-1)


@lru_cache(maxsize=8)
def pixel_rays_c(cam: CameraModel) -> FloatArray:
    """Unit camera-frame ray of every superpixel, ``(Hs, Ws, 3)``; cached per camera model.

    Pixels outside the lens model's invertible range are NaN; use :func:`fov_mask`.
    """
    rays = unproject(cam, superpixel_uv(cam))
    rays.setflags(write=False)
    return rays


@lru_cache(maxsize=8)
def fov_mask(cam: CameraModel) -> BoolArray:
    """Superpixels whose ray is within ``cam.fov_max`` of the optical axis and not occluded
    by the model's static occlusion polygons, ``(Hs, Ws)`` bool; cached per camera model."""
    rays = pixel_rays_c(cam)
    with np.errstate(invalid="ignore"):
        mask = rays[..., 2] >= np.cos(cam.fov_max)
    if cam.occlusion_polygons:
        mask &= ~_inside_polygons(cam, cam.occlusion_polygons)
    mask.setflags(write=False)
    return mask


def _inside_polygons(cam: CameraModel, polygons: tuple[FloatArray, ...]) -> BoolArray:
    """Superpixels inside any of ``polygons`` (superpixel ``[u, v]``), ``(Hs, Ws)`` bool."""
    inside = np.zeros(cam.superpixel_shape, dtype=np.uint8)
    cv2.fillPoly(inside, [np.round(p).astype(np.int32) for p in polygons], color=1)
    return inside == 1


@lru_cache(maxsize=8)
def roi_mask(cam: CameraModel) -> BoolArray:
    """The superpixels the measurement uses, ``(Hs, Ws)`` bool, cached per camera:
    :func:`fov_mask` within the camera file's region of interest (``[roi]``: ray angle up
    to ``cam.roi_max_field_angle`` and inside any of ``cam.roi_polygons``;
    docs/measurement.md §4)."""
    mask = np.array(fov_mask(cam))
    if cam.roi_max_field_angle is not None:
        with np.errstate(invalid="ignore"):
            mask &= pixel_rays_c(cam)[..., 2] >= np.cos(cam.roi_max_field_angle)
    if cam.roi_polygons:
        mask &= _inside_polygons(cam, cam.roi_polygons)
    mask.setflags(write=False)
    return mask


# ------------------------------------------------------------------ lens polarization
def _meridian_basis(rays_c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit ``exp(2i alpha)`` of the ray azimuth as (cos 2alpha, sin 2alpha), and the ray's
    meridian basis (e_gamma, e_alpha) of docs/model.md §6.1 (M); the optical axis uses
    alpha = 0."""
    px, py, pz = rays_c[..., 0], rays_c[..., 1], rays_c[..., 2]
    rho = np.hypot(px, py)
    safe = rho > 1e-15
    cos_a = np.where(safe, px / np.where(safe, rho, 1.0), 1.0)
    sin_a = np.where(safe, py / np.where(safe, rho, 1.0), 0.0)
    e_gamma = np.stack([pz * cos_a, pz * sin_a, -rho], axis=-1)
    e_alpha = np.stack([-sin_a, cos_a, np.zeros_like(cos_a)], axis=-1)
    return e_gamma, e_alpha


def doubled_aop_from_evector(evec_c: ArrayLike, rays_c: ArrayLike, model: str) -> FloatArray:
    """Image-plane AoP of a camera-frame E-vector as (cos 2zeta, sin 2zeta), ``(..., 2)``.

    Parameters
    ----------
    evec_c : array_like, (..., 3)
        E-vector in the camera frame (any length; perpendicular to the ray).
    rays_c : array_like, (..., 3)
        Unit observation rays in the camera frame.
    model : {"projection", "meridian"}
        docs/model.md §6.1 lens polarization model (P) or (M).
    """
    e = np.asarray(evec_c, dtype=float)
    if model == "projection":
        ex, ey = e[..., 0], e[..., 1]
    elif model == "meridian":
        e_gamma, e_alpha = _meridian_basis(np.asarray(rays_c, dtype=float))
        a, b = np.sum(e * e_gamma, axis=-1), np.sum(e * e_alpha, axis=-1)
        # zeta = alpha + atan2(b, a): rotate (a, b) by the ray azimuth alpha.
        ca, sa = e_alpha[..., 1], -e_alpha[..., 0]
        ex, ey = a * ca - b * sa, a * sa + b * ca
    else:
        raise ValueError(f"unknown lens polarization model {model!r}")
    norm2 = ex * ex + ey * ey
    return np.stack([(ex * ex - ey * ey) / norm2, 2.0 * ex * ey / norm2], axis=-1)


def evector_from_aop(aop: ArrayLike, rays_c: ArrayLike, model: str) -> FloatArray:
    """Unit camera-frame E-vector ``(..., 3)`` of an image-plane AoP [rad] at rays ``(..., 3)``.

    Inverse of :func:`doubled_aop_from_evector` (up to the sign of the axial E-vector).
    """
    zeta = np.asarray(aop, dtype=float)
    p = np.asarray(rays_c, dtype=float)
    if model == "projection":
        c, s = np.cos(zeta), np.sin(zeta)
        e = np.stack([c, s, -(p[..., 0] * c + p[..., 1] * s) / p[..., 2]], axis=-1)
        return e / np.linalg.norm(e, axis=-1, keepdims=True)
    if model == "meridian":
        e_gamma, e_alpha = _meridian_basis(p)
        alpha = np.arctan2(-e_alpha[..., 0], e_alpha[..., 1])
        d = (zeta - alpha)[..., None]
        return np.cos(d) * e_gamma + np.sin(d) * e_alpha
    raise ValueError(f"unknown lens polarization model {model!r}")
