"""DA3Config: Small/Base presets equal the official key lists; presets and inferred configs."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file

from kvtracker_sdk.errors import CheckpointMismatchError, ConfigError
from kvtracker_sdk.models.da3 import (
    DA3BackboneConfig,
    DA3Config,
    DA3HeadConfig,
    DepthAnything3,
    canonical_state_dict,
)
from tests.helpers import shared_path

# unique parameters from the official configs (the four tied LayerNorm copies counted once)
PARAMS = {"small": 34_299_463, "base": 135_366_599}


@pytest.fixture(scope="module")
def official_keys() -> dict[str, dict[str, tuple[int, ...]]]:
    listed = json.loads(shared_path("golden", "da3", "da3_keys.json").read_text())
    return {
        size: {name: tuple(shape) for name, shape in listed[size]} for size in ("small", "base")
    }


@pytest.mark.parametrize("size", ["small", "base"])
@pytest.mark.parametrize("prefixed", [False, True])
def test_preset_matches_official_keys(
    official_keys: dict[str, dict[str, tuple[int, ...]]], size: str, prefixed: bool
) -> None:
    with torch.device("meta"):
        model = DepthAnything3(DA3Config.preset(size))
    expected = official_keys[size]
    assert len(expected) == 443
    # a hub checkpoint's names carry "model."; canonical_state_dict must map them back. Shapes on
    # the meta device, but the tied LayerNorm copies are real (the loader compares their values).
    listed = {
        ("model." + k if prefixed else k): torch.zeros(
            shape, device="meta" if len(shape) > 1 else "cpu"
        )
        for k, shape in expected.items()
    }
    canonical = {k: tuple(v.shape) for k, v in canonical_state_dict(listed).items()}
    ours = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert set(ours) - set(canonical) == set(), "missing keys"
    assert set(canonical) - set(ours) == set(), "unexpected keys"
    assert ours == canonical == expected
    assert sum(p.numel() for p in model.parameters()) == PARAMS[size]
    assert DA3Config.from_state_dict(model.state_dict()) == DA3Config.preset(size)


@pytest.mark.parametrize("size", ["small", "base", "large", "giant"])
def test_presets_round_trip_through_their_weights(size: str) -> None:
    config = DA3Config.preset(size)
    with torch.device("meta"):
        model = DepthAnything3(config)
    assert DA3Config.from_state_dict(model.state_dict()) == config
    assert config.preset_name == size
    assert config.backbone.head_dim == 64
    giant = size == "giant"
    assert ("backbone.pretrained.blocks.0.mlp.w12.weight" in model.state_dict()) is giant


def test_preset_properties() -> None:
    small = DA3Config.small()
    assert small == DA3Config()
    assert small.backbone.global_block_indices == (5, 7, 9, 11)
    assert DA3Config.large().backbone.global_block_indices == tuple(range(9, 24, 2))
    assert DA3Config.giant().backbone.global_block_indices == tuple(range(13, 40, 2))
    with torch.device("meta"):
        assert DepthAnything3(small).tokens_per_frame(224, 224) == 257  # camera token + 16*16
    assert DA3Config.small().config_hash != DA3Config.base().config_hash
    assert len(small.config_hash) == 16
    custom = small.model_copy(
        update={"head": DA3HeadConfig(features=32, out_channels=(16, 32, 64, 128))}
    )
    assert custom.preset_name is None
    with pytest.raises(ConfigError, match="unknown DA3 preset"):
        DA3Config.preset("tiny")


def test_infers_golden_config() -> None:
    architecture = json.loads(shared_path("golden", "da3", "config.json").read_text())[
        "architecture"
    ]
    config = DA3Config.from_state_dict(
        load_file(shared_path("golden", "da3", "weights.safetensors"))
    )
    assert config.backbone.embed_dim == architecture["embed_dim"] == 128
    assert config.backbone.num_heads == architecture["num_heads"] == 2
    assert config.backbone.depth == architecture["depth"]
    assert config.backbone.global_block_indices == tuple(architecture["global_blocks"])
    assert config.backbone.out_layers == tuple(architecture["out_layers"])
    assert config.head == DA3HeadConfig(features=32, out_channels=(16, 32, 64, 128))


def test_infer_from_incomplete_checkpoint_names_the_key() -> None:
    with pytest.raises(CheckpointMismatchError, match="backbone.pretrained.cls_token") as info:
        DA3Config.from_state_dict({"head.norm.weight": torch.zeros(8)})
    assert info.value.missing == ["backbone.pretrained.cls_token"]


def test_invalid_configs_are_rejected() -> None:
    with pytest.raises(ConfigError, match="divisible by 4"):
        DA3BackboneConfig(embed_dim=36, num_heads=2)  # head_dim 18
    with pytest.raises(ConfigError, match="alt_start"):
        DA3BackboneConfig(depth=4, alt_start=4)
    with pytest.raises(ConfigError, match="no global block"):
        DA3BackboneConfig(depth=5, alt_start=4, out_layers=(0, 1, 2, 3))
    with pytest.raises(ConfigError, match="out_layers"):
        DA3BackboneConfig(out_layers=(5, 7, 9, 12))
    with pytest.raises(ConfigError, match="divisible by 4"):
        DA3HeadConfig(features=12)  # features / 2 = 6
    with pytest.raises(ConfigError):
        DA3HeadConfig(extra=1)  # type: ignore[call-arg]
