"""Checkpoint loading: file, folder, hub id (offline), strict key checks, fingerprints."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from kvtracker_sdk.errors import CheckpointMismatchError, ModelError, WeightsNotFoundError
from kvtracker_sdk.models.pi3 import load_pi3, resolve_weights, weights_fingerprint
from tests.helpers import shared_path
from tests.models.pi3.factories import random_pi3, tiny_config


@pytest.fixture()
def tiny_checkpoint(tmp_path: Path) -> tuple[Path, dict[str, torch.Tensor]]:
    model = random_pi3(tiny_config(), seed=3)
    state = {k: v.contiguous() for k, v in model.state_dict().items()}
    path = tmp_path / "tiny.safetensors"
    save_file(state, path)
    return path, state


def test_load_from_file_roundtrips_weights(
    tiny_checkpoint: tuple[Path, dict[str, torch.Tensor]],
) -> None:
    path, state = tiny_checkpoint
    loaded = load_pi3(path)
    assert loaded.path == path
    assert loaded.model.config == tiny_config()
    assert not loaded.model.training
    for key, value in loaded.model.state_dict().items():
        assert torch.equal(value, state[key]), key
    assert loaded.fingerprint == weights_fingerprint(state)


def test_load_from_folder(tmp_path: Path) -> None:
    folder = tmp_path / "Pi3"
    folder.mkdir()
    shutil.copy(shared_path("golden", "pi3", "weights.safetensors"), folder / "model.safetensors")
    loaded = load_pi3(folder)
    assert loaded.path == folder / "model.safetensors"
    assert loaded.model.config.decoder.depth == 8
    direct = load_pi3(shared_path("golden", "pi3", "weights.safetensors"))
    assert loaded.fingerprint == direct.fingerprint  # content, not path
    with pytest.raises(WeightsNotFoundError, match="has no model.safetensors"):
        resolve_weights(tmp_path)


@pytest.mark.parametrize(
    ("edit", "field", "key"),
    [
        ("drop", "missing", "decoder.1.attn.k_norm.weight"),
        ("add", "unexpected", "encoder.mask_token"),
        ("reshape", "shape_mismatches", "camera_head.fc_t.weight"),
    ],
)
def test_mismatch_lists_keys(
    tmp_path: Path,
    tiny_checkpoint: tuple[Path, dict[str, torch.Tensor]],
    edit: str,
    field: str,
    key: str,
) -> None:
    _, state = tiny_checkpoint
    state = dict(state)
    if edit == "drop":
        del state[key]
    elif edit == "add":
        state[key] = torch.zeros(1, 32)
    else:
        state[key] = torch.zeros(4, 16)
    path = tmp_path / "broken.safetensors"
    save_file(state, path)
    with pytest.raises(CheckpointMismatchError, match=key.replace(".", r"\.")) as info:
        load_pi3(path, config=tiny_config())
    listed = getattr(info.value, field)
    assert [entry if isinstance(entry, str) else entry[0] for entry in listed] == [key]


def test_wrong_config_is_a_mismatch(tiny_checkpoint: tuple[Path, dict[str, torch.Tensor]]) -> None:
    path, _ = tiny_checkpoint
    with pytest.raises(CheckpointMismatchError) as info:
        load_pi3(path, config=tiny_config(depth=6))
    assert "decoder.5.norm1.weight" in info.value.missing


def test_hub_id_offline_says_how_to_pass_a_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("huggingface_hub")
    import huggingface_hub.constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))  # an empty cache: nothing to fall back on
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    with pytest.raises(WeightsNotFoundError, match="pass the local file") as info:
        load_pi3("yyfz233/Pi3")
    assert "yyfz233/Pi3" in str(info.value)
    assert isinstance(info.value, FileNotFoundError)


def test_unreachable_hub_fails_fast_without_retrying(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No network and no cached copy: a clear error at once, never huggingface_hub's retry loop."""
    huggingface_hub = pytest.importorskip("huggingface_hub")
    import socket

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", False)

    def no_dns(*args: object, **kwargs: object) -> None:
        raise socket.gaierror("Name or service not known")

    def must_not_download(*args: object, **kwargs: object) -> None:
        if not kwargs.get("local_files_only"):
            raise AssertionError("the network download must not be attempted")
        raise huggingface_hub.errors.LocalEntryNotFoundError("not cached")

    monkeypatch.setattr(socket, "getaddrinfo", no_dns)
    monkeypatch.setattr(huggingface_hub, "hf_hub_download", must_not_download)
    with pytest.raises(WeightsNotFoundError, match="cannot be reached"):
        load_pi3("yyfz233/Pi3")


def test_rejects_pickles_and_unknown_paths(tmp_path: Path) -> None:
    pickle = tmp_path / "model.pth"
    pickle.write_bytes(b"not read")
    with pytest.raises(ModelError, match="only .safetensors"):
        load_pi3(pickle)
    with pytest.raises(WeightsNotFoundError, match="neither"):
        load_pi3(tmp_path / "nowhere" / "x.safetensors")


def test_fingerprint_depends_on_content_only() -> None:
    a = {"x": torch.arange(6.0).reshape(2, 3), "y": torch.ones(2)}
    b = {"y": torch.ones(2), "x": torch.arange(6.0).reshape(2, 3)}
    assert weights_fingerprint(a) == weights_fingerprint(b)
    c = dict(a, x=a["x"] + 1e-3)
    assert weights_fingerprint(c) != weights_fingerprint(a)
    assert weights_fingerprint({"x": a["x"].reshape(3, 2), "y": a["y"]}) != weights_fingerprint(a)


def test_offline_mode_asks_no_name_lookup(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """HF_HUB_OFFLINE set: the error comes without resolving the hub's name (no DNS query)."""
    huggingface_hub = pytest.importorskip("huggingface_hub")
    import socket

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    looked_up: list[object] = []
    monkeypatch.setattr(socket, "getaddrinfo", lambda *args, **kwargs: looked_up.append(args))
    with pytest.raises(WeightsNotFoundError, match="HF_HUB_OFFLINE is set"):
        load_pi3("yyfz233/Pi3")
    assert looked_up == []
