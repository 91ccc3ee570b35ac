"""Model families by name: which network a checkpoint holds, and loading it by name or file.

Two families share the KV-cache machinery (``models/layers``): ``pi3`` (π³, weights CC BY-NC)
and ``da3`` (Depth Anything 3; Small/Base weights Apache-2.0). A checkpoint's family is read from
its tensor names only (``safetensors`` headers, no tensor data):

| family | marker keys |
|---|---|
| pi3 | ``register_token`` and ``decoder.0.*`` |
| da3 | ``backbone.pretrained.camera_token`` (hub files: ``model.backbone.pretrained.camera_token``) |

``MODEL_NAMES`` maps the names users type to a family and the official hub repository:
``pi3``, ``da3-small``, ``da3-base``, ``da3-large``, ``da3-giant``. ``load_model`` accepts one
of those names, or a file / folder / hub repo id of either family.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from safetensors import SafetensorError, safe_open
from torch import nn

from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.models.checkpoint_utils import resolve_weights
from kvtracker_sdk.models.da3 import DA3Config, DepthAnything3, load_da3
from kvtracker_sdk.models.da3.checkpoint import HUB_REPOS as DA3_HUB_REPOS
from kvtracker_sdk.models.pi3 import Pi3, Pi3Config, load_pi3

__all__ = [
    "MODEL_NAMES",
    "Family",
    "LoadedModel",
    "checkpoint_family",
    "family_of_keys",
    "load_model",
    "model_family",
    "model_name",
]

Family = Literal["pi3", "da3"]

# user-facing model name -> (family, official hub repository)
MODEL_NAMES: dict[str, tuple[Family, str]] = {
    "pi3": ("pi3", "yyfz233/Pi3"),
    **{f"da3-{preset}": ("da3", repo) for preset, repo in DA3_HUB_REPOS.items()},
}


@dataclass(frozen=True)
class LoadedModel:
    """A network loaded from a checkpoint (fp32, CPU, eval mode) with its identity."""

    family: Family
    name: str  # "pi3", "da3-small", ... or "<family>-custom" for other architectures
    model: nn.Module  # Pi3 or DepthAnything3
    fingerprint: str  # content hash of the (canonical) weights
    path: Path


def family_of_keys(keys: Iterable[str]) -> Family:
    """The family whose checkpoints use these tensor names; ``ModelError`` if neither does."""
    names = set(keys)
    if names & {"backbone.pretrained.camera_token", "model.backbone.pretrained.camera_token"}:
        return "da3"
    if "register_token" in names and any(name.startswith("decoder.0.") for name in names):
        return "pi3"
    sample = ", ".join(sorted(names)[:5])
    raise ModelError(
        f"not a Pi3 or Depth Anything 3 checkpoint (no register_token/decoder.* nor "
        f"backbone.pretrained.camera_token among {len(names)} tensors; first: {sample})"
    )


def checkpoint_family(path: str | os.PathLike[str]) -> Family:
    """Family of a local ``.safetensors`` file, from its header (tensor data is not read)."""
    try:
        with safe_open(os.fspath(path), framework="pt") as handle:
            keys = list(handle.keys())
    except (SafetensorError, ValueError) as exc:  # a pickle, a zip, an empty or truncated file
        raise ModelError(f"{path} is not a readable .safetensors checkpoint: {exc}") from exc
    return family_of_keys(keys)


def load_model(
    weights: str | os.PathLike[str], *, config: Pi3Config | DA3Config | None = None
) -> LoadedModel:
    """Load a model by name (``MODEL_NAMES``) or from a file, folder or hub repo id of any family.

    A name that is also an existing path is read as the path. ``config`` (None: inferred from
    the tensor shapes) must belong to the checkpoint's family.
    """
    text = os.fspath(weights)
    if text in MODEL_NAMES and not Path(text).exists():
        weights = MODEL_NAMES[text][1]
    path = resolve_weights(weights)
    family = checkpoint_family(path)
    if config is not None and not isinstance(config, Pi3Config if family == "pi3" else DA3Config):
        raise ModelError(f"{path} holds a {family} checkpoint, got a {type(config).__name__}")
    if family == "pi3":
        pi3 = load_pi3(path, config=config if isinstance(config, Pi3Config) else None)
        return LoadedModel("pi3", model_name(pi3.model), pi3.model, pi3.fingerprint, pi3.path)
    da3 = load_da3(path, config=config if isinstance(config, DA3Config) else None)
    return LoadedModel("da3", model_name(da3.model), da3.model, da3.fingerprint, da3.path)


def model_family(model: nn.Module) -> Family:
    """The family of a network; ``ModelError`` for anything but ``Pi3`` / ``DepthAnything3``."""
    if isinstance(model, Pi3):
        return "pi3"
    if isinstance(model, DepthAnything3):
        return "da3"
    raise ModelError(f"{type(model).__name__} is neither a Pi3 nor a DepthAnything3 network")


def model_name(model: nn.Module) -> str:
    """The user-facing name of a network's architecture: ``pi3``, ``da3-small``, ... or
    ``<family>-custom`` for configurations that are not an official release."""
    if isinstance(model, Pi3):
        return "pi3" if model.config == Pi3Config.large() else "pi3-custom"
    if isinstance(model, DepthAnything3):
        return f"da3-{model.config.preset_name or 'custom'}"
    raise ModelError(f"{type(model).__name__} is neither a Pi3 nor a DepthAnything3 network")
