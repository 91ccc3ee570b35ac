"""Pi3Config: the large preset equals the official key list; configs inferred from checkpoints."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file

from kvtracker_sdk.errors import CheckpointMismatchError, ConfigError
from kvtracker_sdk.models.pi3 import (
    Pi3,
    Pi3Config,
    Pi3DecoderConfig,
    Pi3EncoderConfig,
    Pi3HeadsConfig,
)
from tests.helpers import shared_path


@pytest.fixture(scope="module")
def large_on_meta() -> Pi3:
    with torch.device("meta"):
        return Pi3(Pi3Config.large())


def test_large_matches_official_keys_and_shapes(large_on_meta: Pi3) -> None:
    official = json.loads(shared_path("golden", "pi3", "full_model_keys.json").read_text())
    expected = {name: tuple(shape) for name, shape in official["keys"]}
    ours = {name: tuple(t.shape) for name, t in large_on_meta.state_dict().items()}
    assert len(official["keys"]) == 1210
    assert set(ours) - set(expected) == set(), "unexpected keys"
    assert set(expected) - set(ours) == set(), "missing keys"
    assert ours == expected
    assert (
        sum(t.numel() for t in large_on_meta.state_dict().values())
        == official["n_params"]
        == 958_696_738
    )


def test_large_properties(large_on_meta: Pi3) -> None:
    config = Pi3Config.large()
    assert config == Pi3Config()
    assert config.decoder.global_block_indices == tuple(range(1, 36, 2))
    assert len(config.decoder.global_block_indices) == 18
    assert config.decoder.head_dim == 64
    assert large_on_meta.tokens_per_frame(308, 308) == 489  # 5 registers + 22*22 patches
    assert Pi3Config.from_state_dict(large_on_meta.state_dict()) == config


def test_infers_golden_config() -> None:
    architecture = json.loads(shared_path("golden", "pi3", "config.json").read_text())[
        "architecture"
    ]
    config = Pi3Config.from_state_dict(
        load_file(shared_path("golden", "pi3", "weights.safetensors"))
    )
    assert config.encoder.embed_dim == architecture["encoder"]["embed_dim"] == 64
    assert config.encoder.depth == architecture["encoder"]["depth"]
    assert config.encoder.num_heads == architecture["encoder"]["num_heads"]
    assert config.encoder.num_register_tokens == 4
    assert config.decoder.depth == 8 and config.decoder.num_heads == 2
    assert config.decoder.global_block_indices == tuple(architecture["decoder"]["global_layers"])
    assert config.heads.embed_dim == 48 and config.heads.depth == 2
    assert config.heads.point_out_dim == 48 and config.heads.camera_out_dim == 32


def test_infer_from_incomplete_checkpoint_names_the_key() -> None:
    with pytest.raises(CheckpointMismatchError, match="decoder.0.norm1.weight") as info:
        Pi3Config.from_state_dict({"encoder.cls_token": torch.zeros(1, 1, 8)})
    assert info.value.missing == ["decoder.0.norm1.weight"]


def test_invalid_configs_are_rejected() -> None:
    with pytest.raises(ConfigError, match="divisible by 4"):
        Pi3DecoderConfig(embed_dim=36, num_heads=2)  # head_dim 18
    with pytest.raises(ConfigError, match="even"):
        Pi3DecoderConfig(embed_dim=32, num_heads=2, depth=3)
    with pytest.raises(ConfigError, match="not divisible"):
        Pi3EncoderConfig(embed_dim=30, num_heads=4)
    with pytest.raises(ConfigError, match="must equal"):
        Pi3Config(
            encoder=Pi3EncoderConfig(embed_dim=64, num_heads=2),
            decoder=Pi3DecoderConfig(embed_dim=32, num_heads=2),
        )
    with pytest.raises(ConfigError):
        Pi3HeadsConfig(extra_field=1)  # type: ignore[call-arg]


def test_frozen_and_hash() -> None:
    config = Pi3Config.large()
    with pytest.raises(ConfigError):
        config.patch_size = 16  # type: ignore[misc]
    small = config.model_copy(update={"heads": Pi3HeadsConfig(embed_dim=32, num_heads=2)})
    assert config.config_hash == Pi3Config.large().config_hash
    assert small.config_hash != config.config_hash
    assert len(config.config_hash) == 16
