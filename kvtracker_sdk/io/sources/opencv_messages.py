"""OpenCV's own messages, moved from the terminal into the SDK's log.

OpenCV's C++ code writes warnings such as ``[ WARN:0@0.012] global cap_v4l.cpp:914 open
VIDEOIO(V4L2:/dev/video3): can't open camera by index`` straight to file descriptor 2. Python's
logging never sees them, and in a terminal they tear through the CLI's own output. There is no
Python hook for that output (``cv2.utils.logging`` only sets the level), so while a capture is
being opened, descriptor 2 is pointed at a temporary file and what OpenCV wrote is logged
afterwards as ``opencv_message`` events (INFO: the CLI shows them with -v). Only the open is wrapped: it is short and
happens before tracking starts, so no other thread's output is expected on stderr meanwhile.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator

from kvtracker_sdk.log import get_logger

__all__ = ["opencv_messages_logged"]

_log = get_logger(__name__)
_STDERR_FD = 2


@contextlib.contextmanager
def opencv_messages_logged(target: str) -> Iterator[list[str]]:
    """Run the block with descriptor 2 captured; yields the list that receives OpenCV's lines
    (filled when the block ends, each also logged with ``target``)."""
    lines: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(_STDERR_FD)
    except (OSError, ValueError):  # no descriptor 2 (embedded interpreters): leave it alone
        yield lines
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), _STDERR_FD)
        try:
            yield lines
        finally:
            os.dup2(saved, _STDERR_FD)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode("utf-8", errors="replace")
            lines.extend(line.strip() for line in text.splitlines() if line.strip())
            for line in lines:
                _log.info("opencv_message", target=target, opencv=line)
