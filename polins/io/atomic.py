"""Atomic file output: write to a temporary file in the target folder, then ``os.replace``.

An interrupted run (exception, Ctrl-C, killed process) therefore never leaves a truncated
file under the final name: either the previous file or the complete new one is there. The
temporary file is hidden (``.<name>.<random>.tmp<suffix>``) and removed on errors; it keeps
the final suffix because some writers (OpenCV) choose the format from it.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Context manager yielding a temporary path that replaces ``path`` on success.

    Parameters
    ----------
    path : str or Path
        Final file name; its folder is created if needed.

    Yields
    ------
    Path
        A fresh temporary file in the same folder (same file system, so the final
        ``os.replace`` is atomic). Write the complete content to it inside the block.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = _create_temporary(final)
    try:
        yield tmp
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _create_temporary(final: Path) -> Path:
    """A new, empty hidden file next to ``final``, with the permissions the umask allows.

    Created with ``O_CREAT | O_EXCL`` and mode 0o666, so the OS applies the process umask
    (as for any new file) without reading or changing it.
    """
    for _ in range(100):
        name = f".{final.name}.{secrets.token_hex(4)}.tmp{final.suffix}"
        tmp = final.parent / name
        try:
            fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(f"no free temporary name next to {final}")


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write a text file atomically (UTF-8); returns the final path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


__all__ = ["atomic_path", "write_text_atomic"]
