"""``start_writeback``: ask the kernel to start writing a file's dirty pages to the disk now.

A large file written and then ``fsync``'ed waits for the whole disk write at the end, after
every CPU step of the save (snapshot, hashing, copying into the page cache). Linux's
``sync_file_range(SYNC_FILE_RANGE_WRITE)`` starts the write-out of a range without waiting for
it, so the disk works while the CPU does the rest and the final ``fsync`` only waits for the
tail. It is not a durability guarantee (the ``fsync`` still gives that) and Python's ``os`` has
no binding for it, hence ``ctypes``; elsewhere (other systems, no glibc) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from typing import Any

__all__ = ["start_writeback"]

_SYNC_FILE_RANGE_WRITE = 2  # <fcntl.h>


def _sync_file_range() -> Any:
    if not sys.platform.startswith("linux"):
        return None
    try:
        function = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True).sync_file_range
    except (OSError, AttributeError):
        return None
    function.argtypes = (ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint)
    function.restype = ctypes.c_int
    return function


_FUNCTION = _sync_file_range()


def start_writeback(fd: int, offset: int, length: int) -> None:
    """Start writing ``length`` bytes of ``fd`` from ``offset`` to the disk, without waiting (a
    hint: failures are ignored, the caller's ``fsync`` is what makes the data durable)."""
    if _FUNCTION is not None:
        _FUNCTION(fd, offset, length, _SYNC_FILE_RANGE_WRITE)
