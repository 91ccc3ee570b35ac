"""The one-pass save and the load's checks (``benchmarks/map_io.py`` measures their speed): a
header rewritten in place once the data's digests are known, writeback hints, the K/V written
straight from the cache's buffers under its lock, and the finiteness check of loaded K/V."""

from __future__ import annotations

import io
import math
import os
import threading
from pathlib import Path
from typing import Any

import pytest
import torch
from safetensors import safe_open

from kvtracker_sdk.errors import MapCorruptedError
from kvtracker_sdk.io.map_file import map_file
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from kvtracker_sdk.io.map_file.map_tensors import map_to_tensors, sha256_of
from kvtracker_sdk.io.map_file.safetensors_writer import write_safetensors
from kvtracker_sdk.io.map_file.writeback import start_writeback
from tests.io.map_factory import backend_info, make_map, maps_equal


def test_the_header_is_rewritten_with_the_final_metadata(tmp_path: Path) -> None:
    tensors = {"b": torch.arange(6, dtype=torch.float32), "a": torch.ones(3, dtype=torch.uint8)}
    path = tmp_path / "t.safetensors"
    with open(path, "wb") as handle:
        size = write_safetensors(handle, tensors, {"digest": "0" * 8},
                                 final_metadata=lambda: {"digest": "12345678"})  # fmt: skip
    assert path.stat().st_size == size
    with safe_open(str(path), framework="pt") as reader:
        assert reader.metadata() == {"digest": "12345678"}
        assert torch.equal(reader.get_tensor("b"), tensors["b"])
    with pytest.raises(ValueError, match="final header"):  # another length would shift the data
        write_safetensors(io.BytesIO(), tensors, {"digest": "0"},
                          final_metadata=lambda: {"digest": "0123456789"})  # fmt: skip


def test_a_saved_map_carries_the_digests_of_its_tensors(tmp_path: Path) -> None:
    keyframe_map = make_map(seed=3)
    info = save_map(tmp_path / "m.kvmap", keyframe_map, backend_info=backend_info(),
                    tracker_config_json="{}", mode="scene")  # fmt: skip
    tensors, _, _ = map_to_tensors(keyframe_map, info.resolution)
    expected = sha256_of(tensors)
    assert info.tensor_sha256 == expected  # what save returned ...
    assert read_map_info(tmp_path / "m.kvmap").tensor_sha256 == expected  # ... and wrote
    assert "0" * 64 not in (tmp_path / "m.kvmap").read_bytes()[:200_000].decode("latin-1")


def test_writeback_hints_are_harmless(tmp_path: Path) -> None:
    path = tmp_path / "f"
    with open(path, "wb") as handle:
        handle.write(b"x" * 10_000)
        handle.flush()
        start_writeback(handle.fileno(), 0, 10_000)
    start_writeback(-1, 0, 10)  # a bad descriptor: ignored, the caller's fsync decides
    assert path.read_bytes() == b"x" * 10_000


def _other_thread_can_take(lock: Any) -> bool:
    """Whether a thread other than the caller could acquire ``lock`` right now."""
    taken: list[bool] = []

    def attempt() -> None:
        taken.append(lock.acquire(blocking=False))
        if taken[-1]:
            lock.release()

    thread = threading.Thread(target=attempt)
    thread.start()
    thread.join()
    return taken[0]


@pytest.mark.parametrize(("dtype", "storage"), [(torch.bfloat16, None), (torch.float32, "int8")])
def test_kv_written_from_the_cache_buffers_are_the_bytes_of_a_copy(
    dtype: torch.dtype, storage: str | None
) -> None:
    keyframe_map = make_map(seed=4, dtype=dtype, storage=storage)
    resolution = keyframe_map.resolution
    copies, _, _ = map_to_tensors(keyframe_map, resolution)
    with keyframe_map.cache.lock:
        views, _, _ = map_to_tensors(keyframe_map, resolution, cache_views=True)
        # the cache has spare capacity: its views are strided, contiguous only head by head
        assert any(not view.is_contiguous() for view in views.values())
        written = [io.BytesIO(), io.BytesIO()]
        for handle, tensors in zip(written, (copies, views), strict=True):
            write_safetensors(handle, tensors, {"note": "same"})
        assert sha256_of(views) == sha256_of(copies)
    assert written[0].getvalue() == written[1].getvalue()


def test_the_cache_lock_is_held_while_writing_and_released_before_the_fsync(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    keyframe_map = make_map(seed=5)
    lock = keyframe_map.cache.lock
    seen: dict[str, bool] = {}
    real_write, real_fsync = map_file.write_safetensors, os.fsync

    def watched_write(*args: Any, **kwargs: Any) -> int:
        seen["while writing"] = _other_thread_can_take(lock)
        return real_write(*args, **kwargs)

    def watched_fsync(fd: int) -> None:
        seen.setdefault("at the fsync", _other_thread_can_take(lock))
        real_fsync(fd)

    monkeypatch.setattr(map_file, "write_safetensors", watched_write)
    monkeypatch.setattr(os, "fsync", watched_fsync)
    save_map(tmp_path / "m.kvmap", keyframe_map, backend_info=backend_info(),
             tracker_config_json="{}", mode="scene")  # fmt: skip
    assert seen == {"while writing": False, "at the fsync": True}
    assert maps_equal(load_map(tmp_path / "m.kvmap").keyframe_map, keyframe_map)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_kv_are_refused_on_load_in_every_float_dtype(
    tmp_path: Path, dtype: torch.dtype, bad: float
) -> None:
    keyframe_map = make_map(seed=6, dtype=dtype)
    cache = keyframe_map.cache
    length = cache.layer_length(1)
    keys, _ = cache.buffers(1)
    keys[0, -1, length:] = math.nan  # spare capacity: not part of the map
    path = tmp_path / "m.kvmap"
    save_map(path, keyframe_map, backend_info=backend_info(dtype=str(dtype).removeprefix("torch.")),
             tracker_config_json="{}", mode="scene")  # fmt: skip
    assert load_map(path).info.num_keyframes == 3  # the spare capacity was not saved
    keys[0, -1, length - 1, -1] = bad  # the last value of the last head
    save_map(path, keyframe_map, backend_info=backend_info(dtype=str(dtype).removeprefix("torch.")),
             tracker_config_json="{}", mode="scene")  # fmt: skip
    with pytest.raises(MapCorruptedError, match=r"layer 1 key: values that are not finite"):
        load_map(path)
