"""Atomic writes: the target is the old file or the complete new one, never a partial one."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from pathlib import Path

import pytest

from kvtracker_sdk.io.files import atomic
from kvtracker_sdk.io.files.atomic import STALE_TEMP_SECONDS, atomic_path, atomic_write


def test_text_and_binary_writes_replace_the_target(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"
    target.write_text("old")
    with atomic_write(target) as handle:
        handle.write("new\n")
        assert target.read_text() == "old"  # nothing visible before the block ends
    assert target.read_text() == "new\n"
    with atomic_write(tmp_path / "out.bin", binary=True) as handle:
        handle.write(b"\x00\x01")
    assert (tmp_path / "out.bin").read_bytes() == b"\x00\x01"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin", "out.txt"]


def test_an_error_mid_write_keeps_the_old_file_and_cleans_up(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="disk full"), atomic_write(target) as handle:
        handle.write("half of the new conte")
        raise RuntimeError("disk full")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]  # the temporary file is gone


def test_permissions_follow_the_umask_like_a_plain_open(tmp_path: Path) -> None:
    with atomic_write(tmp_path / "atomic.txt") as handle:
        handle.write("x")
    (tmp_path / "plain.txt").write_text("x")
    mode = os.stat(tmp_path / "atomic.txt").st_mode & 0o777
    assert mode == os.stat(tmp_path / "plain.txt").st_mode & 0o777


@pytest.mark.parametrize("writer", ["handle", "path"])
def test_leftovers_of_killed_writers_are_removed_once_stale(tmp_path: Path, writer: str) -> None:
    target = tmp_path / "room.kvmap"
    stale = tmp_path / ".room.kvmap.0123456789ab.tmp"  # a writer killed two hours ago
    fresh = tmp_path / ".room.kvmap.ba9876543210.tmp"  # a concurrent writer, still writing
    other = tmp_path / ".other.kvmap.0123456789ab.tmp"  # another target's: not ours to remove
    for leftover in (stale, fresh, other):
        leftover.write_bytes(b"partial")
    two_hours_ago = time.time() - 2 * STALE_TEMP_SECONDS
    for old in (stale, other):
        os.utime(old, (two_hours_ago, two_hours_ago))
    if writer == "handle":
        with atomic_write(target, binary=True) as handle:
            handle.write(b"map")
    else:
        with atomic_path(target) as path:
            path.write_bytes(b"map")
    assert target.read_bytes() == b"map"
    assert not stale.exists() and fresh.exists() and other.exists()


def _descriptors_of(path: Path) -> int:
    """How many of this process's descriptors are open on the file ``path`` names now."""
    inode = path.stat().st_ino
    count = 0
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            count += os.stat(f"/proc/self/fd/{fd}").st_ino == inode
    return count


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc")
@pytest.mark.parametrize(("writer", "large"), [("handle", True), ("path", True), ("handle", False)])
def test_the_replaced_file_is_freed_after_the_rename_not_in_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, writer: str, large: bool
) -> None:
    target = tmp_path / "room.kvmap"
    target.write_bytes(b"old" * 1000)
    held_during_rename: list[int] = []
    real_replace = os.replace

    def watched_replace(source: Path, destination: Path) -> None:
        held_during_rename.append(_descriptors_of(Path(destination)))
        real_replace(source, destination)

    monkeypatch.setattr(atomic.os, "replace", watched_replace)
    if large:  # this 3000-byte file counts as large: closed on a thread
        monkeypatch.setattr(atomic, "FREE_IN_BACKGROUND_BYTES", 1000)
    before = len(os.listdir("/proc/self/fd"))
    if writer == "handle":
        with atomic_write(target, binary=True) as handle:
            handle.write(b"new")
    else:
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"new")
    assert held_during_rename == [1]  # the old file stays open across the rename ...
    for thread in threading.enumerate():
        if thread.name == "kvtracker-free-old":
            thread.join(timeout=10)
    assert len(os.listdir("/proc/self/fd")) == before  # ... and is closed afterwards
    assert target.read_bytes() == b"new"
