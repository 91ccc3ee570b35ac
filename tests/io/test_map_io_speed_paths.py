"""The one-pass save (``benchmarks/map_io.py`` measures its speed): a header rewritten in place
once the data's digests are known, and writeback hints."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import torch
from safetensors import safe_open

from kvtracker_sdk.io.map_file.map_file import read_map_info, save_map
from kvtracker_sdk.io.map_file.map_tensors import map_to_tensors, sha256_of
from kvtracker_sdk.io.map_file.safetensors_writer import write_safetensors
from kvtracker_sdk.io.map_file.writeback import start_writeback
from tests.io.map_factory import backend_info, make_map


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
