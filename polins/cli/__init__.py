"""Command line: ``polins sun | demo | simulate | heading | fuse | imu-model | calibrate | tune | manifest``.

The fault policy of docs/faults.md: a user mistake (a bad argument, file, unit, manifest or
naive time: :class:`polins.errors.UserInputError`, or a file that cannot be opened) prints
one readable line and exits with status 2, before any work where the check is cheap; a run
that produced nothing usable exits with status 1 after writing its outputs whole; any other
exception is a bug in polins and keeps its traceback (exit status 1). ``--debug`` shows the
traceback of user mistakes too. Ctrl-C (or SIGTERM) prints one line and exits with status
130 (143), leaving the previous output set; a closed pipe (``| head``) ends quietly (141).
Output folders are written whole (:mod:`polins.io.outputs`, docs/outputs.md).

One module per command group, each with ``add_<command>(sub)`` that registers its
sub-parser and handler: :mod:`~polins.cli.sun` (sun, heading),
:mod:`~polins.cli.simulate` (demo, simulate), :mod:`~polins.cli.fuse`,
:mod:`~polins.cli.models` (imu-model), :mod:`~polins.cli.calibrate`, :mod:`~polins.cli.tune`,
:mod:`~polins.cli.bag` (manifest); the shared argument
checks are in :mod:`~polins.cli.common`. A new command gets its own module and one line in
:func:`build_parser`.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from polins.cli import bag, calibrate, fuse, models, simulate, sun, tune
from polins.cli.common import USER_ERRORS, ArgumentError, Handler, Parser
from polins.cli.fuse import filter_options_text
from polins.cli.sun import sun_report
from polins.io.outputs import Terminated, signals_unwind

__all__ = ["USER_ERRORS", "ArgumentError", "Terminated", "build_parser", "filter_options_text",
           "main", "sun_report"]  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    """The ``polins`` argument parser with all subcommands (in the order of ``--help``)."""
    parser = Parser(
        prog="polins",
        description="Bio-inspired polarization navigation: sky images -> heading -> INS fusion.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                parser_class=Parser)  # fmt: skip
    sun.add_sun(sub)
    simulate.add_demo(sub)
    simulate.add_simulate(sub)
    sun.add_heading(sub)
    fuse.add_fuse(sub)
    models.add_imu_model(sub)
    calibrate.add_calibrate(sub)
    tune.add_tune(sub)
    bag.add_manifest(sub)
    return parser


def _quiet_stdout() -> None:
    """After a closed pipe: point stdout at /dev/null so that the exit flush stays silent."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``polins`` console script (exit status: docs/faults.md)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --list-options (0) or a one-line argparse error (2)
        return exc.code if isinstance(exc.code, int) else 2
    handler: Handler = args.handler
    name = f"polins {args.command}"
    if args.command == "calibrate":
        name += f" {args.kind}"
    try:
        with signals_unwind():
            return handler(args)
    except USER_ERRORS as exc:
        if args.debug:
            raise
        message = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
        print(f"{name}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{name}: interrupted; outputs unchanged", file=sys.stderr)
        return 130
    except Terminated:
        print(f"{name}: terminated; outputs unchanged", file=sys.stderr)
        return 143
    except BrokenPipeError:  # stdout closed early (| head): not an error of the run
        _quiet_stdout()
        return 141
