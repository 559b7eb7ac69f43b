"""Intrinsics calibration: lens projection and distortion from checkerboard images, through OpenCV.

Record 10-30 images of a flat checkerboard held at varied distances and tilts, covering the
whole field of view, especially its edge (docs/calibrate.md#intrinsics). The board is found
in the S0 (intensity) image of each mosaic, which is at superpixel resolution, so the
intrinsics come out in the superpixel units of the camera model (docs/model.md §5):
pixel (i, j) of the S0 image sits at (u, v) = (j, i), the OpenCV convention. OpenCV does
the work: ``cv2.findChessboardCorners`` and ``cv2.cornerSubPix`` (or
``cv2.findChessboardCornersSB``) for the corners, then
``cv2.fisheye.calibrate`` (Kannala-Brandt, k1..k4) or ``cv2.calibrateCamera`` (pinhole, with
as many distortion coefficients as the base camera has) according to the camera's
projection.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.calibration.images import channel_stack, provenance
from polins.errors import UserInputError
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = ["IntrinsicsResult", "calibrate_intrinsics", "s0_images"]


@dataclass(frozen=True)
class IntrinsicsResult:
    """Lens intrinsics fitted to checkerboard images.

    Attributes
    ----------
    camera_matrix : (3, 3)
        K in superpixel units.
    distortion : (n,)
        Kannala-Brandt k1..k4, or OpenCV pinhole coefficients.
    reprojection_rms_px : float
        RMS distance between the reprojected and the detected corners [superpixel].
    used : (m,) bool
        Images in which the board was found and kept (an image whose corners reproject
        more than 5x the median, and over 1 superpixel, off is dropped once).
    residuals : list of (N, 2) arrays
        Reprojected minus detected corners of each used image [superpixel].
    provenance : dict
    """

    camera_matrix: FloatArray
    distortion: FloatArray
    reprojection_rms_px: float
    used: NDArray[np.bool_]
    residuals: list[FloatArray]
    provenance: dict[str, Any] = field(default_factory=dict)

    def camera_changes(self) -> dict[str, Any]:
        """The camera-model fields this calibration sets."""
        return {"camera_matrix": self.camera_matrix.copy(), "distortion": self.distortion.copy()}


def s0_images(raws: Sequence[ArrayLike] | ArrayLike, cam: CameraModel) -> FloatArray:
    """Intensity images S0 ``(m, Hs, Ws)`` [DN] of raw mosaics: dark-subtracted,
    gain-corrected channel mean, ``S0 = 1/2 sum_k (I_k - o_k) / g_k`` (unpolarized light)."""
    stack = channel_stack(raws, cam, what="intrinsics")
    return 0.5 * np.sum((stack.channels - cam.dark_offset_dn) / cam.gain, axis=-1)


def _fisheye_flag(name: str) -> int:
    """A ``cv2.fisheye`` calibration flag: in ``cv2.fisheye`` (OpenCV 4) or ``cv2`` (OpenCV 5)."""
    return int(getattr(cv2.fisheye, name, None) or getattr(cv2, name))


def _to_uint8(image: FloatArray) -> NDArray[np.uint8]:
    """8-bit view for the corner finders: the 0.5-99.5 percentile range to 20-235 (saturating
    the squares to 0 and 255 makes the classic detector miss boards)."""
    lo, hi = np.percentile(image, [0.5, 99.5])
    scaled = 20.0 + 215.0 * (image - lo) / max(hi - lo, 1e-9)
    return np.asarray(np.rint(np.clip(scaled, 0.0, 255.0)), dtype=np.uint8)


def _find_corners(gray: NDArray[np.uint8], pattern: tuple[int, int]) -> FloatArray | None:
    """Board corners ``(N, 2)`` [superpixel]: the classic detector refined by
    ``cv2.cornerSubPix``, else ``cv2.findChessboardCornersSB`` (slower, more robust to
    distortion); None when neither finds the board."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if found:
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
    else:
        found, corners = cv2.findChessboardCornersSB(gray, pattern)
        if not found:
            return None
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2)


def _opencv_calibrate(
    obj: FloatArray, found_points: list[FloatArray], size: tuple[int, int], cam: CameraModel
) -> tuple[FloatArray, FloatArray, list[FloatArray]]:
    """K, distortion and per-image reprojection residuals ``(N, 2)`` from OpenCV."""
    # (1, N, 3) / (1, N, 2): the layout cv2.fisheye.calibrate accepts in OpenCV 4 and 5.
    obj_points = [obj.reshape(1, -1, 3).copy() for _ in found_points]
    k0 = cam.camera_matrix.copy()
    if cam.projection == "kannala-brandt":
        fe_flags = (
            _fisheye_flag("CALIB_RECOMPUTE_EXTRINSIC")
            | _fisheye_flag("CALIB_FIX_SKEW")
            | _fisheye_flag("CALIB_USE_INTRINSIC_GUESS")
        )
        _, k, d, rvecs, tvecs = cv2.fisheye.calibrate(
            obj_points,
            found_points,
            size,
            k0,
            cam.distortion.reshape(4, 1).copy(),
            flags=fe_flags,
            criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10),
        )
        projected = [
            cv2.fisheye.projectPoints(o.reshape(-1, 1, 3), r, t, k, d)[0]
            for o, r, t in zip(obj_points, rvecs, tvecs, strict=True)
        ]
    else:
        n_dist = cam.distortion.size
        pin_flags = cv2.CALIB_USE_INTRINSIC_GUESS
        if n_dist == 4:
            pin_flags |= cv2.CALIB_FIX_K3
        elif n_dist == 8:
            pin_flags |= cv2.CALIB_RATIONAL_MODEL
        obj32 = [o.astype(np.float32) for o in obj_points]
        img32 = [p.astype(np.float32) for p in found_points]
        d0 = np.zeros(8 if n_dist == 8 else 5)
        d0[:n_dist] = cam.distortion
        _, k, d, rvecs, tvecs = cv2.calibrateCamera(obj32, img32, size, k0, d0, flags=pin_flags)
        projected = [
            cv2.projectPoints(o, r, t, k, d)[0] for o, r, t in zip(obj32, rvecs, tvecs, strict=True)
        ]
        d = np.ravel(d)[:n_dist]
    residuals = [
        (p.reshape(-1, 2) - f.reshape(-1, 2)).astype(np.float64)
        for p, f in zip(projected, found_points, strict=True)
    ]
    return np.asarray(k, dtype=np.float64), np.ravel(d).astype(np.float64), residuals


def calibrate_intrinsics(
    raws: Sequence[ArrayLike] | ArrayLike,
    cam: CameraModel,
    *,
    board: tuple[int, int],
    square_m: float,
) -> IntrinsicsResult:
    """Camera matrix and distortion from checkerboard images (OpenCV).

    Parameters
    ----------
    raws : array_like, (m, H, W)
        Raw mosaics [DN] showing the board.
    cam : CameraModel
        Base camera: projection, number of distortion coefficients, starting intrinsics,
        dark offsets and gains (for the S0 image).
    board : (int, int)
        Inner corners of the board (columns, rows).
    square_m : float
        Side of a board square [m] (sets the scale of the poses only).

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    UserInputError
        The board found in fewer than 3 images, or bad board arguments.
    """
    cols, rows = board
    if cols < 3 or rows < 3 or not square_m > 0:
        raise UserInputError(
            f"board={board}, square_m={square_m}: need >= 3x3 inner corners and a size > 0"
        )
    images = s0_images(raws, cam)
    obj = np.zeros((rows * cols, 3))
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    found_points, used = [], np.zeros(len(images), dtype=bool)
    for i, image in enumerate(images):  # one OpenCV call per image
        corners = _find_corners(_to_uint8(image), (cols, rows))
        if corners is not None:
            found_points.append(corners.reshape(1, -1, 2))
            used[i] = True
    if len(found_points) < 3:
        raise UserInputError(
            f"intrinsics: the {cols}x{rows} board was found in {len(found_points)} of "
            f"{len(images)} images; need at least 3"
        )
    size = (cam.superpixel_shape[1], cam.superpixel_shape[0])  # OpenCV: (width, height)
    index = np.flatnonzero(used)
    k, d, residuals = _opencv_calibrate(obj, found_points, size, cam)
    # A board whose pose did not converge (or whose corners came out misordered) spoils the
    # RMS: drop images far above the median and calibrate again, once.
    per_image = np.array([np.sqrt(np.mean(np.sum(r**2, axis=-1))) for r in residuals])
    bad = per_image > max(1.0, 5.0 * float(np.median(per_image)))
    if bad.any() and (~bad).sum() >= 3:
        found_points = [p for p, b in zip(found_points, bad, strict=True) if not b]
        used[index[bad]] = False
        k, d, residuals = _opencv_calibrate(obj, found_points, size, cam)
    rms = float(np.sqrt(np.mean(np.concatenate([np.sum(r**2, axis=-1) for r in residuals]))))
    return IntrinsicsResult(
        camera_matrix=k,
        distortion=d,
        reprojection_rms_px=rms,
        used=used,
        residuals=residuals,
        provenance=provenance(
            "intrinsics",
            f"checkerboard {cols}x{rows} on the S0 image, OpenCV "
            + (
                "cv2.fisheye.calibrate"
                if cam.projection == "kannala-brandt"
                else "cv2.calibrateCamera"
            )
            + " (docs/calibrate.md#intrinsics)",
            int(used.sum()),
            reprojection_rms_px=float(f"{rms:.3g}"),
        ),
    )
