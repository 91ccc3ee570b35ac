"""DA3 checkpoint loading: ``model.`` prefix, the tied LayerNorm, unused heads, strict key checks."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file, save_model

from kvtracker_sdk.errors import CheckpointMismatchError, WeightsNotFoundError
from kvtracker_sdk.models.checkpoint_utils import weights_fingerprint
from kvtracker_sdk.models.da3 import DA3Config, canonical_state_dict, load_da3
from tests.helpers import shared_path
from tests.models.da3.factories import random_da3, tiny_config

TIED = [
    f"head.scratch.output_conv2_aux.{level}.2.{leaf}"
    for level in range(4)
    for leaf in ("weight", "bias")
]


@pytest.fixture(scope="module")
def golden_state() -> dict[str, torch.Tensor]:
    return load_file(shared_path("golden", "da3", "weights.safetensors"))


def _save(tmp_path: Path, state: dict[str, torch.Tensor], name: str = "model.safetensors") -> Path:
    path = tmp_path / name
    save_file(
        {k: v.clone().contiguous() for k, v in state.items()}, path
    )  # clone: no shared storage
    return path


def test_golden_loads_strictly_with_a_content_fingerprint(
    golden_state: dict[str, torch.Tensor],
) -> None:
    loaded = load_da3(shared_path("golden", "da3", "weights.safetensors"))
    assert not loaded.model.training
    assert loaded.fingerprint == weights_fingerprint(golden_state)
    state = loaded.model.state_dict()
    assert set(state) == set(golden_state) and all(
        torch.equal(state[k], golden_state[k]) for k in state
    )
    norms = [loaded.model.head.scratch.output_conv2_aux[level][2] for level in range(4)]
    assert all(norm is norms[0] for norm in norms)  # one shared module, as in the official head


def test_hub_layout_prefix_and_deduplicated_tie(
    tmp_path: Path, golden_state: dict[str, torch.Tensor]
) -> None:
    # what PyTorchModelHubMixin writes: "model." names, one copy of the shared LayerNorm
    hub = {"model." + k: v for k, v in golden_state.items() if not k.startswith(tuple(TIED[2:]))}
    assert len(hub) == 443 - 6
    folder = tmp_path / "DA3-SMALL"
    folder.mkdir()
    _save(folder, hub)
    loaded = load_da3(folder)
    direct = load_da3(shared_path("golden", "da3", "weights.safetensors"))
    assert loaded.path == folder / "model.safetensors"
    assert loaded.fingerprint == direct.fingerprint  # canonical content, not the file's layout
    for key in TIED:
        assert torch.equal(loaded.model.state_dict()[key], golden_state[key])


def test_save_model_round_trip(tmp_path: Path) -> None:
    model = random_da3(seed=4)
    path = tmp_path / "tiny.safetensors"
    save_model(model, str(path))  # drops the duplicate names of the tied LayerNorm
    assert len(load_file(path)) < len(model.state_dict())
    with pytest.raises(CheckpointMismatchError, match="pass out_layers"):  # not visible in weights
        load_da3(path)
    loaded = load_da3(path, config=tiny_config())
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.model.state_dict()[key], value), key


def test_broken_tie_is_a_mismatch(tmp_path: Path, golden_state: dict[str, torch.Tensor]) -> None:
    state = dict(golden_state)
    state[TIED[4]] = state[TIED[4]] + 1.0  # level 2's weight no longer equals level 0's
    with pytest.raises(CheckpointMismatchError, match="shared module") as info:
        load_da3(_save(tmp_path, state))
    assert [entry[0] for entry in info.value.shape_mismatches] == [TIED[4]]


def test_gaussian_head_is_the_only_ignored_extra(
    tmp_path: Path, golden_state: dict[str, torch.Tensor]
) -> None:
    extras = {
        "gs_head.scratch.output_conv2.0.weight": torch.zeros(2, 2),
        "gs_head.norm.bias": torch.zeros(2),
    }
    assert set(canonical_state_dict({**golden_state, **extras})) == set(golden_state)
    state = {**golden_state, "head.sky_output_conv2.0.weight": torch.zeros(2, 2)}
    with pytest.raises(CheckpointMismatchError, match="sky_output_conv2") as info:
        load_da3(_save(tmp_path, state))
    assert info.value.unexpected == ["head.sky_output_conv2.0.weight"]


@pytest.mark.parametrize(
    ("edit", "field", "key"),
    [
        ("drop", "missing", "backbone.pretrained.blocks.5.attn.k_norm.weight"),
        ("add", "unexpected", "backbone.pretrained.mask_token"),
        ("reshape", "shape_mismatches", "cam_dec.fc_qvec.weight"),
    ],
)
def test_mismatch_lists_keys(
    tmp_path: Path, golden_state: dict[str, torch.Tensor], edit: str, field: str, key: str
) -> None:
    state = dict(golden_state)
    if edit == "drop":
        del state[key]
    elif edit == "add":
        state[key] = torch.zeros(1, 128)
    else:
        state[key] = torch.zeros(4, 8)
    config = DA3Config.from_state_dict(golden_state)
    with pytest.raises(CheckpointMismatchError, match=key.replace(".", r"\.")) as info:
        load_da3(_save(tmp_path, state), config=config)
    listed = getattr(info.value, field)
    assert [entry if isinstance(entry, str) else entry[0] for entry in listed] == [key]


def test_preset_name_offline_names_the_hub_repo(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("huggingface_hub")
    import huggingface_hub.constants

    monkeypatch.chdir(tmp_path)  # no local folder called "da3-small"
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    with pytest.raises(WeightsNotFoundError, match="pass the local file") as info:
        load_da3("da3-small")
    assert "depth-anything/DA3-SMALL" in str(info.value)
