"""The camera model: a DoFP polarization camera with its lens and calibration, read strictly from TOML.

``models/cameras/<name>.toml`` (or any path) holds the sensor, the polarizer channels, the
noise model, the lens, the mount and the occluders; every key carries its unit in its name
(docs/conventions.md#model-files). Optional parts record a calibration
(docs/calibrate.md): per-pixel maps of gain, transmission angle and efficiency named in
``[polarizer]`` (``.npy`` files beside the TOML, :mod:`polins.models.maps`), and an array
of tables ``[[calibration]]``, one entry per calibration step (kind, UTC date, method,
number of images and fit figures).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.models.maps import load_pixel_map
from polins.models.schema import (
    ModelFileError,
    Optional,
    Schema,
    TableArray,
    choice,
    integer,
    matrix,
    nonneg,
    number,
    polygons,
    positive,
    read_model,
    string,
    table_entry,
    vector,
)

FloatArray = NDArray[np.float64]

__all__ = [
    "CALIBRATION_KINDS",
    "EFFICIENCY_MAP_MAX",
    "MAP_FIELDS",
    "UNCALIBRATED_ANGLE_STD_DEG",
    "UNCALIBRATED_GAIN_STD",
    "CameraModel",
    "calibration_entry",
    "load_camera",
    "mixing_std",
    "uncalibrated_instrumental_std",
]

CALIBRATION_KINDS = (
    "dark",
    "flat",
    "polarizer",
    "sky-rotation",
    "intrinsics",
    "noise",
    "camera-imu",
)
"""The kinds of a ``[[calibration]]`` entry (the estimators of :mod:`polins.calibration`)."""

UNCALIBRATED_GAIN_STD = 0.01
"""1-sigma relative channel-gain error [-] of a camera file without a calibration record
(docs/own-camera.md): a DoFP sensor's channels as delivered differ by 1-2 %."""

UNCALIBRATED_ANGLE_STD_DEG = 0.5
"""1-sigma channel-angle error [deg] of a camera file without a calibration record."""

MAP_FIELDS = {
    "gain_map": "gain_map_npy",
    "transmission_angle_map": "transmission_angle_map_rad_npy",
    "efficiency_map": "efficiency_map_npy",
}
"""Per-pixel map field of :class:`CameraModel` -> its key in the file's ``[polarizer]`` table."""

EFFICIENCY_MAP_MAX = 1.1
"""Largest per-pixel efficiency a map may hold: a fitted map scatters about its channel's
efficiency (<= 1) by its noise, and clipping it at 1 would bias it."""


def mixing_std(
    gain: ArrayLike,
    transmission_angle: ArrayLike,
    efficiency: ArrayLike,
    transmission_angle_std: ArrayLike,
    efficiency_std: ArrayLike,
) -> float:
    """1-sigma [-] of the camera-fixed mixing of the linear Stokes components that channel
    angles and efficiencies known to their standard errors leave (docs/measurement.md §12).

    The channels ``I_k = g_k/2 (S0 + eta_k (S1 cos 2 alpha_k + S2 sin 2 alpha_k))`` are
    inverted with the fitted values; errors ``d alpha_k``, ``d eta_k`` turn the estimated
    ``L = (S1, S2)`` into ``(I + E) L`` with ``E = -[pinv(R) dR]`` (its linear-by-linear
    block). A common angle offset (the rotation part of ``E``) turns every heading alike
    and a common efficiency (its trace) scales the DoP; what bends the AoP across the sky
    is the symmetric traceless part ``[[a, b], [b, -a]]``. With independent errors, the
    mean square of the sigmas of ``a`` and ``b``, square-rooted.
    """
    g = np.asarray(gain, dtype=float)
    alpha = np.asarray(transmission_angle, dtype=float)
    eta = np.asarray(efficiency, dtype=float)
    c, s = np.cos(2 * alpha), np.sin(2 * alpha)
    response = 0.5 * g[:, None] * np.stack([np.ones_like(eta), eta * c, eta * s], -1)
    demod = np.linalg.pinv(response)[1:]  # (2, 4): L from the channels
    # d(row k)/d alpha_k and d(row k)/d eta_k, linear part (2,) each
    d_rows = np.concatenate([(0.5 * g * eta)[:, None] * np.stack([-2 * s, 2 * c], -1),
                             (0.5 * g)[:, None] * np.stack([c, s], -1)])  # fmt: skip
    cols = np.concatenate([demod.T, demod.T])  # (8, 2): pinv(R)[1:, k] of each parameter
    e = -cols[:, :, None] * d_rows[:, None, :]  # (8, 2, 2)
    a = 0.5 * (e[:, 0, 0] - e[:, 1, 1])
    b = 0.5 * (e[:, 0, 1] + e[:, 1, 0])
    var = np.concatenate([np.asarray(transmission_angle_std, float),
                          np.asarray(efficiency_std, float)]) ** 2  # fmt: skip
    return float(np.sqrt(0.5 * (np.sum(a * a * var) + np.sum(b * b * var))))


def uncalibrated_instrumental_std(
    gain: ArrayLike, transmission_angle: ArrayLike, efficiency: ArrayLike
) -> tuple[float, float]:
    """``(instrumental_dop_std, instrumental_mixing_std)`` [-] of channels known only to
    :data:`UNCALIBRATED_GAIN_STD` and :data:`UNCALIBRATED_ANGLE_STD_DEG` (docs/measurement.md
    §12): a relative gain error ``s`` per channel leaves ``s / sqrt(2)`` of polarization per
    Stokes component, the angle errors the mixing of :func:`mixing_std`."""
    eta = np.asarray(efficiency, dtype=float)
    angle_std = np.full(4, np.radians(UNCALIBRATED_ANGLE_STD_DEG))
    mixing = mixing_std(gain, transmission_angle, eta, angle_std, np.zeros(4))
    return float(UNCALIBRATED_GAIN_STD / np.sqrt(2.0)), mixing


def _utc_date(v: Any) -> str:
    """An ISO-8601 UTC time (a string, or a TOML offset date-time), as an ISO string."""
    if isinstance(v, str):
        try:
            v = dt.datetime.fromisoformat(v)
        except ValueError:
            raise ValueError(
                "expected an ISO-8601 UTC time like 2026-05-04T10:30:00+00:00"
            ) from None
    if not isinstance(v, dt.datetime) or v.tzinfo is None or v.utcoffset() != dt.timedelta(0):
        raise ValueError("expected an ISO-8601 UTC time like 2026-05-04T10:30:00+00:00")
    return v.astimezone(dt.UTC).isoformat()


def _figure(v: Any) -> int | float | list[int | float]:
    """A fit figure: a number, or a list of numbers (one per channel, say); not a bool or a
    string."""
    if isinstance(v, list):
        return [_number_figure(x) for x in v]
    return _number_figure(v)


def _number_figure(v: Any) -> int | float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise TypeError("expected a number or a list of numbers")
    return v


_CALIBRATION_ENTRY: Schema = {
    "kind": choice(*CALIBRATION_KINDS),
    "date": _utc_date,
    "method": string,
    "n_images": integer,
}

_CAMERA_SCHEMA: Schema = {
    "name": string,
    "description": string,
    "sensor": {
        "width_px": integer,
        "height_px": integer,
        "pixel_pitch_um": Optional(positive),  # informative: no computation uses it
        "bit_depth": integer,
        "saturation_dn": positive,
        "mosaic_layout_deg": matrix(2, 2),
    },
    "polarizer": {
        "nominal_angle_deg": vector(4),
        "transmission_angle_deg": vector(4),
        "gain": vector(4),
        "efficiency": vector(4),
        "dark_offset_dn": vector(4),
        "instrumental_dop_std": Optional(nonneg),
        "instrumental_mixing_std": Optional(nonneg),
        **{key: Optional(string) for key in MAP_FIELDS.values()},
    },
    "noise": {"read_noise_dn": nonneg, "conversion_gain_e_per_dn": positive},
    "lens": {
        "projection": choice("kannala-brandt", "pinhole"),
        "polarization_model": choice("projection", "meridian"),
        "fx_superpixel": positive,
        "fy_superpixel": positive,
        "cx_superpixel": number,
        "cy_superpixel": number,
        "distortion": lambda v: np.asarray([number(x) for x in v], dtype=float),
        "fov_max_deg": positive,
    },
    "mount": {"mat_bc": matrix(3, 3)},
    "occlusion": {"polygons_superpixel": polygons},
    "roi": Optional({"max_field_angle_deg": Optional(positive), "polygons_px": Optional(polygons)}),
    "calibration": TableArray(
        _CALIBRATION_ENTRY,
        extra=_figure,
        extra_what="fit figures must be numbers or lists of numbers",
    ),
}


def calibration_entry(record: Mapping[str, Any]) -> dict[str, Any]:
    """A ``[[calibration]]`` entry from a calibration's ``provenance`` record, checked like a
    file's entry (kind, ISO-8601 UTC date, method, number of images, numeric figures).

    Raises
    ------
    ModelFileError
        A missing or malformed key.
    """
    return table_entry(record, _CAMERA_SCHEMA["calibration"], Path("calibration record"))


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A DoFP polarization camera with its lens, as read from ``models/cameras/*.toml``.

    Intrinsics are in 2x2 superpixel units (docs/model.md §5): superpixel (i, j) covers
    full-resolution rows 2i..2i+1 and columns 2j..2j+1 and sits at (u, v) = (j, i).
    Channel arrays are ordered by ``nominal_angle_deg`` (0, 45, 90, 135 deg for the IMX250MZR).
    Equality is identity, so a loaded model can key per-camera caches (e.g. pixel rays).

    The optional per-pixel maps ``(Hs, Ws, 4)`` replace the channel values pixel by pixel
    in the Stokes step (docs/measurement.md §1); a NaN entry means "the channel's value".
    ``calibration`` holds the file's ``[[calibration]]`` entries, oldest first.
    """

    name: str
    description: str
    path: Path
    width_px: int  # full-resolution mosaic width
    height_px: int
    pixel_pitch_um: float | None  # [um], optional in the file: no computation uses it
    bit_depth: int
    saturation_dn: float
    channel_at: NDArray[np.int_]  # (2, 2): channel index at mosaic position (row % 2, col % 2)
    nominal_angle_deg: FloatArray  # (4,) vendor labels
    transmission_angle: FloatArray  # (4,) calibrated transmission axes alpha_k [rad]
    gain: FloatArray  # (4,) g_k (the paper's beta_k)
    efficiency: FloatArray  # (4,) eta_k
    dark_offset_dn: FloatArray  # (4,) o_k [DN]
    read_noise_dn: float
    conversion_gain_e_per_dn: float  # inf: no shot noise
    projection: str  # "kannala-brandt" | "pinhole"
    polarization_model: str  # "projection" (docs/model.md §6.1 P) | "meridian" (M)
    camera_matrix: FloatArray  # (3, 3) K in superpixel units
    distortion: FloatArray  # KB: k1..k4; pinhole: OpenCV (k1, k2, p1, p2[, k3 ...])
    fov_max: float  # [rad] largest ray angle from the optical axis that is used
    mat_bc: FloatArray  # (3, 3) camera -> body
    occlusion_polygons: tuple[FloatArray, ...] = field(default=())
    roi_max_field_angle: float | None = None  # [rad] region of interest: field-angle limit
    roi_polygons: tuple[FloatArray, ...] = ()  # region of interest, superpixel [u, v]
    gain_map: FloatArray | None = None  # (Hs, Ws, 4) per-pixel g [-], NaN: channel value
    transmission_angle_map: FloatArray | None = None  # (Hs, Ws, 4) per-pixel alpha [rad]
    efficiency_map: FloatArray | None = None  # (Hs, Ws, 4) per-pixel eta [-]
    calibration: tuple[Mapping[str, Any], ...] = ()  # [[calibration]] entries
    # 1-sigma of the camera-fixed polarization the calibration leaves [-] (docs/measurement.md
    # §12); None: the measurement's default, a calibration good to +-0.5 % in gain
    instrumental_dop_std: float | None = None
    # 1-sigma of the camera-fixed mixing of S1, S2 that the channel angles and efficiencies
    # leave [-] (docs/measurement.md §12); None: 0, the file's angles taken as exact
    instrumental_mixing_std: float | None = None

    def __post_init__(self) -> None:
        expected = (*self.superpixel_shape, 4)
        for name in MAP_FIELDS:
            value = getattr(self, name)
            if value is not None and np.shape(value) != expected:
                raise ValueError(
                    f"CameraModel.{name} has shape {np.shape(value)}; camera {self.name!r} "
                    f"needs {expected} (superpixel rows, columns, 4 channels) or None"
                )

    @property
    def shape(self) -> tuple[int, int]:
        """Full-resolution raw image shape ``(H, W)``."""
        return (self.height_px, self.width_px)

    @property
    def superpixel_shape(self) -> tuple[int, int]:
        """Superpixel image shape ``(H // 2, W // 2)``."""
        return (self.height_px // 2, self.width_px // 2)

    @property
    def rot_bc(self) -> Rotation:
        """Camera-to-body rotation."""
        return Rotation.from_matrix(self.mat_bc)

    @property
    def has_pixel_maps(self) -> bool:
        """The camera carries at least one per-pixel map (gain, angle or efficiency)."""
        return any(getattr(self, name) is not None for name in MAP_FIELDS)

    def pixel_calibration(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Per-pixel gain, transmission angle [rad] and efficiency, each ``(Hs, Ws, 4)``: the
        maps where present and finite, the channel values elsewhere."""
        shape = (*self.superpixel_shape, 4)
        out = []
        for name, channel in (
            ("gain_map", self.gain),
            ("transmission_angle_map", self.transmission_angle),
            ("efficiency_map", self.efficiency),
        ):
            values = getattr(self, name)
            full = np.broadcast_to(channel, shape)
            out.append(full.copy() if values is None else np.where(np.isnan(values), full, values))
        return out[0], out[1], out[2]

    def without_pixel_maps(self) -> CameraModel:
        """The same camera with its per-pixel maps dropped (channel values only)."""
        return self.with_changes(**dict.fromkeys(MAP_FIELDS))

    def downscaled(self, factor: int) -> CameraModel:
        """The same lens and sensor imaged at ``1/factor`` resolution (for fast runs).

        Intrinsics scale about pixel centres: ``f' = f / factor``,
        ``c' = (c + 0.5) / factor - 0.5``; occlusion polygons scale likewise. Per-pixel maps
        are binned: a binned superpixel responds with the mean of its ``factor x factor``
        superpixels' response rows ``g/2 (1, eta cos 2alpha, eta sin 2alpha)`` (exact for a
        scene uniform over the block), from which the binned gain, angle and efficiency
        follow. A binned efficiency map is kept whenever an angle map is (angles that
        differ within a block depolarize); a block whose map entries were all NaN stays NaN.
        """
        if factor < 1 or self.width_px % (2 * factor) or self.height_px % (2 * factor):
            raise ValueError(
                f"factor {factor} must divide the superpixel image {self.superpixel_shape}"
            )
        k = self.camera_matrix.copy()
        k[:2, :2] /= factor
        k[:2, 2] = (k[:2, 2] + 0.5) / factor - 0.5
        return self.with_changes(
            name=f"{self.name}/{factor}",
            width_px=self.width_px // factor,
            height_px=self.height_px // factor,
            camera_matrix=k,
            occlusion_polygons=tuple((p + 0.5) / factor - 0.5 for p in self.occlusion_polygons),
            roi_polygons=tuple((p + 0.5) / factor - 0.5 for p in self.roi_polygons),
            **self._binned_maps(factor),
        )

    def _binned_maps(self, factor: int) -> dict[str, FloatArray | None]:
        if not self.has_pixel_maps or factor == 1:
            return {name: getattr(self, name) for name in MAP_FIELDS}
        hs, ws = self.superpixel_shape
        g, alpha, eta = self.pixel_calibration()
        rows = np.stack([g, g * eta * np.cos(2 * alpha), g * eta * np.sin(2 * alpha)], -1)
        binned = rows.reshape(hs // factor, factor, ws // factor, factor, 4, 3).mean(axis=(1, 3))
        angle = 0.5 * np.arctan2(binned[..., 2], binned[..., 1])
        angle += np.pi * np.round((self.transmission_angle - angle) / np.pi)  # channel's branch
        values = {
            "gain_map": binned[..., 0],
            "transmission_angle_map": angle,
            "efficiency_map": np.hypot(binned[..., 1], binned[..., 2]) / binned[..., 0],
        }
        out: dict[str, FloatArray | None] = {}
        for name, value in values.items():
            source = getattr(self, name)
            if (
                name == "efficiency_map"
                and source is None
                and self.transmission_angle_map is not None
            ):
                source = self.transmission_angle_map  # depolarization by the binned angles
            if source is None:
                out[name] = None
                continue
            empty = np.isnan(source).reshape(hs // factor, factor, ws // factor, factor, 4)
            out[name] = np.where(empty.all(axis=(1, 3)), np.nan, value)
        return out

    def with_changes(self, **changes: Any) -> CameraModel:
        """A copy with some fields replaced (e.g. a swapped channel calibration)."""
        fields = {k: getattr(self, k) for k in self.__dataclass_fields__}
        unknown = set(changes) - set(fields)
        if unknown:
            raise TypeError(f"CameraModel has no field(s) {sorted(unknown)}")
        fields.update(changes)
        return CameraModel(**fields)


def _roi(roi: Mapping[str, Any]) -> tuple[float | None, tuple[FloatArray, ...]]:
    """The file's optional ``[roi]`` table: the field-angle limit [deg -> rad] and the
    polygons in full-resolution pixel coordinates ``[x, y]`` (pixel centres at integers)
    -> superpixel ``[u, v] = ([x, y] - 0.5) / 2``."""
    limit = roi.get("max_field_angle_deg")
    polys = tuple((p - 0.5) / 2.0 for p in roi.get("polygons_px", ()))
    return (None if limit is None else float(np.radians(limit))), polys


def _check_maps(path: Path, maps: dict[str, FloatArray], pol: Mapping[str, Any]) -> None:
    """Map values: finite or NaN, gains > 0, efficiencies in (0, 1], angles near the labels."""
    nominal = np.radians(pol["nominal_angle_deg"])
    for name, arr in maps.items():
        key = f"polarizer.{MAP_FIELDS[name]}"
        finite = np.isfinite(arr)
        if np.any(np.isinf(arr)):
            raise ModelFileError(f"{path}: key '{key}': the map holds infinite values")
        if name == "gain_map" and np.any(arr[finite] <= 0):
            raise ModelFileError(f"{path}: key '{key}': gains must be > 0 (NaN: channel value)")
        if name == "efficiency_map" and np.any(
            (arr[finite] <= 0) | (arr[finite] > EFFICIENCY_MAP_MAX)
        ):
            raise ModelFileError(
                f"{path}: key '{key}': efficiencies must be in (0, {EFFICIENCY_MAP_MAX:g}] "
                "(a fitted map scatters about the channel values, so slightly above 1 is kept)"
            )
        if name == "transmission_angle_map":
            off = np.where(finite, arr - nominal, 0.0)
            if np.any(np.abs(off) > np.radians(20.0)):
                raise ModelFileError(
                    f"{path}: key '{key}': angles more than 20 deg from the nominal labels: "
                    "radians expected, image-plane convention (+x_c towards +y_c)"
                )


def _key_error(path: Path, key: str, why: str) -> ModelFileError:
    """The one-line error for a bad ``key`` of the camera file ``path``."""
    return ModelFileError(f"{path}: key '{key}': {why}")


def _channel_layout(path: Path, s: Mapping[str, Any], pol: Mapping[str, Any]) -> NDArray[np.int_]:
    """Check the sensor and the polarizer channels; returns the channel index of each
    mosaic position (2 x 2)."""
    if s["width_px"] % 2 or s["height_px"] % 2:
        raise _key_error(path, "sensor.width_px", "a 2x2 DoFP mosaic needs even width and height")
    nominal = pol["nominal_angle_deg"]
    layout = s["mosaic_layout_deg"]
    if sorted(layout.ravel().tolist()) != sorted(nominal.tolist()):
        raise _key_error(
            path,
            "sensor.mosaic_layout_deg",
            f"unknown mosaic layout {layout.tolist()}: it must hold each of the polarizer "
            f"nominal angles {nominal.tolist()} exactly once",
        )
    channel_at = np.array([[int(np.flatnonzero(nominal == a)[0]) for a in row] for row in layout])
    if np.any(pol["gain"] <= 0) or np.any((pol["efficiency"] <= 0) | (pol["efficiency"] > 1)):
        raise _key_error(
            path, "polarizer.gain/efficiency", "gains must be > 0 and efficiencies in (0, 1]"
        )
    if np.any(np.abs(pol["transmission_angle_deg"] - nominal) > 20.0):
        raise _key_error(
            path,
            "polarizer.transmission_angle_deg",
            "more than 20 deg from the nominal labels: degrees expected, and the angles must "
            "follow the image-plane convention (+x_c towards +y_c)",
        )
    if s["saturation_dn"] > 2 ** s["bit_depth"] - 1:
        raise _key_error(path, "sensor.saturation_dn", f"above the {s['bit_depth']}-bit range")
    return channel_at


def _check_lens(path: Path, s: Mapping[str, Any], lens: Mapping[str, Any]) -> None:
    """Check the lens: distortion length, field of view in degrees, focal length in
    superpixels consistent with the sensor size."""
    n_dist = {"kannala-brandt": (4,), "pinhole": (4, 5, 8)}[lens["projection"]]
    if lens["distortion"].shape[0] not in n_dist:
        raise _key_error(
            path, "lens.distortion", f"{lens['projection']} takes {n_dist} coefficients"
        )
    if not 0 < lens["fov_max_deg"] < (100.0 if lens["projection"] == "kannala-brandt" else 90.0):
        raise _key_error(
            path, "lens.fov_max_deg", "must be in (0, 100) deg for a fisheye, (0, 90) pinhole"
        )
    if lens["fov_max_deg"] < 10.0:  # a sky camera sees tens of degrees
        raise _key_error(
            path,
            "lens.fov_max_deg",
            f"{lens['fov_max_deg']:g} deg is implausible "
            f"for a sky camera: degrees expected (in radians it would be "
            f"{np.degrees(lens['fov_max_deg']):.1f} deg)",
        )
    theta = np.radians(lens["fov_max_deg"])  # image radius of the field of view vs the sensor
    r_fov = lens["fx_superpixel"] * (
        theta if lens["projection"] == "kannala-brandt" else np.tan(theta)
    )
    ratio = r_fov / (0.25 * np.hypot(s["width_px"], s["height_px"]))  # half-diagonal, superpixels
    if not 0.05 <= ratio <= 20.0:
        raise _key_error(
            path,
            "lens.fx_superpixel",
            f"the field of view "
            f"({lens['fov_max_deg']:g} deg) spans {ratio:.3g} x the sensor's "
            "half-diagonal: the focal length must be in superpixels (2 x 2 "
            "pixels) and agree with the sensor size",
        )


def _pixel_maps(
    path: Path, pol: Mapping[str, Any], superpixel_shape: tuple[int, int]
) -> dict[str, FloatArray]:
    """The per-pixel maps named in ``[polarizer]`` (read-only), read relative to the
    TOML's folder and checked."""
    maps: dict[str, FloatArray] = {}
    for name, key in MAP_FIELDS.items():
        if key in pol:
            map_path = path.parent / pol[key]  # an absolute path stays absolute
            maps[name] = load_pixel_map(
                map_path, superpixel_shape, what=f"{path}: key 'polarizer.{key}'"
            )
            maps[name].setflags(write=False)
    _check_maps(path, maps, pol)
    return maps


def _instrumental_std(d: Mapping[str, Any]) -> dict[str, float | None]:
    """The instrumental DoP and mixing 1-sigma: as stated, or, for the datasheet's
    channels with no calibration record and no stated quality, those of the channels as
    delivered."""
    pol = d["polarizer"]
    instrumental: dict[str, float | None] = {
        k: pol.get(k) for k in ("instrumental_dop_std", "instrumental_mixing_std")
    }
    nominal_channels = (
        np.all(pol["gain"] == 1.0)
        and np.all(pol["efficiency"] == 1.0)
        and np.all(pol["transmission_angle_deg"] == pol["nominal_angle_deg"])
    )
    if (
        nominal_channels
        and not d.get("calibration")
        and all(v is None for v in instrumental.values())
    ):
        # The datasheet's channels, no record, no stated quality: the channels as delivered.
        dop_std, mix_std = uncalibrated_instrumental_std(
            pol["gain"], np.radians(pol["transmission_angle_deg"]), pol["efficiency"]
        )
        instrumental = {"instrumental_dop_std": dop_std, "instrumental_mixing_std": mix_std}
    return instrumental


def load_camera(name_or_path: str | Path) -> CameraModel:
    """Load a camera model: a shipped name (``"paper-table1"``) or a path to a TOML file.

    Per-pixel map files named in ``[polarizer]`` are read relative to the TOML's folder
    (absolute paths are kept) and checked against the sensor's superpixel shape.

    Raises
    ------
    FileNotFoundError
        Unknown name or missing file.
    ModelFileError
        Unknown, missing or malformed keys, or a missing or malformed map file, named with
        the file.
    """
    path, d = read_model(name_or_path, "cameras", _CAMERA_SCHEMA)
    s, pol, lens = d["sensor"], d["polarizer"], d["lens"]
    nominal = pol["nominal_angle_deg"]
    channel_at = _channel_layout(path, s, pol)
    _check_lens(path, s, lens)
    mat_bc = d["mount"]["mat_bc"]
    if not np.allclose(mat_bc @ mat_bc.T, np.eye(3), atol=1e-6) or np.linalg.det(mat_bc) < 0:
        raise _key_error(path, "mount.mat_bc", "not a proper rotation matrix")
    camera_matrix = np.array(
        [
            [lens["fx_superpixel"], 0.0, lens["cx_superpixel"]],
            [0.0, lens["fy_superpixel"], lens["cy_superpixel"]],
            [0.0, 0.0, 1.0],
        ]
    )
    maps = _pixel_maps(path, pol, (s["height_px"] // 2, s["width_px"] // 2))
    roi_limit, roi_polygons = _roi(d.get("roi", {}))
    instrumental = _instrumental_std(d)
    return CameraModel(
        name=d["name"],
        description=d["description"],
        path=path,
        width_px=s["width_px"],
        height_px=s["height_px"],
        pixel_pitch_um=s.get("pixel_pitch_um"),
        bit_depth=s["bit_depth"],
        saturation_dn=s["saturation_dn"],
        channel_at=channel_at,
        nominal_angle_deg=nominal,
        transmission_angle=np.radians(pol["transmission_angle_deg"]),
        gain=pol["gain"],
        efficiency=pol["efficiency"],
        dark_offset_dn=pol["dark_offset_dn"],
        **instrumental,
        read_noise_dn=d["noise"]["read_noise_dn"],
        conversion_gain_e_per_dn=d["noise"]["conversion_gain_e_per_dn"],
        projection=lens["projection"],
        polarization_model=lens["polarization_model"],
        camera_matrix=camera_matrix,
        distortion=lens["distortion"],
        fov_max=float(np.radians(lens["fov_max_deg"])),
        mat_bc=mat_bc,
        occlusion_polygons=d["occlusion"]["polygons_superpixel"],
        roi_max_field_angle=roi_limit,
        roi_polygons=roi_polygons,
        calibration=tuple(d.get("calibration", [])),  # plain dicts: a model pickles
        gain_map=maps.get("gain_map"),
        transmission_angle_map=maps.get("transmission_angle_map"),
        efficiency_map=maps.get("efficiency_map"),
    )
