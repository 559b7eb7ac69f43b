"""Command ``polins calibrate KIND IMAGES... --camera BASE.toml --out NEW.toml``: a camera file from calibration images.

One calibration step per run (docs/calibrate.md): the images are raw mosaics (PNG/TIFF,
full size, in the order given; a folder stands for its images sorted by name), the base
camera supplies what the step does not fit, and the new camera file is written whole
(:func:`polins.io.model_files.write_camera_file`, atomically): the fitted values, the
base camera's ``[[calibration]]`` record plus this step's entry (kind, UTC date, method,
number of images, fit figures), provenance comments at its top and the per-pixel maps as
``.npy`` files in ``--maps-dir`` (default: beside the TOML). A step that fits a channel
quantity (gain, angle, efficiency) drops the base camera's per-pixel map of it unless it
writes a new one, so that an old map never overrides the new channel values.
``polins calibrate check CAMERA IMAGES...`` scores a camera file on images and writes
nothing. ``polins calibrate camera-imu LOG --camera BASE.toml --out NEW.toml`` runs on a
polins log folder instead of images (:mod:`polins.calibration.camera_imu_log`).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from polins.cli.common import ArgumentError, check, finite

__all__ = [
    "CLI_KINDS",
    "cmd_calibrate",
    "cmd_check",
    "frame_clock",
    "read_images",
    "summary_lines",
]

CLI_KINDS = ("dark", "noise", "flat", "polarizer", "sky-rotation", "intrinsics")
"""The kinds ``polins calibrate`` runs from images (camera-imu runs on a log folder)."""

_MAP_SOURCES = {  # result attribute -> camera map field
    "gain_map": "gain_map",
    "angle_map": "transmission_angle_map",
    "efficiency_map": "efficiency_map",
}
_CHANNEL_MAPS = {  # camera field a step fits -> the per-pixel map that would override it
    "gain": "gain_map",
    "transmission_angle": "transmission_angle_map",
    "efficiency": "efficiency_map",
}
_IMAGE_SUFFIXES = (".png", ".tif", ".tiff")


def image_files(items: Sequence[str]) -> list[Path]:
    """The image files of the ``IMAGES`` arguments: files as given, folders expanded to
    their PNG/TIFF files sorted by name."""
    files: list[Path] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES)
            check(bool(found), f"{path}: no PNG or TIFF images in this folder")
            files.extend(found)
        elif not path.is_file():
            raise FileNotFoundError(f"image not found: {path}")
        else:
            files.append(path)
    return files


def read_images(files: Sequence[Path], shape: tuple[int, int], bit_depth: int) -> np.ndarray:
    """Raw mosaics ``(m, H, W)`` of ``files`` (each checked against the camera's size;
    a pixel above the camera's bit depth is a one-line warning)."""
    import sys

    from polins.io.images import bit_depth_warning, read_image

    raws = np.empty((len(files), *shape), dtype=np.uint16)
    warned = False
    for i, path in enumerate(files):
        raw = read_image(path, shape=shape)
        note = None if warned else bit_depth_warning(raw, bit_depth, str(path))
        if note:
            print(f"polins calibrate: warning: {note}", file=sys.stderr)
            warned = True
        raws[i] = raw
    return raws


def _board(text: str) -> tuple[int, int]:
    cols, sep, rows = text.lower().partition("x")
    usage = f"--board {text!r}: expected COLUMNSxROWS of inner corners, e.g. 9x6"
    check(bool(sep) and cols.strip().isdigit() and rows.strip().isdigit(), usage)
    board = (int(cols), int(rows))
    check(min(board) >= 3, f"--board {text}: at least 3x3 inner corners")
    return board


def _angles_deg(text: str, option: str = "--angles-deg") -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.replace(" ", "").split(",") if v != ""])
    except ValueError:
        raise ArgumentError(f"{option} {text!r}: expected numbers separated by commas") from None
    check(values.size > 0 and bool(np.all(np.isfinite(values))),
          f"{option} {text!r}: expected finite numbers separated by commas")  # fmt: skip
    return values


def _turns(text: str | None, n_images: int) -> np.ndarray | None:
    """``--turns-deg`` as radians, one per image (or None)."""
    if text is None:
        return None
    turns = np.radians(_angles_deg(text, "--turns-deg"))
    check(turns.size == n_images, f"--turns-deg: {turns.size} angles for {n_images} images")
    return turns


def frame_clock(files: Sequence[Path]) -> tuple[np.ndarray, str]:
    """The images' clock for a turntable score: the frame counter at the end of every file
    name (a hexadecimal number of 8 digits or more after the last ``_``), else their order."""
    tails = [f.stem.rsplit("_", 1)[-1] for f in files]
    if all(len(t) >= 8 and all(c in "0123456789abcdefABCDEF" for c in t) for t in tails):
        return np.array([int(t, 16) for t in tails], dtype=float), "the file names' frame counter"
    return np.arange(len(files), dtype=float), "the image order"


def _sky_clock(args: argparse.Namespace, n_images: int) -> dict[str, Any]:
    """``times_utc`` and ``site`` of ``--times-utc FILE --lat --lon [--alt]`` (or nothing)."""
    from polins.errors import UserInputError
    from polins.site import Site, to_utc_index

    given = [args.times_utc is not None, args.lat is not None, args.lon is not None]
    if not any(given):
        return {}
    check(all(given), "--times-utc, --lat and --lon go together (the sun's motion needs "
          "the image times and the site)")  # fmt: skip
    path = Path(args.times_utc)
    if not path.is_file():
        raise FileNotFoundError(f"--times-utc: file not found: {path}")
    lines = [ln.strip() for ln in path.read_text(encoding="utf-8-sig").splitlines()]
    times = [ln for ln in lines if ln and not ln.startswith("#")]
    check(len(times) == n_images,
          f"--times-utc {path}: {len(times)} times for {n_images} images")  # fmt: skip
    try:
        times_utc = to_utc_index(times)
    except UserInputError as exc:
        raise ArgumentError(f"--times-utc {path}: {exc}") from None
    return {"times_utc": times_utc, "site": Site(args.lat, args.lon, args.alt)}


def _estimate(kind: str, raws: np.ndarray, base: Any, args: argparse.Namespace) -> Any:
    """Run the estimator of ``kind``; its result (with ``camera_changes`` and provenance)."""
    from polins import calibration as cal

    if kind == "dark":
        return cal.calibrate_dark(raws, base)
    if kind == "noise":
        return cal.calibrate_noise(raws, base)
    if kind == "flat":
        return cal.calibrate_flat(raws, base, pixel_map=args.gain_map)
    if kind == "polarizer":
        angles = None
        if args.angles_deg is not None:
            angles = np.radians(_angles_deg(args.angles_deg))
            check(angles.size == len(raws),
                  f"--angles-deg: {angles.size} angles for {len(raws)} images")  # fmt: skip
        check(0.0 < args.polarizer_dop <= 1.0,
              f"--polarizer-dop {args.polarizer_dop:g}: expected a DoP in (0, 1]")  # fmt: skip
        return cal.calibrate_polarizer(raws, base, angles, polarizer_dop=args.polarizer_dop,
                                       pixel_maps=args.pixel_maps)  # fmt: skip
    if kind == "sky-rotation":
        check(args.rings >= 2, f"--rings {args.rings}: expected an integer >= 2")
        clock = _sky_clock(args, len(raws))
        turns = _turns(args.turns_deg, len(raws))
        return cal.fit_sky_rotation(raws, base, turns=turns, n_rings=args.rings,
                                    min_span_deg=args.min_span_deg,
                                    tilt_terms=not args.aligned_axis,
                                    ifov_correction=not args.no_ifov_correction, **clock)  # fmt: skip
    if kind == "intrinsics":
        check(args.square_mm > 0, f"--square-mm {args.square_mm:g}: expected a size > 0 [mm]")
        return cal.calibrate_intrinsics(raws, base, board=_board(args.board),
                                        square_m=args.square_mm / 1000.0)  # fmt: skip
    raise AssertionError(kind)  # pragma: no cover - argparse limits the kinds


def _std_of(result: Any, key: str) -> Any:
    for name in (f"{key}_std",
                 *(key[: -len(u)] + "_std" + u for u in ("_e_per_dn", "_dn") if key.endswith(u))):  # fmt: skip
        if hasattr(result, name):
            return getattr(result, name)
    return None


def summary_lines(result: Any, cam: Any) -> list[str]:
    """The fitted values (with standard errors where the result has them) and the fit
    figures of a calibration result, one per line (the new file's comments and the
    command's output)."""
    lines = []
    labels = ", ".join(f"{a:g}" for a in cam.nominal_angle_deg)
    for key, value in result.camera_changes().items():
        std = _std_of(result, key)
        if key == "transmission_angle":
            value, std = np.degrees(value), None if std is None else np.degrees(std)
            key = "transmission_angle_deg"
        if key == "camera_matrix":
            k = np.asarray(value)
            lines.append(f"fx, fy, cx, cy [superpixel]: {k[0, 0]:.4f}, {k[1, 1]:.4f}, "
                         f"{k[0, 2]:.4f}, {k[1, 2]:.4f}")  # fmt: skip
            continue
        if key in _MAP_SOURCES.values():
            if value is not None:
                lines.append(f"{key}: per-pixel, {' x '.join(map(str, np.shape(value)))}")
            continue
        if key == "mat_bc":
            rows = np.asarray(value, dtype=float)
            lines.append("mat_bc: " + "; ".join(", ".join(f"{x:.6f}" for x in r) for r in rows))
            continue
        arr = np.atleast_1d(np.asarray(value, dtype=float))
        text = ", ".join(f"{x:.6g}" for x in arr)
        if std is not None and np.all(np.isfinite(std)):
            text += " (std " + ", ".join(f"{x:.2g}" for x in np.atleast_1d(std)) + ")"
        where = f" [channels {labels} deg]" if arr.size == 4 and key != "distortion" else ""
        lines.append(f"{key}{where}: {text}")
    shown = {line.split(" [")[0].split(":")[0] for line in lines}
    for key, value in result.provenance.items():
        if key not in ("kind", "date", "method", "n_images", *shown):
            lines.append(f"{key}: {value}")
    return lines


def _new_camera(base: Any, result: Any, args: argparse.Namespace) -> tuple[Any, list[str]]:
    """The base camera with the result's fields, its new maps, and its calibration entry;
    and notes on the maps dropped or written."""
    from polins.calibration import apply_to_camera
    from polins.models.camera import calibration_entry

    changes: dict[str, Any] = {}
    notes = []
    for attr, field in _MAP_SOURCES.items():
        values = getattr(result, attr, None)
        if values is not None:
            changes[field] = values
    for channel_field, map_field in _CHANNEL_MAPS.items():
        if channel_field in result.camera_changes() and map_field not in changes:
            if getattr(base, map_field) is not None:
                changes[map_field] = None
                notes.append(f"dropped the base camera's {map_field}: this step fits "
                             f"{channel_field} per channel")  # fmt: skip
    cam = apply_to_camera(base, result).with_changes(
        name=args.name or Path(args.out).stem,
        calibration=(*base.calibration, calibration_entry(result.provenance)),
        **changes,
    )
    notes += [f"per-pixel {field} written" for field in _MAP_SOURCES.values() if field in changes
              and changes[field] is not None]  # fmt: skip
    return cam, notes


def cmd_calibrate(args: argparse.Namespace) -> int:
    """``polins calibrate KIND``: fit, then write the new camera file and its maps."""
    from polins.io.model_files import write_camera_file
    from polins.models import load_camera

    kind = args.kind
    out = Path(args.out)
    check(out.suffix == ".toml", f"--out {out}: the camera file must end in .toml")
    check(not out.is_dir(), f"--out {out} is a folder; give a .toml file name")
    if args.maps_dir is not None:
        check(not Path(args.maps_dir).is_file(), f"--maps-dir {args.maps_dir}: is a file")
    base = load_camera(args.camera)
    files = image_files(args.images)
    raws = read_images(files, base.shape, base.bit_depth)
    import warnings

    from polins.calibration import SkyRotationResidualWarning

    with warnings.catch_warnings():  # printed below, and written into the file's comments
        warnings.simplefilter("ignore", SkyRotationResidualWarning)
        result = _estimate(kind, raws, base, args)
    cam, notes = _new_camera(base, result, args)
    notes = [*getattr(result, "notes", ()), *notes]
    if getattr(result, "residual_pattern", ""):
        notes.append(f"warning: the model does not explain these images ({result.residual_pattern});"
                     " the standard errors (and the file's instrumental_*_std) are scaled by it")  # fmt: skip
    prov = result.provenance
    folders = sorted({str(f.parent) for f in files})
    comments = [
        f"camera model written by polins calibrate {kind} (docs/calibrate.md)",
        f"base camera: {base.path}",
        f"{kind}: {prov['method']}",
        f"{prov['n_images']} of {len(files)} images used, from {', '.join(folders)}",
        f"date (UTC): {prov['date']}",
        *summary_lines(result, cam),
        *notes,
        "the [[calibration]] entries at the end record every step of this file",
    ]
    written = write_camera_file(cam, out, comments=comments, maps_dir=args.maps_dir)
    load_camera(out)  # the file reads back (a bug otherwise, not a user mistake)
    print(f"polins calibrate {kind}: {prov['n_images']} images, {prov['method']}")
    print("\n".join(summary_lines(result, cam)))
    for note in notes:
        print(note)
    print(f"wrote {', '.join(str(p) for p in written)}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    """``polins calibrate check CAMERA IMAGES...``: how well the file explains the images."""
    from polins.calibration import check as check_camera
    from polins.models import load_camera

    cam = load_camera(args.camera_file)
    files = image_files(args.images)
    raws = read_images(files, cam.shape, cam.bit_depth)
    if args.turns_deg is not None:
        return _check_turntable(cam, raws, files, args)
    report = check_camera(cam, raws, unpolarized=args.unpolarized)
    if args.json:
        figures = {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                   for k, v in vars(report).items()}  # fmt: skip
        print(json.dumps({"camera": str(cam.path), **figures}, indent=2))
    else:
        print(f"camera {cam.name} ({cam.path})"
              + (", with per-pixel maps" if cam.has_pixel_maps else ""))  # fmt: skip
        print(report.summary())
    return 0


def _check_turntable(cam: Any, raws: np.ndarray, files: Sequence[Path],
                     args: argparse.Namespace) -> int:  # fmt: skip
    """``check --turns-deg``: relative headings of a turntable sequence against its turns."""
    from polins.calibration.turntable import score_turntable

    turns = _turns(args.turns_deg, len(raws))
    assert turns is not None  # the caller checked --turns-deg
    clock, how = frame_clock(files)
    score = score_turntable(raws, cam, turns, clock, method=args.method)
    if args.json:
        out = {"camera": str(cam.path), "rmse_deg": float(np.degrees(score.rmse)),
               "rms_err_over_sigma": score.rms_z, "max_err_over_sigma": score.max_z,
               "n_ok": score.n_ok, "ms_per_image": score.ms_per_image, "clock": how,
               "error_deg": [None if not np.isfinite(e) else float(np.degrees(e))
                             for e in score.error]}  # fmt: skip
        print(json.dumps(out, indent=2))
        return 0
    print(f"camera {cam.name} ({cam.path}), method {args.method}: sun-free headings of "
          f"{len(raws)} images against --turns-deg, an offset and a drift linear in {how} "
          "taken out (modulo 180 deg)")  # fmt: skip
    print(score.summary())
    print("errors [deg]: " + ", ".join(f"{np.degrees(e):.2f}" for e in score.error))
    return 0


def cmd_camera_imu(args: argparse.Namespace) -> int:
    """``polins calibrate camera-imu LOG``: time offset and ``mat_bc`` from a log with turns,
    written as a new camera file (the time offset has no key there: printed, and kept in
    the ``[[calibration]]`` entry)."""
    import warnings

    from scipy.spatial.transform import Rotation

    from polins.calibration import HeldAxisWarning
    from polins.calibration.camera_imu_log import camera_imu_from_log
    from polins.io.log import read_log
    from polins.io.model_files import write_camera_file
    from polins.models import load_camera

    out = Path(args.out)
    check(out.suffix == ".toml", f"--out {out}: the camera file must end in .toml")
    check(not out.is_dir(), f"--out {out} is a folder; give a .toml file name")
    check(args.max_offset_s > 0, f"--max-offset-s {args.max_offset_s:g}: expected > 0 [s]")
    base = load_camera(args.camera)
    log = read_log(args.log)
    check(log.camera.shape == base.shape,
          f"--camera {args.camera}: {base.shape[1]}x{base.shape[0]} pixels, but the log's "
          f"images are {log.camera.shape[1]}x{log.camera.shape[0]}")  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", HeldAxisWarning)
        result, how = camera_imu_from_log(log, base, attitude=args.attitude,
                                          clock=False if args.no_clock else None,
                                          max_offset_s=args.max_offset_s)  # fmt: skip
    held = [str(w.message) for w in caught if issubclass(w.category, HeldAxisWarning)]
    for w in caught:
        if not issubclass(w.category, HeldAxisWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    cam, _ = _new_camera(base, result, args)
    prov = result.provenance
    change = Rotation.from_matrix(cam.mat_bc) * base.rot_bc.inv()
    std = np.degrees(result.boresight_std_b)
    boresight = ("boresight change from the base camera, about body x, y, z [deg]: "
                 + ", ".join(f"{x:.4f}" for x in change.as_rotvec(degrees=True))
                 + " (std " + ", ".join(f"{x:.2g}" for x in std) + ")")  # fmt: skip
    offset = (f"time offset dt = {1e3 * result.time_offset_s:.2f} ms (std "
              f"{1e3 * result.time_offset_std_s:.2g} ms): add it to the image times (the camera "
              "file has no key for it; kept in its [[calibration]] entry)")  # fmt: skip
    comments = [
        "camera model written by polins calibrate camera-imu (docs/calibrate.md#camera-imu)",
        f"base camera: {base.path}",
        f"log: {log.manifest_path}",
        how,
        f"camera-imu: {prov['method']}",
        f"date (UTC): {prov['date']}",
        offset,
        boresight,
        *summary_lines(result, cam),
        *held,
        "the [[calibration]] entries at the end record every step of this file",
    ]
    written = write_camera_file(cam, out, comments=comments, maps_dir=args.maps_dir)
    load_camera(out)  # the file reads back (a bug otherwise, not a user mistake)
    print(f"polins calibrate camera-imu: {how}")
    print(offset)
    print(boresight)
    print("\n".join(summary_lines(result, cam)))
    for line in held:
        print(f"warning: {line}")
    print(f"wrote {', '.join(str(p) for p in written)}")
    return 0


def add_kind_parser(sub: Any, kind: str, help_text: str) -> argparse.ArgumentParser:
    """The sub-parser of one kind, with the options every kind shares."""
    p: argparse.ArgumentParser = sub.add_parser(kind, help=help_text)
    p.add_argument("images", nargs="+", metavar="IMAGES",
                   help="raw mosaics (PNG/TIFF, full size) in order, or folders of them")  # fmt: skip
    p.add_argument("--camera", required=True,
                   help="base camera: a shipped model name or a .toml path")  # fmt: skip
    p.add_argument("--out", required=True, help="the new camera file (.toml) to write")
    p.add_argument("--maps-dir", default=None,
                   help="folder of the per-pixel maps (.npy) (None: beside --out)")  # fmt: skip
    p.add_argument("--name", default=None, help="model name (None: the --out file's stem)")
    p.set_defaults(handler=cmd_calibrate, kind=kind)
    return p


def add_calibrate(sub: Any) -> None:
    """Register ``polins calibrate`` and its kinds."""
    parser = sub.add_parser(
        "calibrate", help="camera file from calibration images (dark, flat, polarizer, ...)",
        description="Fit one calibration step to raw images and write a new camera file "
        "(docs/calibrate.md). Run the steps in order: dark, noise, flat or polarizer or "
        "sky-rotation, intrinsics, then camera-imu on a log recorded with turns; each --out "
        "becomes the next step's --camera.",
    )  # fmt: skip
    kinds = parser.add_subparsers(dest="kind", metavar="KIND", required=True,
                                  parser_class=type(parser))  # fmt: skip
    add_kind_parser(kinds, "dark", "dark offsets and read noise from >= 2 capped-lens frames")
    add_kind_parser(kinds, "noise", "read noise and conversion gain from flat-frame pairs "
                    "(consecutive images form a pair; >= 3 levels)")  # fmt: skip
    p = add_kind_parser(kinds, "flat", "channel gains from frames of unpolarized uniform light")
    p.add_argument("--gain-map", action="store_true",
                   help="also store the per-pixel gain map (vignetting included)")  # fmt: skip
    p = add_kind_parser(kinds, "polarizer",
                        "gains, angles, efficiencies from a turning linear polarizer (>= 6)")  # fmt: skip
    p.add_argument("--angles-deg", default=None, metavar="A1,A2,...",
                   help="polarizer angle of each image in the image plane [deg] (+u towards "
                   "+v); None: fitted (the source must then be stable); a negative first angle needs "
                   "--angles-deg=-15,0,...")  # fmt: skip
    p.add_argument("--polarizer-dop", type=finite, default=1.0,
                   help="degree of polarization behind the polarizer, (r - 1)/(r + 1) for an "
                   "extinction ratio r")  # fmt: skip
    p.add_argument("--pixel-maps", action="store_true",
                   help="also store per-pixel gain, angle and efficiency maps (Powell & Gruev)")  # fmt: skip
    p = add_kind_parser(kinds, "sky-rotation",
                        "gains, angles, efficiencies from a clear sky seen while turning")  # fmt: skip
    p.add_argument("--aligned-axis", action="store_true",
                   help="the turn axis is the optical axis: no tilt terms (fewer images)")  # fmt: skip
    p.add_argument("--no-ifov-correction", action="store_true",
                   help="do not interpolate the channels to the superpixel centres (only for "
                   "images free of the DoFP field-of-view mismatch, e.g. simulated without it)")  # fmt: skip
    p.add_argument("--times-utc", default=None, metavar="FILE",
                   help="text file of the images' timezone-aware ISO times, one a line in the "
                   "images' order: with --lat/--lon the sun's motion comes from the ephemeris")  # fmt: skip
    p.add_argument("--lat", type=finite, default=None, help="site latitude [deg]")
    p.add_argument("--lon", type=finite, default=None, help="site longitude [deg]")
    p.add_argument("--alt", type=finite, default=0.0, help="site height [m]")
    p.add_argument("--turns-deg", default=None, metavar="A1,A2,...",
                   help="the camera's turn about its optical axis at each image [deg] (a "
                   "turntable's angles; +u towards +v: counter-clockwise seen from above for a "
                   "camera looking up); None: fitted")  # fmt: skip
    p.add_argument("--rings", type=int, default=12, help="ring windows about the axis")
    p.add_argument("--min-span-deg", type=finite, default=90.0,
                   help="refuse turns spanning less [deg] (modulo 180)")  # fmt: skip
    p = add_kind_parser(kinds, "intrinsics", "camera matrix and distortion from checkerboards")
    p.add_argument("--board", required=True, metavar="COLSxROWS",
                   help="inner corners of the checkerboard, e.g. 9x6")  # fmt: skip
    p.add_argument("--square-mm", type=finite, required=True, help="side of a square [mm]")
    p = kinds.add_parser(
        "camera-imu", help="time offset and mat_bc from a polins log with turns",
        description="Camera time offset and camera-to-body rotation from a log recorded "
        "while turning (docs/calibrate.md#camera-imu). Clock mode (the ephemeris sun at the "
        "log's epoch and site) with the log's truth attitude; no-clock mode (one unknown, "
        "slowly drifting sun) with the integrated gyro, which needs no absolute attitude. "
        "Without tilts during the turns the no-clock mode cannot see the boresight about "
        "the turn axis and keeps the base camera's (it says so).",
    )  # fmt: skip
    p.add_argument("log", metavar="LOG", help="log folder (or its manifest.toml)")
    p.add_argument("--camera", required=True,
                   help="base camera: a shipped model name or a .toml path, at the images' size")  # fmt: skip
    p.add_argument("--out", required=True, help="the new camera file (.toml) to write")
    p.add_argument("--attitude", choices=("auto", "truth", "gyro"), default="auto",
                   help="attitude: the log's truth table (absolute), or the integrated gyro "
                   "(relative); auto: the truth when the log has one")  # fmt: skip
    p.add_argument("--no-clock", action="store_true",
                   help="do not use the ephemeris (the log's epoch is not UTC, or unknown)")  # fmt: skip
    p.add_argument("--max-offset-s", type=finite, default=0.2,
                   help="largest time offset searched [s]")  # fmt: skip
    p.add_argument("--maps-dir", default=None,
                   help="folder of the base camera's per-pixel maps (None: beside --out)")  # fmt: skip
    p.add_argument("--name", default=None, help="model name (None: the --out file's stem)")
    p.set_defaults(handler=cmd_camera_imu, kind="camera-imu")
    p = kinds.add_parser("check", help="score a camera file on images (writes nothing)")
    p.add_argument("camera_file", metavar="CAMERA", help="camera file (.toml) or shipped name")
    p.add_argument("images", nargs="+", metavar="IMAGES",
                   help="raw mosaics (PNG/TIFF, full size), or folders of them")  # fmt: skip
    p.add_argument("--unpolarized", action="store_true",
                   help="the images show unpolarized light: report the residual polarization")  # fmt: skip
    p.add_argument("--turns-deg", default=None, metavar="A1,A2,...",
                   help="a turntable sequence: the camera's turn at each image [deg]; prints "
                   "the relative-heading RMSE and RMS(err/sigma), an offset and a drift "
                   "(the sun's motion) taken out")  # fmt: skip
    p.add_argument("--method", choices=("compensated", "traditional"), default="compensated",
                   help="with --turns-deg: the measurement method")  # fmt: skip
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(handler=cmd_check)
