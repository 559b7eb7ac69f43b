"""Whole output sets: a command's files are written into a temporary sibling folder and swapped in.

A run of ``polins fuse``, ``polins demo`` or ``polins simulate`` leaves either the previous
complete set of files or the new complete set in its output folder, never a mix
(docs/outputs.md): the files are written into a hidden sibling folder
``.<name>.polins-tmp-<random>``, a ``run.json`` stamp (version, command, settings,
``"status": "complete"``) is written last, and the folder is then renamed into place (the
previous set is first renamed aside to ``.<name>.polins-old-<random>`` and removed after the
swap). An interrupted or failed run removes its temporary folder; one killed outright leaves
it behind, and the next run into the same folder removes it (or, if the kill fell between
the two renames of the swap, restores the previous set).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import os
import secrets
import shutil
import signal
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from polins.errors import UserInputError

STAMP_NAME = "run.json"
TMP_TAG = ".polins-tmp-"
OLD_TAG = ".polins-old-"


class Terminated(BaseException):
    """SIGTERM received: unwinds like Ctrl-C, so that a temporary output set is removed."""


class OutputFolderError(UserInputError):
    """An output folder that cannot hold an output set (named in the message)."""


@dataclass
class OutputSet:
    """The state of one output set being written (yielded by :func:`output_set`).

    Attributes
    ----------
    path : Path
        The temporary folder to write every file into.
    final : Path
        Where the set appears when complete.
    stamp : dict
        Extra entries of ``run.json`` (settings, status, ...); fill it before the block ends.
    """

    path: Path
    final: Path
    stamp: dict[str, Any] = field(default_factory=dict)

    def files(self) -> list[str]:
        """Names of the files written so far (relative to the folder, sorted)."""
        return sorted(str(p.relative_to(self.path)) for p in self.path.rglob("*") if p.is_file())


def _json_default(v: Any) -> Any:
    item = getattr(v, "item", None)  # numpy scalars
    if callable(item):
        return item()
    tolist = getattr(v, "tolist", None)  # numpy arrays
    if callable(tolist):
        return tolist()
    return str(v)


def to_json(data: Any) -> str:
    """JSON text of a report or stamp (numpy values and paths converted), ending in a newline."""
    return json.dumps(data, indent=2, default=_json_default) + "\n"


def check_output_folder(out: str | Path, known: Iterable[str] = (), option: str = "--out") -> Path:
    """Check before any work that ``out`` can take an output set; returns it as a Path.

    ``out`` must not be a file; its nearest existing ancestor must be a writable folder; an
    existing ``out`` must be empty, hold a previous output set (``run.json``), or hold only
    files named in ``known`` (outputs of an earlier polins without a stamp): swapping in a new
    set replaces the whole folder, so a folder of other files is refused.

    Raises
    ------
    OutputFolderError
        One line naming the folder and the problem.
    """
    path = Path(out)
    if path.is_file():
        raise OutputFolderError(f"{option} {out}: is a file, expected a folder")
    if path.exists() and not path.is_dir():
        raise OutputFolderError(f"{option} {out}: exists and is not a folder")
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputFolderError(f"{option} {out}: cannot be created ({parent} is a file)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputFolderError(f"{option} {out}: cannot be created ({parent} is not writable)")
    if path.is_dir():
        names = {p.name for p in path.iterdir()}
        foreign = sorted(names - set(known) - {STAMP_NAME})
        if names and STAMP_NAME not in names and foreign:
            raise OutputFolderError(
                f"{option} {out}: the folder holds files polins did not write ({foreign[0]}, ...); "
                "the output set replaces the whole folder: give a new or empty folder"
            )
    return path


def clean_stale(final: str | Path) -> list[Path]:
    """Remove the temporary siblings of ``final`` left by killed runs; returns them.

    A previous set renamed aside (``.<name>.polins-old-*``) is moved back if ``final`` is
    missing (the kill fell inside the swap), else removed.
    """
    final = Path(final).absolute()
    if not final.parent.is_dir():
        return []
    removed = []
    for p in sorted(final.parent.glob(f".{final.name}{OLD_TAG}*")):
        if not final.exists():
            os.rename(p, final)
        else:
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    for p in sorted(final.parent.glob(f".{final.name}{TMP_TAG}*")):
        shutil.rmtree(p, ignore_errors=True)
        removed.append(p)
    return removed


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Ignore SIGINT/SIGTERM for the few system calls of the swap (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler)


def _on_signal(main_pid: int) -> Callable[[int, Any], None]:
    """A handler raising KeyboardInterrupt (SIGINT) or Terminated (SIGTERM) in the process
    that installed it; a forked worker inheriting it ignores the signal (its parent ends it)."""

    def handler(signum: int, frame: Any) -> None:
        if os.getpid() != main_pid:
            return
        raise KeyboardInterrupt if signum == signal.SIGINT else Terminated

    return handler


@contextlib.contextmanager
def signals_unwind() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` and SIGINT ``KeyboardInterrupt``
    (main thread only), so that the ``finally`` clauses run and :func:`output_set` removes
    its temporary folder; worker processes forked inside the block ignore both (their
    parent shuts them down), so Ctrl-C prints no traceback of theirs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handler = _on_signal(os.getpid())
    saved = {}
    for s in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(s) is not signal.SIG_IGN:  # e.g. a background job keeps SIGINT off
            saved[s] = signal.signal(s, handler)
    try:
        yield
    finally:
        for s, previous in saved.items():
            signal.signal(s, previous)


def _swap(tmp: Path, final: Path) -> None:
    """Rename ``tmp`` to ``final``, replacing a previous set there."""
    with _signals_deferred():
        if final.exists():
            old = final.parent / f".{final.name}{OLD_TAG}{secrets.token_hex(4)}"
            os.rename(final, old)
            os.rename(tmp, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, final)


@contextlib.contextmanager
def output_set(
    final: str | Path, *, command: str, known: Iterable[str] = ()
) -> Iterator[OutputSet]:
    """Write a whole output set: yields an :class:`OutputSet` whose ``path`` takes the files.

    When the block ends normally, ``run.json`` is written (``polins_version``, ``command``,
    ``created_utc``, ``files``, ``status: "complete"`` and the entries of ``stamp``) and the
    folder replaces ``final``. On any exception (including Ctrl-C) the temporary folder is
    removed, ``final`` is left as it was, and the exception propagates.
    """
    from polins import __version__

    final = check_output_folder(final, known).absolute()
    clean_stale(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.parent / f".{final.name}{TMP_TAG}{secrets.token_hex(4)}"
    tmp.mkdir()
    out = OutputSet(path=tmp, final=final)
    try:
        yield out
        stamp = {
            "polins_version": __version__,
            "command": command,
            "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            **out.stamp,
            "files": [*out.files(), STAMP_NAME],
            "status": "complete",
        }
        (tmp / STAMP_NAME).write_text(to_json(stamp), encoding="utf-8")
        _swap(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def read_stamp(folder: str | Path) -> Mapping[str, Any] | None:
    """The ``run.json`` of an output folder, or None if it has none."""
    path = Path(folder) / STAMP_NAME
    if not path.is_file():
        return None
    data: Mapping[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return data


__all__ = [
    "STAMP_NAME",
    "OutputFolderError",
    "OutputSet",
    "Terminated",
    "check_output_folder",
    "clean_stale",
    "output_set",
    "read_stamp",
    "signals_unwind",
    "to_json",
]
