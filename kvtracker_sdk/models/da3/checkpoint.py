"""Loading Depth Anything 3 weights strictly, from a file, a folder or a hub repo id.

``load_da3(weights)`` accepts what ``resolve_weights`` does (``models/checkpoint_utils.py``): a
``.safetensors`` file, a folder containing ``model.safetensors`` or a hub repo id (the official
ones are listed in ``HUB_REPOS``). Before the strict key check the state dict is put in canonical
form (``canonical_state_dict``):

- **prefix**: hub checkpoints are saved from the wrapper ``DepthAnything3`` that holds the net as
  ``self.model``, so their keys start with ``model.``; a state dict whose every key has that
  prefix is stripped of it.
- **tied LayerNorm**: ``head.scratch.output_conv2_aux.{0,1,2,3}.2.{weight,bias}`` are one module
  in the official head. ``safetensors.torch.save_model`` (what the hub mixin uses) keeps a single
  name of a shared tensor, a plain ``state_dict()`` keeps all four. Any non-empty subset of the
  four copies is accepted if the copies present are equal; the missing names are filled from
  them. Unequal copies (a broken tie) are a ``CheckpointMismatchError``.
- **unused heads**: DA3-Giant checkpoints also hold the 3D-Gaussian head ``gs_head.*``, which
  this SDK does not build (tracking needs poses, depth and confidence). Those keys, and only
  those, are dropped; every other key must match the model exactly.

The fingerprint is taken over the canonical state dict, so a checkpoint gives the same
fingerprint with or without the prefix and with one or four LayerNorm copies.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch

from kvtracker_sdk.errors import CheckpointMismatchError
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.models.checkpoint_utils import (
    DEFAULT_FILENAME,
    load_strictly,
    read_state_dict,
    resolve_weights,
)
from kvtracker_sdk.models.da3.config import DA3Config
from kvtracker_sdk.models.da3.model import DepthAnything3

__all__ = ["HUB_REPOS", "LoadedDA3", "canonical_state_dict", "load_da3"]

# official hub repositories per preset (Small/Base Apache-2.0, Large/Giant CC BY-NC 4.0)
HUB_REPOS = {
    "small": "depth-anything/DA3-SMALL",
    "base": "depth-anything/DA3-BASE",
    "large": "depth-anything/DA3-LARGE-1.1",
    "giant": "depth-anything/DA3-GIANT-1.1",
}
_PREFIX = "model."
_TIED_NORM = re.compile(r"^head\.scratch\.output_conv2_aux\.(\d+)\.2\.(weight|bias)$")
_UNUSED_PREFIXES = ("gs_head.",)
_log = get_logger(__name__)


@dataclass(frozen=True)
class LoadedDA3:
    """A model loaded from a checkpoint (fp32 as stored, on CPU, eval mode)."""

    model: DepthAnything3
    fingerprint: str  # weights_fingerprint of the canonical state dict
    path: Path  # the safetensors file read


def _strip_prefix(state_dict: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    if state_dict and all(key.startswith(_PREFIX) for key in state_dict):
        return {key[len(_PREFIX) :]: value for key, value in state_dict.items()}
    return dict(state_dict)


def _fill_tied_norm(state_dict: dict[str, torch.Tensor], levels: int = 4) -> None:
    """Give every aux level the shared LayerNorm's tensors (in place); reject a broken tie."""
    present: dict[str, list[str]] = {}
    for key in state_dict:
        if match := _TIED_NORM.match(key):
            present.setdefault(match.group(2), []).append(key)
    for leaf, keys in present.items():
        first = state_dict[keys[0]]
        differing = [
            k
            for k in keys[1:]
            if state_dict[k].shape != first.shape or not torch.equal(state_dict[k], first)
        ]
        if differing:
            raise CheckpointMismatchError(
                f"the aux-head LayerNorm is one shared module, but {differing} differ from {keys[0]}",
                shape_mismatches=[
                    (k, tuple(state_dict[k].shape), tuple(first.shape)) for k in differing
                ],
            )
        for level in range(levels):
            state_dict.setdefault(f"head.scratch.output_conv2_aux.{level}.2.{leaf}", first)


def canonical_state_dict(state_dict: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Official DA3 state dict -> the names of ``DepthAnything3`` (see the module docstring)."""
    canonical = _strip_prefix(state_dict)
    unused = [key for key in canonical if key.startswith(_UNUSED_PREFIXES)]
    if unused:
        _log.info("da3_checkpoint_unused_keys", count=len(unused), prefixes=list(_UNUSED_PREFIXES))
        for key in unused:
            del canonical[key]
    _fill_tied_norm(canonical)
    return canonical


def load_da3(
    weights: str | os.PathLike[str],
    *,
    config: DA3Config | None = None,
    filename: str = DEFAULT_FILENAME,
) -> LoadedDA3:
    """Load a DA3 checkpoint strictly; ``config`` None infers it from the tensor shapes.

    ``weights`` may also be a preset name (``"da3-small"``, ...) that is not an existing path:
    it stands for the preset's official hub repository.
    """
    name = os.fspath(weights)
    if name.startswith("da3-") and name[4:] in HUB_REPOS and not Path(name).exists():
        weights = HUB_REPOS[name[4:]]
    path = resolve_weights(weights, filename=filename)
    state_dict = canonical_state_dict(read_state_dict(path))
    config = config or DA3Config.from_state_dict(state_dict)
    model, fingerprint = load_strictly(lambda: DepthAnything3(config), state_dict)
    return LoadedDA3(model=model, fingerprint=fingerprint, path=path)
