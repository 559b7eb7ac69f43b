"""Sensor model files: typed, strict loading of the camera and IMU models (TOML).

Shipped models live in ``models/`` (installed as the ``polins.models`` package data):
``models/cameras/<name>.toml`` and ``models/imus/<name>.toml``. Every key carries its unit
in its name (``fov_max_deg``, ``arw_deg_per_sqrt_h``); the loaders convert to SI and
radians, and reject unknown keys, missing keys, keys in the wrong unit and IMU values
outside the plausible range of their grade (``IMU_PLAUSIBLE_RANGES``, docs/imu-model.md)
with a message that names the file and the key.
"""

from __future__ import annotations

import difflib
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from polins.errors import UserInputError

FloatArray = NDArray[np.float64]

_DEG_PER_H = np.pi / 180.0 / 3600.0  # [rad/s] per [deg/h]
_MG = 9.80665e-3  # [m/s^2] per [mg]


class ModelFileError(UserInputError):
    """A model file is missing a key, has an unknown key, or a bad value."""


# ----------------------------------------------------------------------------- schema
def _number(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise TypeError("expected a number")
    return float(v)


def _positive(v: Any) -> float:
    x = _number(v)
    if not x > 0:
        raise ValueError("expected a positive number")
    return x


def _nonneg(v: Any) -> float:
    x = _number(v)
    if not x >= 0:
        raise ValueError("expected a number >= 0")
    return x


def _integer(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
        raise TypeError("expected a positive integer")
    return int(v)


def _string(v: Any) -> str:
    if not isinstance(v, str):
        raise TypeError("expected a string")
    return v


def _boolean(v: Any) -> bool:
    if not isinstance(v, bool):
        raise TypeError("expected true or false")
    return v


def _vector(n: int) -> Callable[[Any], FloatArray]:
    def check(v: Any) -> FloatArray:
        arr = np.asarray([_number(x) for x in v], dtype=float) if isinstance(v, list) else None
        if arr is None or arr.shape != (n,):
            raise TypeError(f"expected a list of {n} numbers")
        return arr

    return check


def _matrix(rows: int, cols: int) -> Callable[[Any], FloatArray]:
    def check(v: Any) -> FloatArray:
        if not isinstance(v, list) or len(v) != rows:
            raise TypeError(f"expected a {rows}x{cols} nested list")
        return np.stack([_vector(cols)(row) for row in v])

    return check


def _choice(*options: str) -> Callable[[Any], str]:
    def check(v: Any) -> str:
        if v not in options:
            raise ValueError(f"expected one of {', '.join(repr(o) for o in options)}")
        return str(v)

    return check


def _polygons(v: Any) -> tuple[FloatArray, ...]:
    if not isinstance(v, list):
        raise TypeError("expected a list of polygons [[u, v], ...]")
    polys = []
    for poly in v:
        if not isinstance(poly, list) or len(poly) < 3:
            raise TypeError("each polygon needs at least 3 [u, v] vertices")
        polys.append(_matrix(len(poly), 2)(poly))
    return tuple(polys)


Schema = Mapping[str, Any]  # key -> validator, or key -> nested Schema for a table


def _validate(data: Mapping[str, Any], schema: Schema, path: Path, prefix: str = "") -> dict:
    out: dict[str, Any] = {}
    for key in data:
        if key not in schema:
            guess = difflib.get_close_matches(key, list(schema), n=1, cutoff=0.5)
            hint = (
                f"; did you mean '{prefix}{guess[0]}' (note the unit in the name)?" if guess else ""
            )
            raise ModelFileError(
                f"{path}: unknown key '{prefix}{key}'{hint} (allowed: {', '.join(sorted(schema))})"
            )
    for key, rule in schema.items():
        if key not in data:
            raise ModelFileError(f"{path}: missing key '{prefix}{key}'")
        value = data[key]
        if isinstance(rule, Mapping):
            if not isinstance(value, dict):
                raise ModelFileError(f"{path}: '{prefix}{key}' must be a table [{prefix}{key}]")
            out[key] = _validate(value, rule, path, f"{prefix}{key}.")
            continue
        try:
            out[key] = rule(value)
        except (TypeError, ValueError) as exc:
            raise ModelFileError(f"{path}: key '{prefix}{key}' = {value!r}: {exc}") from None
    return out


def _resolve(name_or_path: str | Path, kind: str) -> Path:
    candidate = Path(name_or_path)
    if candidate.suffix == ".toml" or candidate.exists():
        if not candidate.is_file():
            raise FileNotFoundError(f"{kind} model file not found: {candidate}")
        return candidate
    shipped = shipped_folder(kind) / f"{name_or_path}.toml"
    if not shipped.is_file():
        raise FileNotFoundError(
            f"unknown {kind[:-1]} model {str(name_or_path)!r}: shipped models are "
            f"{', '.join(shipped_models(kind))}; or give a path to a .toml file"
        )
    return shipped


def shipped_folder(kind: str) -> Path:
    """The folder of the shipped ``kind`` models ('cameras' or 'imus').

    Installed, the TOML files are package data beside this module; in a source checkout
    they are the repository's top-level ``models/<kind>`` folder.
    """
    here = Path(__file__).resolve().parent
    for folder in (here / kind, here.parents[1] / "models" / kind):
        if folder.is_dir():
            return folder
    raise FileNotFoundError(f"no shipped {kind} folder beside {here} or in the checkout")


def shipped_models(kind: str) -> list[str]:
    """Names of the models shipped in ``models/<kind>`` (``kind``: 'cameras' or 'imus')."""
    return sorted(p.stem for p in shipped_folder(kind).glob("*.toml"))


def _read(name_or_path: str | Path, kind: str, schema: Schema) -> tuple[Path, dict]:
    path = _resolve(name_or_path, kind)
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ModelFileError(f"{path}: not valid TOML: {exc}") from None
    return path, _validate(data, schema, path)


# ----------------------------------------------------------------------------- camera
_CAMERA_SCHEMA: Schema = {
    "name": _string,
    "description": _string,
    "sensor": {
        "width_px": _integer,
        "height_px": _integer,
        "pixel_pitch_um": _positive,
        "bit_depth": _integer,
        "saturation_dn": _positive,
        "mosaic_layout_deg": _matrix(2, 2),
    },
    "polarizer": {
        "nominal_angle_deg": _vector(4),
        "transmission_angle_deg": _vector(4),
        "gain": _vector(4),
        "efficiency": _vector(4),
        "dark_offset_dn": _vector(4),
    },
    "noise": {"read_noise_dn": _nonneg, "conversion_gain_e_per_dn": _positive},
    "lens": {
        "projection": _choice("kannala-brandt", "pinhole"),
        "polarization_model": _choice("projection", "meridian"),
        "fx_superpixel": _positive,
        "fy_superpixel": _positive,
        "cx_superpixel": _number,
        "cy_superpixel": _number,
        "distortion": lambda v: np.asarray([_number(x) for x in v], dtype=float),
        "fov_max_deg": _positive,
    },
    "mount": {"mat_bc": _matrix(3, 3)},
    "occlusion": {"polygons_superpixel": _polygons},
}


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A DoFP polarization camera with its lens, as read from ``models/cameras/*.toml``.

    Intrinsics are in 2x2 superpixel units (docs/model.md §5): superpixel (i, j) covers
    full-resolution rows 2i..2i+1 and columns 2j..2j+1 and sits at (u, v) = (j, i).
    Channel arrays are ordered by ``nominal_angle_deg`` (0, 45, 90, 135 deg for the IMX250MZR).
    Equality is identity, so a loaded model can key per-camera caches (e.g. pixel rays).
    """

    name: str
    description: str
    path: Path
    width_px: int  # full-resolution mosaic width
    height_px: int
    pixel_pitch_um: float
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

    def downscaled(self, factor: int) -> CameraModel:
        """The same lens and sensor imaged at ``1/factor`` resolution (for fast runs).

        Intrinsics scale about pixel centres: ``f' = f / factor``,
        ``c' = (c + 0.5) / factor - 0.5``; occlusion polygons scale likewise.
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
        )

    def with_changes(self, **changes: Any) -> CameraModel:
        """A copy with some fields replaced (e.g. a swapped channel calibration)."""
        fields = {k: getattr(self, k) for k in self.__dataclass_fields__}
        unknown = set(changes) - set(fields)
        if unknown:
            raise TypeError(f"CameraModel has no field(s) {sorted(unknown)}")
        fields.update(changes)
        return CameraModel(**fields)


def load_camera(name_or_path: str | Path) -> CameraModel:
    """Load a camera model: a shipped name (``"paper-table1"``) or a path to a TOML file.

    Raises
    ------
    FileNotFoundError
        Unknown name or missing file.
    ModelFileError
        Unknown, missing or malformed keys, named with the file.
    """
    path, d = _read(name_or_path, "cameras", _CAMERA_SCHEMA)
    s, pol, lens = d["sensor"], d["polarizer"], d["lens"]

    def fail(key: str, why: str) -> ModelFileError:
        return ModelFileError(f"{path}: key '{key}': {why}")

    if s["width_px"] % 2 or s["height_px"] % 2:
        raise fail("sensor.width_px", "a 2x2 DoFP mosaic needs even width and height")
    nominal = pol["nominal_angle_deg"]
    layout = s["mosaic_layout_deg"]
    if sorted(layout.ravel().tolist()) != sorted(nominal.tolist()):
        raise fail(
            "sensor.mosaic_layout_deg",
            f"unknown mosaic layout {layout.tolist()}: it must hold each of the polarizer "
            f"nominal angles {nominal.tolist()} exactly once",
        )
    channel_at = np.array([[int(np.flatnonzero(nominal == a)[0]) for a in row] for row in layout])
    if np.any(pol["gain"] <= 0) or np.any((pol["efficiency"] <= 0) | (pol["efficiency"] > 1)):
        raise fail("polarizer.gain/efficiency", "gains must be > 0 and efficiencies in (0, 1]")
    if np.any(np.abs(pol["transmission_angle_deg"] - nominal) > 20.0):
        raise fail(
            "polarizer.transmission_angle_deg",
            "more than 20 deg from the nominal labels: degrees expected, and the angles must "
            "follow the image-plane convention (+x_c towards +y_c)",
        )
    if s["saturation_dn"] > 2 ** s["bit_depth"] - 1:
        raise fail("sensor.saturation_dn", f"above the {s['bit_depth']}-bit range")
    n_dist = {"kannala-brandt": (4,), "pinhole": (4, 5, 8)}[lens["projection"]]
    if lens["distortion"].shape[0] not in n_dist:
        raise fail("lens.distortion", f"{lens['projection']} takes {n_dist} coefficients")
    if not 0 < lens["fov_max_deg"] < (100.0 if lens["projection"] == "kannala-brandt" else 90.0):
        raise fail("lens.fov_max_deg", "must be in (0, 100) deg for a fisheye, (0, 90) pinhole")
    if lens["fov_max_deg"] < 10.0:  # a sky camera sees tens of degrees
        raise fail("lens.fov_max_deg", f"{lens['fov_max_deg']:g} deg is implausible for a sky "
                   f"camera: degrees expected (in radians it would be "
                   f"{np.degrees(lens['fov_max_deg']):.1f} deg)")  # fmt: skip
    theta = np.radians(lens["fov_max_deg"])  # image radius of the field of view vs the sensor
    r_fov = lens["fx_superpixel"] * (
        theta if lens["projection"] == "kannala-brandt" else np.tan(theta)
    )
    ratio = r_fov / (0.25 * np.hypot(s["width_px"], s["height_px"]))  # half-diagonal, superpixels
    if not 0.05 <= ratio <= 20.0:
        raise fail("lens.fx_superpixel", f"the field of view ({lens['fov_max_deg']:g} deg) spans "
                   f"{ratio:.3g} x the sensor's half-diagonal: the focal length must be in "
                   "superpixels (2 x 2 pixels) and agree with the sensor size")  # fmt: skip
    mat_bc = d["mount"]["mat_bc"]
    if not np.allclose(mat_bc @ mat_bc.T, np.eye(3), atol=1e-6) or np.linalg.det(mat_bc) < 0:
        raise fail("mount.mat_bc", "not a proper rotation matrix")
    camera_matrix = np.array(
        [
            [lens["fx_superpixel"], 0.0, lens["cx_superpixel"]],
            [0.0, lens["fy_superpixel"], lens["cy_superpixel"]],
            [0.0, 0.0, 1.0],
        ]
    )
    return CameraModel(
        name=d["name"],
        description=d["description"],
        path=path,
        width_px=s["width_px"],
        height_px=s["height_px"],
        pixel_pitch_um=s["pixel_pitch_um"],
        bit_depth=s["bit_depth"],
        saturation_dn=s["saturation_dn"],
        channel_at=channel_at,
        nominal_angle_deg=nominal,
        transmission_angle=np.radians(pol["transmission_angle_deg"]),
        gain=pol["gain"],
        efficiency=pol["efficiency"],
        dark_offset_dn=pol["dark_offset_dn"],
        read_noise_dn=d["noise"]["read_noise_dn"],
        conversion_gain_e_per_dn=d["noise"]["conversion_gain_e_per_dn"],
        projection=lens["projection"],
        polarization_model=lens["polarization_model"],
        camera_matrix=camera_matrix,
        distortion=lens["distortion"],
        fov_max=float(np.radians(lens["fov_max_deg"])),
        mat_bc=mat_bc,
        occlusion_polygons=d["occlusion"]["polygons_superpixel"],
    )


# ----------------------------------------------------------------------------- IMU
_SENSOR_SCHEMA = {
    "gyro": {
        "arw_deg_per_sqrt_h": _nonneg,
        "bias_deg_per_h": _nonneg,
        "bias_rw_deg_per_h_per_sqrt_h": _nonneg,
        "scale_factor_ppm": _nonneg,
    },
    "accel": {
        "vrw_m_per_s_per_sqrt_h": _nonneg,
        "bias_mg": _nonneg,
        "bias_rw_mg_per_sqrt_h": _nonneg,
        "scale_factor_ppm": _nonneg,
    },
}
_IMU_SCHEMA: Schema = {
    "name": _string,
    "description": _string,
    "grade": _choice("navigation", "tactical", "mems"),
    "earth_rate": _boolean,
    "sample_rate_hz": _positive,
    **_SENSOR_SCHEMA,
}


# Plausible ranges per grade, in the TOML's units, [low, high] inclusive; 0 is always
# accepted and means "this error term is absent" (simulations). Each range spans the
# sensors of its class with a margin, and excludes the usual unit mistakes (rad for deg,
# deg/s for deg/h, deg/s/sqrt(Hz) for deg/sqrt(h)). docs/imu-model.md tabulates them.
IMU_PLAUSIBLE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "navigation": {
        "gyro.arw_deg_per_sqrt_h": (1e-4, 0.01),
        "gyro.bias_deg_per_h": (1e-4, 0.1),
        "gyro.bias_rw_deg_per_h_per_sqrt_h": (1e-5, 0.05),
        "gyro.scale_factor_ppm": (0.1, 100.0),
        "accel.vrw_m_per_s_per_sqrt_h": (1e-4, 0.05),
        "accel.bias_mg": (1e-3, 0.2),
        "accel.bias_rw_mg_per_sqrt_h": (1e-5, 0.05),
        "accel.scale_factor_ppm": (1.0, 300.0),
    },
    "tactical": {
        "gyro.arw_deg_per_sqrt_h": (0.005, 0.5),
        "gyro.bias_deg_per_h": (0.05, 50.0),
        "gyro.bias_rw_deg_per_h_per_sqrt_h": (1e-3, 5.0),
        "gyro.scale_factor_ppm": (10.0, 3000.0),
        "accel.vrw_m_per_s_per_sqrt_h": (0.005, 0.3),
        "accel.bias_mg": (0.05, 5.0),
        "accel.bias_rw_mg_per_sqrt_h": (1e-3, 1.0),
        "accel.scale_factor_ppm": (10.0, 3000.0),
    },
    "mems": {
        "gyro.arw_deg_per_sqrt_h": (0.05, 10.0),
        "gyro.bias_deg_per_h": (1.0, 1e5),
        "gyro.bias_rw_deg_per_h_per_sqrt_h": (0.01, 1000.0),
        "gyro.scale_factor_ppm": (100.0, 5e4),
        "accel.vrw_m_per_s_per_sqrt_h": (0.01, 2.0),
        "accel.bias_mg": (0.1, 200.0),
        "accel.bias_rw_mg_per_sqrt_h": (1e-3, 50.0),
        "accel.scale_factor_ppm": (100.0, 5e4),
    },
}


def _check_plausible(path: Path, grade: str, d: Mapping[str, Any]) -> None:
    """Raise a one-line ModelFileError for the first value outside its grade's range."""
    for key, (lo, hi) in IMU_PLAUSIBLE_RANGES[grade].items():
        table, name = key.split(".")
        value = d[table][name]
        if value != 0.0 and not lo <= value <= hi:
            raise ModelFileError(
                f"{path}: key '{key}' = {value:g} is implausible for grade '{grade}': "
                f"expected {lo:g} to {hi:g} (or 0 to switch the term off); check the unit "
                "in the key's name or the grade"
            )


@dataclass(frozen=True)
class ImuModel:
    """IMU error model, in SI units, as read from ``models/imus/*.toml``.

    The error model is, per axis: white noise (ARW / VRW) + a constant turn-on bias
    (1-sigma) + a bias random walk + a constant scale-factor error (1-sigma).
    """

    name: str
    description: str
    path: Path
    grade: str
    earth_rate: bool  # the mechanization includes Earth rate and transport rate
    sample_rate_hz: float
    gyro_arw: float  # [rad/sqrt(s)] (= rad/s/sqrt(Hz))
    gyro_bias: float  # [rad/s] turn-on 1-sigma
    gyro_bias_rw: float  # [rad/s/sqrt(s)]
    gyro_scale_factor: float  # [-] 1-sigma
    accel_vrw: float  # [m/s/sqrt(s)]
    accel_bias: float  # [m/s^2] turn-on 1-sigma
    accel_bias_rw: float  # [m/s^2/sqrt(s)]
    accel_scale_factor: float  # [-] 1-sigma

    def toml_values(self) -> dict[str, dict[str, float]]:
        """The error terms in the TOML's units: ``{"gyro": {...}, "accel": {...}}``.

        The inverse of the unit conversion :func:`load_imu` applies (docs/imu-model.md).
        """
        sqrt_h = 60.0  # sqrt(3600 s)
        return {
            "gyro": {
                "arw_deg_per_sqrt_h": float(np.degrees(self.gyro_arw)) * sqrt_h,
                "bias_deg_per_h": self.gyro_bias / _DEG_PER_H,
                "bias_rw_deg_per_h_per_sqrt_h": self.gyro_bias_rw / _DEG_PER_H * sqrt_h,
                "scale_factor_ppm": self.gyro_scale_factor * 1e6,
            },
            "accel": {
                "vrw_m_per_s_per_sqrt_h": self.accel_vrw * sqrt_h,
                "bias_mg": self.accel_bias / _MG,
                "bias_rw_mg_per_sqrt_h": self.accel_bias_rw / _MG * sqrt_h,
                "scale_factor_ppm": self.accel_scale_factor * 1e6,
            },
        }

    def check_plausible(self) -> None:
        """Raise :class:`ModelFileError` if a value is outside its grade's plausible range."""
        if self.grade not in IMU_PLAUSIBLE_RANGES:
            raise ModelFileError(
                f"{self.path}: unknown grade {self.grade!r}: expected one of "
                f"{', '.join(repr(g) for g in IMU_PLAUSIBLE_RANGES)}"
            )
        _check_plausible(self.path, self.grade, self.toml_values())


def load_imu(name_or_path: str | Path) -> ImuModel:
    """Load an IMU model: a shipped name (``"fins-paper"``, ``"mems-typical"``) or a TOML path.

    The keys and their units are documented in docs/imu-model.md.

    Raises
    ------
    FileNotFoundError
        Unknown name or missing file.
    ModelFileError
        Unknown, missing or malformed keys, or a value outside the plausible range of the
        model's grade (``IMU_PLAUSIBLE_RANGES``), named with the file and the key.
    """
    path, d = _read(name_or_path, "imus", _IMU_SCHEMA)
    _check_plausible(path, d["grade"], d)
    g, a = d["gyro"], d["accel"]
    sqrt_h = 60.0  # sqrt(3600 s)
    return ImuModel(
        name=d["name"],
        description=d["description"],
        path=path,
        grade=d["grade"],
        earth_rate=d["earth_rate"],
        sample_rate_hz=d["sample_rate_hz"],
        gyro_arw=np.radians(g["arw_deg_per_sqrt_h"]) / sqrt_h,
        gyro_bias=g["bias_deg_per_h"] * _DEG_PER_H,
        gyro_bias_rw=g["bias_rw_deg_per_h_per_sqrt_h"] * _DEG_PER_H / sqrt_h,
        gyro_scale_factor=g["scale_factor_ppm"] * 1e-6,
        accel_vrw=a["vrw_m_per_s_per_sqrt_h"] / sqrt_h,
        accel_bias=a["bias_mg"] * _MG,
        accel_bias_rw=a["bias_rw_mg_per_sqrt_h"] * _MG / sqrt_h,
        accel_scale_factor=a["scale_factor_ppm"] * 1e-6,
    )
