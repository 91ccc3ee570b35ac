"""``read_exactly``: fill a buffer from a file offset with ``pread``, through one descriptor.

Shared by the readers that must never memory-map what they read (checkpoints:
``models/weights_file.py``; maps: ``io/map_file/map_reader.py``), because a memory-mapped page of a file
truncated underneath raises SIGBUS. Each caller turns a short read into its own typed error.
"""

from __future__ import annotations

import os

__all__ = ["read_exactly"]


def read_exactly(fd: int, buffer: memoryview, offset: int) -> int:
    """Read ``len(buffer)`` bytes of ``fd`` from byte ``offset`` into ``buffer``.

    Returns the number of bytes read: ``len(buffer)``, or fewer only where the file ended first.
    ``OSError`` propagates (the caller names the file in its own error).
    """
    done = 0
    while done < len(buffer):
        count = os.preadv(fd, [buffer[done:]], offset + done)
        if count == 0:
            break
        done += count
    return done
