"""Read a small input file only if it is a regular file: a FIFO, a device or a folder is refused.

``Path.read_text`` on a FIFO blocks until some other process writes to it (forever, for a FIFO
nobody feeds), and on ``/dev/zero`` it never ends. The file is opened once with ``O_NONBLOCK``
(which makes opening a FIFO return at once instead of waiting for a writer), the opened
descriptor is checked with ``fstat`` (so a file swapped in after a path check cannot slip
through), and only then read.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from kvtracker_sdk.errors import KVTrackerError

__all__ = ["read_regular_bytes", "read_regular_text"]

_NOT_REGULAR = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def read_regular_bytes(
    path: str | os.PathLike[str], error: type[KVTrackerError], *, what: str = "file"
) -> bytes:
    """The bytes of ``path``; ``error(...)`` (a typed error of the caller's choosing) when it
    cannot be opened or read, or is not a regular file. ``what`` names it in the message."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
        raise error(f"{what} {path}: cannot read it ({exc})") from exc
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):  # checked before fdopen, which raises on a folder
        os.close(fd)
        kind = next((name for test, name in _NOT_REGULAR if test(mode)), "not a regular file")
        raise error(f"{what} {path}: is {kind}, not a regular file")
    with os.fdopen(fd, "rb") as handle:
        try:
            return handle.read()
        except OSError as exc:
            raise error(f"{what} {path}: cannot read it ({exc})") from exc


def read_regular_text(
    path: str | os.PathLike[str], error: type[KVTrackerError], *, what: str = "file"
) -> str:
    """``read_regular_bytes`` decoded as UTF-8 (a leading BOM is dropped)."""
    data = read_regular_bytes(path, error, what=what)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"{what} {Path(path)}: not UTF-8 text ({exc})") from exc
