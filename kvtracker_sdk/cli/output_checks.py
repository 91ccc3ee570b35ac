"""Every output location of a command is checked before its first frame, not after the run.

A run can take hours; learning at its end that ``--save-map`` named a missing folder, or that
``--out`` is read-only, loses all of it. ``check_output_folder`` and ``check_output_file`` raise
an ``OutputError`` (exit code 10) naming the option, the path and what is wrong.

Writability is tested by creating (and removing) an empty hidden file in the folder: permission
bits alone do not say it (root ignores them, a read-only mount or a full quota does not show in
them), and ``os.access`` answers for the real, not the effective, user.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from kvtracker_sdk.errors import OutputError

__all__ = [
    "check_output_file",
    "check_output_folder",
    "forget_created_folders",
    "remove_created_folders_if_empty",
]

_PROBE_PREFIX = ".kvtracker-write-check-"

# Folders the checks created in this command (outermost first): a command that fails before
# writing into them removes them again, so an early failure (bad --weights, a camera that does
# not open) leaves no empty --out behind. One CLI command per process; reset per command.
_created: list[Path] = []


def forget_created_folders() -> None:
    """Start a command: no folder created yet."""
    _created.clear()


def remove_created_folders_if_empty() -> None:
    """Remove the folders the checks created, innermost first, where nothing was written."""
    for folder in reversed(_created):
        try:
            folder.rmdir()  # only an empty folder: anything written in it stays
        except OSError:
            break  # not empty (or gone): its parents are not empty either
    _created.clear()


def check_output_folder(folder: Path, option: str) -> None:
    """``folder`` (e.g. ``--out``) exists or is created, and files can be created in it."""
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{option} {folder}: exists and is not a folder")
    missing = [p for p in (folder, *folder.parents) if not p.exists()]
    try:
        folder.mkdir(parents=True, exist_ok=True)
        _created.extend(reversed(missing))  # outermost first
    except OSError as exc:
        raise OutputError(f"{option} {folder}: cannot create the folder ({_reason(exc)})") from exc
    _probe(folder, option, folder)


def check_output_file(path: Path, option: str) -> None:
    """``path`` (e.g. ``--save-map``) can be written: it is not a folder, and its folder exists
    and accepts new files (files are written atomically, through a temporary file beside it)."""
    if path.is_dir():
        raise OutputError(f"{option} {path}: is a folder; give a file name")
    parent = path.parent
    if not parent.exists():
        raise OutputError(f"{option} {path}: the folder {parent} does not exist (create it first)")
    if not parent.is_dir():
        raise OutputError(f"{option} {path}: {parent} is not a folder")
    _probe(parent, option, path)


def _probe(folder: Path, option: str, target: Path) -> None:
    try:
        fd, probe = tempfile.mkstemp(prefix=_PROBE_PREFIX, dir=folder)
    except OSError as exc:
        raise OutputError(
            f"{option} {target}: cannot create files in {folder} ({_reason(exc)})"
        ) from exc
    os.close(fd)
    Path(probe).unlink(missing_ok=True)


def _reason(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__
