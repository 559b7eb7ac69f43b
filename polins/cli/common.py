"""Shared pieces of the command line: one-line argument errors, argument types and checks, the parser class.

Every command module (:mod:`polins.cli.sun`, ``simulate``, ``fuse``, ``models``,
``calibrate``) takes its argument checks from here, so that a bad value reads the same in
every command: ``polins CMD: error: --option VALUE: expected ...`` with exit status 2
(docs/faults.md).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

from polins.compass.measurement import METHODS, check_method
from polins.errors import UserInputError

__all__ = [
    "USER_ERRORS",
    "ArgumentError",
    "Handler",
    "HelpFormatter",
    "Parser",
    "add_method_arg",
    "add_site_args",
    "angle",
    "check",
    "finite",
    "fraction",
    "method",
]

Handler = Callable[[argparse.Namespace], int]


class ArgumentError(UserInputError):
    """A command-line argument with an impossible value (named in the message)."""


# Exceptions that report a user mistake; anything else is a bug and keeps its traceback.
USER_ERRORS = (UserInputError, FileNotFoundError, IsADirectoryError, NotADirectoryError,
               PermissionError)  # fmt: skip


def check(ok: bool, message: str) -> None:
    """Raise :class:`ArgumentError` with ``message`` unless ``ok``."""
    if not ok:
        raise ArgumentError(message)


def finite(text: str) -> float:
    """argparse type: a finite number (``inf`` and ``nan`` are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number")
    return value


def fraction(text: str) -> float:
    """argparse type: ``50%`` or ``0.5``, a share in [0, 1]."""
    percent = text.strip().endswith("%")
    try:
        value = float(text.strip().rstrip("%")) / (100.0 if percent else 1.0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a share like 50% or 0.5") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a share in 0%..100%")
    return value


def angle(option: str, value: float, lo: float, hi: float) -> None:
    """Check an angle argument [deg] is in ``[lo, hi]`` (finite by its argparse type)."""
    check(lo <= value <= hi, f"{option} {value:g}: expected an angle in [{lo:g}, {hi:g}] deg")


def add_site_args(p: argparse.ArgumentParser, required: bool = True) -> None:
    """``--time``, ``--lat``, ``--lon``, ``--alt``: one time and place (optional all
    together with ``required=False``)."""
    p.add_argument(
        "--time", required=required, help="timezone-aware ISO time, e.g. 2023-09-05T15:06+08:00"
    )
    p.add_argument("--lat", type=finite, required=required, help="latitude [deg, North positive]")
    p.add_argument("--lon", type=finite, required=required, help="longitude [deg, East positive]")
    p.add_argument("--alt", type=finite, default=0.0, help="height above the ellipsoid [m]")


def method(text: str) -> str:
    """argparse type: a method of ``polins.measure``, with the one line of
    :func:`polins.compass.measurement.check_method` (it names where ``"paper"`` lives)."""
    try:
        check_method(text)
    except UserInputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def add_method_arg(p: argparse.ArgumentParser) -> None:
    """``--method``: the heading estimator of ``polins.measure``."""
    p.add_argument("--method", type=method, default=METHODS[0],
                   metavar="{" + ",".join(METHODS) + "}", help="heading estimator")  # fmt: skip


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (docs/faults.md) and whose help shows
    every default."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> Any:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """``--help`` with each option's default and the epilog's line breaks kept.

    No "(default: ...)" for a required argument, a flag, an option whose default is None (its
    help says what happens without it) or a help text that already names its default.
    """

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if (
            action.required
            or action.default in (None, False)
            or not action.option_strings
            or "default" in text
        ):
            return action.help
        return super()._get_help_string(action)
