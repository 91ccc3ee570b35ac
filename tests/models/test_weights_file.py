"""Checkpoints are read through one descriptor, never a memory map (``models/weights_file.py``).

Without it a checkpoint truncated while it is read (a copy or download still in progress) kills
the process with SIGBUS, and a FIFO named as the weights blocks the app forever: both run in a
child process here, so a signal or a hang fails the test instead of killing pytest.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.models import weights_file
from kvtracker_sdk.models.registry import checkpoint_family
from kvtracker_sdk.models.weights_file import read_safetensors, read_safetensors_keys
from tests.helpers import PROJECT_ROOT

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="needs POSIX files and FIFOs")


def _checkpoint(path: Path) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    tensors = {
        "f32": torch.randn(3, 5, generator=generator),
        "bf16": torch.randn(7, generator=generator).to(torch.bfloat16),
        "f16": torch.randn(2, 2, 2, generator=generator).half(),
        "i64": torch.arange(6).reshape(2, 3),
        "u8": torch.randint(0, 255, (9,), generator=generator, dtype=torch.uint8),
        "bool": torch.tensor([True, False, True]),
        "fp8": torch.randn(4, generator=generator).to(torch.float8_e4m3fn),
        "scalar": torch.tensor(2.5),
        "empty": torch.zeros(0, 4),
    }
    save_file(tensors, str(path), metadata={"format": "pt"})
    return tensors


def test_reads_what_the_safetensors_library_reads(tmp_path: Path) -> None:
    path = tmp_path / "model.safetensors"
    _checkpoint(path)
    ours, theirs = read_safetensors(path), load_file(path)
    assert list(ours) == list(theirs) == read_safetensors_keys(path)
    for name, tensor in theirs.items():
        assert ours[name].dtype == tensor.dtype and ours[name].shape == tensor.shape, name
        assert torch.equal(
            ours[name].reshape(-1).view(torch.uint8), tensor.reshape(-1).view(torch.uint8)
        ), name


def _header(path: Path) -> tuple[int, dict[str, dict[str, object]]]:
    data = path.read_bytes()
    size = int.from_bytes(data[:8], "little")
    return size, json.loads(data[8 : 8 + size])


@pytest.mark.parametrize(
    "damage",
    ["short_data", "offsets_past_the_end", "shape_disagrees", "unknown_dtype", "not_json"],
)
def test_a_damaged_header_or_body_is_a_model_error(tmp_path: Path, damage: str) -> None:
    path = tmp_path / "model.safetensors"
    _checkpoint(path)
    size, header = _header(path)
    body = path.read_bytes()[8 + size :]
    entry = header["f32"]
    assert isinstance(entry, dict)
    if damage == "short_data":
        body = body[:-3]
    elif damage == "offsets_past_the_end":
        entry["data_offsets"] = [0, len(body) + 60]
    elif damage == "shape_disagrees":
        entry["shape"] = [4, 5]
    elif damage == "unknown_dtype":
        entry["dtype"] = "C64"
    raw = b"{not json" if damage == "not_json" else json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)
    path.write_bytes(len(raw).to_bytes(8, "little") + raw + body)
    with pytest.raises(ModelError, match="not a readable .safetensors checkpoint|ended at"):
        read_safetensors(path)


def test_a_file_truncated_while_it_is_read_is_a_model_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "model.safetensors"
    _checkpoint(path)
    header_end = 8 + _header(path)[0]
    real_empty = torch.empty

    def truncate_then_allocate(*args: object, **kwargs: object) -> torch.Tensor:
        os.truncate(path, header_end + 4)  # after the header was validated
        return real_empty(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(weights_file.torch, "empty", truncate_then_allocate)
    with pytest.raises(ModelError, match="truncated or rewritten"):
        read_safetensors(path)


_CHILD = """
import sys
from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.models.checkpoint_utils import read_state_dict
try:
    read_state_dict(sys.argv[1])
    print("loaded")
except ModelError as exc:
    print("ModelError", exc)
"""


def test_a_fifo_named_as_the_weights_is_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "model.safetensors"
    os.mkfifo(fifo)
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(fifo)],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        timeout=120,  # a loader opening the FIFO without O_NONBLOCK waits here forever
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("ModelError") and "not a regular file" in done.stdout


def test_the_family_of_a_fifo_is_a_model_error(tmp_path: Path) -> None:
    fifo = tmp_path / "model.safetensors"
    os.mkfifo(fifo)
    with pytest.raises(ModelError, match="not a regular file"):
        checkpoint_family(fifo)
