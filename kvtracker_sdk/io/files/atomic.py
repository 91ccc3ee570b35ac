"""Atomic file writes: a saved file is either the old one or the complete new one, never half.

Every writer in ``io/`` goes through :func:`atomic_write`: the data goes to a temporary file in
the target's directory (so ``os.replace`` stays on one filesystem and is atomic), is flushed and
fsync'ed, and only then replaces the target. A crash or an exception mid-write leaves the
previous file untouched and removes the temporary one.

A process killed mid-write cannot remove its temporary file. The next successful write of the
same target removes such leftovers once they are older than ``STALE_TEMP_SECONDS`` (an hour): a
concurrent writer's temporary file is being written, so it is always younger than that.

Replacing a large file makes the kernel free the old one's blocks and cached pages inside the
``os.replace`` (tens of milliseconds per hundred megabytes). The writers hold a descriptor of the
old file across the rename and, for a large one, close it on a short-lived background thread, so that the freeing
happens there, after the new file is in place: the rename itself is unchanged (POSIX only).

Temporary names add 18 bytes to the target's name; for a name that would then exceed the
filesystem's limit (255 bytes on most), a digest of the name stands in for it.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import secrets
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["FREE_IN_BACKGROUND_BYTES", "STALE_TEMP_SECONDS", "atomic_path", "atomic_write"]

STALE_TEMP_SECONDS = 3600.0
FREE_IN_BACKGROUND_BYTES = 16 << 20  # a replaced file at least this large is freed on a thread
_TOKEN_BYTES = 6  # the temporary name's random part: 12 hex digits
_ADDED_BYTES = 2 * _TOKEN_BYTES + 6  # ".", ".", the hex digits and ".tmp"


def _temporary_stem(target: Path) -> str:
    """What the temporary names of ``target`` start with: the target's own name, or — when that
    would not fit the filesystem's name limit with the 18 added bytes — a digest of it (still
    one per target, so stale leftovers of ``target`` and only of it are recognised)."""
    name = target.name
    if len(os.fsencode(name)) + _ADDED_BYTES <= _name_max(target.parent):
        return name
    return f"kvtmp-{hashlib.sha256(os.fsencode(name)).hexdigest()[:32]}"


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):  # no pathconf (Windows) or no such folder
        return 255


def _temporary_path(target: Path) -> Path:
    return target.with_name(f".{_temporary_stem(target)}.{secrets.token_hex(_TOKEN_BYTES)}.tmp")


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], *, binary: bool = False) -> Iterator[IO[Any]]:
    """Yield a file handle whose content replaces ``path`` when the ``with`` block succeeds.

    Text mode writes UTF-8 with ``\\n`` line endings; ``binary=True`` yields a bytes handle.
    The parent directory must exist.
    """
    target = Path(path)
    tmp = _temporary_path(target)
    # os.open with 0o666 lets the umask decide the final permissions, as for a plain open();
    # tempfile.mkstemp would leave the saved file readable by its owner only.
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        handle = (
            os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="\n")
        )
        with handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        _replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_directory(target.parent)
    _remove_stale_temporaries(target)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for writers that take a file name, not a handle
    (safetensors' ``save_file`` writes straight from tensor memory, without a bytes copy).

    When the block succeeds the file is fsync'ed and replaces ``path``; on any exception it is
    removed. The temporary name is hidden and ends in ``.tmp``, never in the target's suffix.
    """
    target = Path(path)
    tmp = _temporary_path(target)
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))  # reserve; umask applies
    mode = tmp.stat().st_mode & 0o777
    try:
        yield tmp
        # the writer may have replaced the file by renaming its own (safetensors does, with mode
        # 0600): restore the umask's permissions and fsync what is now at the temporary path
        os.chmod(tmp, mode)
        fd = os.open(tmp, os.O_RDWR)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        _replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_directory(target.parent)
    _remove_stale_temporaries(target)


def _replace(tmp: Path, target: Path) -> None:
    """``os.replace(tmp, target)``, leaving the freeing of the file ``target`` named before to a
    background thread (see the module docstring)."""
    previous = None
    if os.name == "posix":
        # O_NOFOLLOW: a symbolic link is replaced, not the file it names; O_NONBLOCK: a FIFO
        # there must not block this open
        flags = os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
        with contextlib.suppress(OSError):  # none there, or unreadable: freed in the replace
            previous = os.open(target, flags)
    try:
        os.replace(tmp, target)
    finally:
        if previous is not None:
            try:
                large = os.fstat(previous).st_size >= FREE_IN_BACKGROUND_BYTES
            except OSError:
                large = False
            if large:
                threading.Thread(
                    target=os.close, args=(previous,), name="kvtracker-free-old"
                ).start()
            else:  # freeing a small file costs less than a thread
                os.close(previous)


def _remove_stale_temporaries(target: Path) -> None:
    """Remove temporary files of ``target`` left by killed writers (see the module docstring)."""
    stem = re.escape(_temporary_stem(target))
    pattern = re.compile(rf"\.{stem}\.[0-9a-f]{{{2 * _TOKEN_BYTES}}}\.tmp")
    cutoff = time.time() - STALE_TEMP_SECONDS
    with contextlib.suppress(OSError):  # best effort: the save itself has succeeded
        for entry in os.scandir(target.parent):
            if pattern.fullmatch(entry.name) and entry.stat().st_mtime < cutoff:
                with contextlib.suppress(OSError):
                    os.unlink(entry.path)


def _fsync_directory(directory: Path) -> None:
    """Make a completed ``os.replace`` durable: POSIX records a rename with the directory."""
    if os.name != "posix":
        return
    try:
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:  # some filesystems refuse directory fsync; the replace itself has happened
        pass
