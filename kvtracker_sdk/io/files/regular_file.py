"""Whole-file reads of paths a user names, for files with no structure to bound (images, masks,
depth images, ``--config``, the tune cache): :mod:`kvtracker_sdk.user_files`' reader (regular
files only, FIFOs and devices refused at once, symlinks followed) with a cap far above any such
file, so that ``/dev/zero`` behind a file name, or a file that keeps growing, cannot exhaust
memory."""

from __future__ import annotations

import os

from kvtracker_sdk.errors import KVTrackerError
from kvtracker_sdk.user_files import read_user_bytes, read_user_text

__all__ = ["MAX_REGULAR_FILE_BYTES", "read_regular_bytes", "read_regular_text"]

MAX_REGULAR_FILE_BYTES = 1 << 30  # a frame, mask or depth image is megabytes; 1 GiB is far beyond


def read_regular_bytes(
    path: str | os.PathLike[str], error: type[KVTrackerError], *, what: str = "file"
) -> bytes:
    """The bytes of ``path``; ``error(...)`` (a typed error of the caller's choosing) when it
    cannot be opened or read, is not a regular file, or is over ``MAX_REGULAR_FILE_BYTES``.
    ``what`` names it in the message."""
    return read_user_bytes(path, error, what=what, max_bytes=MAX_REGULAR_FILE_BYTES)


def read_regular_text(
    path: str | os.PathLike[str], error: type[KVTrackerError], *, what: str = "file"
) -> str:
    """``read_regular_bytes`` decoded as UTF-8 (a leading BOM is dropped)."""
    return read_user_text(path, error, what=what, max_bytes=MAX_REGULAR_FILE_BYTES)
