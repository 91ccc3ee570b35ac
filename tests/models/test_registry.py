"""Model families: detection from tensor names, loading by file or by name."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from kvtracker_sdk.errors import ModelError, WeightsNotFoundError
from kvtracker_sdk.models.da3 import DepthAnything3
from kvtracker_sdk.models.pi3 import Pi3
from kvtracker_sdk.models.registry import MODEL_NAMES, checkpoint_family, family_of_keys, load_model
from tests.helpers import shared_path


def test_family_of_golden_checkpoints_from_headers() -> None:
    assert checkpoint_family(shared_path("golden", "pi3", "weights.safetensors")) == "pi3"
    assert checkpoint_family(shared_path("golden", "da3", "weights.safetensors")) == "da3"


def test_family_of_keys_with_hub_prefix_and_unknown_keys() -> None:
    assert (
        family_of_keys(["model.backbone.pretrained.camera_token", "model.head.norm.weight"])
        == "da3"
    )
    assert family_of_keys(["register_token", "decoder.0.norm1.weight"]) == "pi3"
    with pytest.raises(ModelError, match="not a Pi3 or Depth Anything 3 checkpoint"):
        family_of_keys(["encoder.cls_token", "decoder.0.norm1.weight"])  # no register_token


def test_load_model_picks_the_family(tmp_path: Path) -> None:
    pi3 = load_model(shared_path("golden", "pi3", "weights.safetensors"))
    assert pi3.family == "pi3" and pi3.name == "pi3-custom" and isinstance(pi3.model, Pi3)
    da3 = load_model(shared_path("golden", "da3", "weights.safetensors"))
    assert (
        da3.family == "da3" and da3.name == "da3-custom" and isinstance(da3.model, DepthAnything3)
    )
    # a hub-style DA3 file ("model." names) in a folder
    state = load_file(shared_path("golden", "da3", "weights.safetensors"))
    save_file(
        {"model." + k: v.contiguous() for k, v in state.items()}, tmp_path / "model.safetensors"
    )
    hub = load_model(tmp_path)
    assert hub.family == "da3" and hub.fingerprint == da3.fingerprint
    with pytest.raises(ModelError, match="holds a da3 checkpoint"):
        load_model(tmp_path, config=pi3.model.config)  # type: ignore[arg-type]
    with pytest.raises(ModelError):
        bogus = tmp_path / "bogus.safetensors"
        save_file({"weight": torch.zeros(2)}, bogus)
        load_model(bogus)


def test_names_map_to_official_repositories(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert MODEL_NAMES["da3-small"] == ("da3", "depth-anything/DA3-SMALL")
    assert MODEL_NAMES["da3-base"] == ("da3", "depth-anything/DA3-BASE")
    assert MODEL_NAMES["pi3"] == ("pi3", "yyfz233/Pi3")
    pytest.importorskip("huggingface_hub")
    import huggingface_hub.constants

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    with pytest.raises(WeightsNotFoundError, match="depth-anything/DA3-BASE"):
        load_model("da3-base")
