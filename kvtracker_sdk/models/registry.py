"""The model families, by name: the one list of them, and the look-ups every layer uses.

Each family is a folder ``models/<family>/`` with a record (``family.py``, a ``ModelFamily``;
``models/family.py`` lists what a record provides). ``FAMILIES`` below holds one record per
family; nothing else in the SDK names a family's classes. A checkpoint's family is read from its
tensor names only (``safetensors`` headers, no tensor data), by asking each record.

``MODEL_NAMES`` maps the names users type to a family and the official hub repository:
``pi3``, ``da3-small``, ``da3-base``, ``da3-large``, ``da3-giant``. ``load_model`` accepts one
of those names, or a file / folder / hub repo id of any family.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch import nn

from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.models.checkpoint_utils import resolve_weights
from kvtracker_sdk.models.da3.family import DA3Family
from kvtracker_sdk.models.family import ModelFamily
from kvtracker_sdk.models.pi3.family import Pi3Family
from kvtracker_sdk.models.weights_file import read_safetensors_keys

__all__ = [
    "FAMILIES",
    "MODEL_NAMES",
    "Family",
    "LoadedModel",
    "checkpoint_family",
    "family_named",
    "family_of",
    "family_of_config",
    "family_of_keys",
    "load_model",
    "model_family",
    "model_name",
]

Family = str  # a key of FAMILIES: "pi3", "da3"

# one line per family
FAMILIES: dict[str, ModelFamily] = {
    family.name: family
    for family in (
        Pi3Family(),
        DA3Family(),
    )
}

# user-facing model name -> (family, official hub repository)
MODEL_NAMES: dict[str, tuple[Family, str]] = {
    model: (family.name, repo) for family in FAMILIES.values() for model, repo in family.hub_repos.items()
}


@dataclass(frozen=True)
class LoadedModel:
    """A network loaded from a checkpoint (fp32, CPU, eval mode) with its identity."""

    family: Family
    name: str  # "pi3", "da3-small", ... or "<family>-custom" for other architectures
    model: nn.Module  # the family's network
    fingerprint: str  # content hash of the (canonical) weights
    path: Path


def family_named(name: str) -> ModelFamily:
    """The record of family ``name`` (``ModelError`` names the known ones)."""
    try:
        return FAMILIES[name]
    except KeyError:
        raise ModelError(f"no model family {name!r}; this SDK has {sorted(FAMILIES)}") from None


def family_of(model: nn.Module) -> ModelFamily:
    """The record of a network's family; ``ModelError`` for networks of no family."""
    for family in FAMILIES.values():
        if isinstance(model, family.model_type):
            return family
    names = " nor a ".join(family.model_type.__name__ for family in FAMILIES.values())
    raise ModelError(f"{type(model).__name__} is neither a {names} network")


def family_of_config(config: Any) -> ModelFamily:
    """The record whose configuration class ``config`` is; ``ModelError`` otherwise."""
    for family in FAMILIES.values():
        if isinstance(config, family.config_type):
            return family
    raise ModelError(f"{type(config).__name__} is no model family's configuration")


def family_of_keys(keys: Iterable[str]) -> Family:
    """The family whose checkpoints use these tensor names; ``ModelError`` if none does."""
    names = set(keys)
    for family in FAMILIES.values():
        if family.owns_checkpoint(names):
            return family.name
    sample = ", ".join(sorted(names)[:5])
    known = " or ".join(family.display_name for family in FAMILIES.values())
    raise ModelError(
        f"not a {known} checkpoint: no family recognises its {len(names)} tensors "
        f"(first: {sample})"
    )


def checkpoint_family(path: str | os.PathLike[str]) -> Family:
    """Family of a local ``.safetensors`` file, from its header (tensor data is not read)."""
    # ModelError for a pickle, a zip, an empty or truncated file, a FIFO
    return family_of_keys(read_safetensors_keys(path))


def load_model(weights: str | os.PathLike[str], *, config: Any | None = None) -> LoadedModel:
    """Load a model by name (``MODEL_NAMES``) or from a file, folder or hub repo id of any family.

    A name that is also an existing path is read as the path. ``config`` (None: inferred from
    the tensor shapes) must belong to the checkpoint's family.
    """
    text = os.fspath(weights)
    if text in MODEL_NAMES and not Path(text).exists():
        weights = MODEL_NAMES[text][1]
    path = resolve_weights(weights)
    family = FAMILIES[checkpoint_family(path)]
    if config is not None and not isinstance(config, family.config_type):
        raise ModelError(f"{path} holds a {family.name} checkpoint, got a {type(config).__name__}")
    loaded = family.load(path, config)
    return LoadedModel(
        family.name, family.model_name(loaded.model), loaded.model, loaded.fingerprint, loaded.path
    )


def model_family(model: nn.Module) -> Family:
    """The family name of a network; ``ModelError`` for networks of no family."""
    return family_of(model).name


def model_name(model: nn.Module) -> str:
    """The user-facing name of a network's architecture: ``pi3``, ``da3-small``, ... or
    ``<family>-custom`` for configurations that are not an official release."""
    return family_of(model).model_name(model)
