"""Strict TOML validation of the model files: value checks, optional keys, arrays of tables, did-you-mean hints.

A schema maps each key to a validator (a function that returns the converted value or
raises ``TypeError`` / ``ValueError``), to a nested schema (a table ``[name]``), to
:class:`Optional` (a key or table that may be absent) or to :class:`TableArray` (an array of
tables ``[[name]]``). :func:`validate` rejects unknown keys, naming the closest allowed key
("did you mean ..., note the unit in the name"), and missing keys, with the file's path in
every message. :func:`read_model` resolves a shipped model's name or a path and validates
its text.
"""

from __future__ import annotations

import difflib
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from polins.errors import UserInputError

FloatArray = NDArray[np.float64]

__all__ = [
    "ModelFileError",
    "Optional",
    "Schema",
    "TableArray",
    "boolean",
    "choice",
    "integer",
    "matrix",
    "nonneg",
    "number",
    "polygons",
    "positive",
    "read_model",
    "shipped_folder",
    "shipped_models",
    "string",
    "table_entry",
    "validate",
    "vector",
]


class ModelFileError(UserInputError):
    """A model file is missing a key, has an unknown key, or a bad value."""


# ----------------------------------------------------------------------------- values
def number(v: Any) -> float:
    """A number (int or float, not a bool)."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise TypeError("expected a number")
    return float(v)


def positive(v: Any) -> float:
    """A number > 0."""
    x = number(v)
    if not x > 0:
        raise ValueError("expected a positive number")
    return x


def nonneg(v: Any) -> float:
    """A number >= 0."""
    x = number(v)
    if not x >= 0:
        raise ValueError("expected a number >= 0")
    return x


def integer(v: Any) -> int:
    """A positive integer."""
    if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
        raise TypeError("expected a positive integer")
    return int(v)


def string(v: Any) -> str:
    """A string."""
    if not isinstance(v, str):
        raise TypeError("expected a string")
    return v


def boolean(v: Any) -> bool:
    """``true`` or ``false``."""
    if not isinstance(v, bool):
        raise TypeError("expected true or false")
    return v


def vector(n: int) -> Callable[[Any], FloatArray]:
    """A list of ``n`` numbers, as a float array ``(n,)``."""

    def check(v: Any) -> FloatArray:
        arr = np.asarray([number(x) for x in v], dtype=float) if isinstance(v, list) else None
        if arr is None or arr.shape != (n,):
            raise TypeError(f"expected a list of {n} numbers")
        return arr

    return check


def matrix(rows: int, cols: int) -> Callable[[Any], FloatArray]:
    """A ``rows`` x ``cols`` nested list of numbers, as a float array."""

    def check(v: Any) -> FloatArray:
        if not isinstance(v, list) or len(v) != rows:
            raise TypeError(f"expected a {rows}x{cols} nested list")
        return np.stack([vector(cols)(row) for row in v])

    return check


def choice(*options: str) -> Callable[[Any], str]:
    """One of the strings ``options``."""

    def check(v: Any) -> str:
        if v not in options:
            raise ValueError(f"expected one of {', '.join(repr(o) for o in options)}")
        return str(v)

    return check


def polygons(v: Any) -> tuple[FloatArray, ...]:
    """A list of polygons ``[[u, v], ...]`` of at least 3 vertices each."""
    if not isinstance(v, list):
        raise TypeError("expected a list of polygons [[u, v], ...]")
    polys = []
    for poly in v:
        if not isinstance(poly, list) or len(poly) < 3:
            raise TypeError("each polygon needs at least 3 [u, v] vertices")
        polys.append(matrix(len(poly), 2)(poly))
    return tuple(polys)


# ----------------------------------------------------------------------------- structure
@dataclass(frozen=True)
class Optional:
    """A key (``rule`` a validator) or a table (``rule`` a schema) that may be absent."""

    rule: Any


@dataclass(frozen=True)
class TableArray:
    """An optional array of tables ``[[name]]``, each validated by ``schema``.

    ``extra``: a validator for keys that ``schema`` does not name (``None``: such keys are
    unknown keys); ``extra_what`` says in messages what such keys must be.
    """

    schema: Mapping[str, Any]
    extra: Callable[[Any], Any] | None = None
    extra_what: str = ""


Schema = Mapping[str, Any]  # key -> validator | nested Schema | Optional | TableArray


def _unknown(key: str, allowed: list[str], path: Path, prefix: str) -> ModelFileError:
    guess = difflib.get_close_matches(key, allowed, n=1, cutoff=0.5)
    hint = f"; did you mean '{prefix}{guess[0]}' (note the unit in the name)?" if guess else ""
    return ModelFileError(
        f"{path}: unknown key '{prefix}{key}'{hint} (allowed: {', '.join(sorted(allowed))})"
    )


def _value(value: Any, rule: Any, path: Path, name: str) -> Any:
    if isinstance(rule, Mapping):
        if not isinstance(value, dict):
            raise ModelFileError(f"{path}: '{name}' must be a table [{name}]")
        return validate(value, rule, path, f"{name}.")
    if isinstance(rule, TableArray):
        if not isinstance(value, list) or not all(isinstance(t, dict) for t in value):
            raise ModelFileError(f"{path}: '{name}' must be an array of tables [[{name}]]")
        return [table_entry(t, rule, path, f"{name}[{i}].") for i, t in enumerate(value)]
    try:
        return rule(value)
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"{path}: key '{name}' = {value!r}: {exc}") from None


def table_entry(data: Mapping[str, Any], rule: TableArray, path: Path, prefix: str = "") -> dict:
    """One table of an array of tables ``rule``, checked: its schema's keys, and the other
    keys by ``rule.extra``. Raises :class:`ModelFileError` naming ``path`` and the key."""
    named = {k: v for k, v in data.items() if k in rule.schema}
    out = validate(named, rule.schema, path, prefix)
    for key, value in data.items():
        if key in rule.schema:
            continue
        if rule.extra is None:
            raise _unknown(key, list(rule.schema), path, prefix)
        try:
            out[key] = rule.extra(value)
        except (TypeError, ValueError) as exc:
            raise ModelFileError(
                f"{path}: key '{prefix}{key}' = {value!r}: {exc} ({rule.extra_what})"
            ) from None
    return out


def validate(data: Mapping[str, Any], schema: Schema, path: Path, prefix: str = "") -> dict:
    """Check ``data`` (parsed TOML) against ``schema`` and return the converted values.

    Absent optional keys are left out of the result. Raises :class:`ModelFileError` naming
    ``path`` and the key (with ``prefix``, the dotted table path) for an unknown key (with
    the closest allowed key), a missing key or a bad value.
    """
    out: dict[str, Any] = {}
    for key in data:
        if key not in schema:
            raise _unknown(key, list(schema), path, prefix)
    for key, rule in schema.items():
        optional = isinstance(rule, Optional | TableArray)
        if key not in data:
            if optional:
                continue
            raise ModelFileError(f"{path}: missing key '{prefix}{key}'")
        out[key] = _value(data[key], rule.rule if isinstance(rule, Optional) else rule, path,
                          f"{prefix}{key}")  # fmt: skip
    return out


# ----------------------------------------------------------------------------- files
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


def read_model(name_or_path: str | Path, kind: str, schema: Schema) -> tuple[Path, dict]:
    """Resolve a shipped ``kind`` model's name or a path, parse the TOML and validate it.

    Returns the file's path and the converted values. Raises ``FileNotFoundError`` or
    :class:`ModelFileError`.
    """
    path = _resolve(name_or_path, kind)
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ModelFileError(f"{path}: not valid TOML: {exc}") from None
    return path, validate(data, schema, path)
