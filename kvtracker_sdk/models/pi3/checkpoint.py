"""Loading Pi3 weights: a ``.safetensors`` file, a folder holding one, or a Hugging Face repo id.

``load_pi3(weights)`` accepts what ``resolve_weights`` does (``models/checkpoint_utils.py``, shared
with the other model families): a ``.safetensors`` file, a folder containing ``model.safetensors``
(the layout of the hub repository ``yyfz233/Pi3``) or a hub repo id such as ``"yyfz233/Pi3"``.
The model is built on the meta device, the checkpoint's keys and shapes are compared with it
(``CheckpointMismatchError`` lists missing, unexpected and wrongly shaped keys), and the tensors
are then assigned without a second copy — the 3.8 GB official checkpoint is held in memory once.
``weights_fingerprint`` hashes the tensors' content, not the file path.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from kvtracker_sdk.models.checkpoint_utils import (
    DEFAULT_FILENAME,
    check_state_dict,
    load_strictly,
    read_state_dict,
    resolve_weights,
    weights_fingerprint,
)
from kvtracker_sdk.models.pi3.config import Pi3Config
from kvtracker_sdk.models.pi3.model import Pi3

__all__ = [
    "DEFAULT_FILENAME",
    "LoadedPi3",
    "check_state_dict",
    "load_pi3",
    "resolve_weights",
    "weights_fingerprint",
]


@dataclass(frozen=True)
class LoadedPi3:
    """A model loaded from a checkpoint (fp32 as stored, on CPU, eval mode)."""

    model: Pi3
    fingerprint: str  # weights_fingerprint of the checkpoint's tensors
    path: Path  # the safetensors file read


def load_pi3(
    weights: str | os.PathLike[str],
    *,
    config: Pi3Config | None = None,
    filename: str = DEFAULT_FILENAME,
) -> LoadedPi3:
    """Load a Pi3 checkpoint strictly; ``config`` None infers it from the tensor shapes."""
    path = resolve_weights(weights, filename=filename)
    state_dict = read_state_dict(path)
    config = config or Pi3Config.from_state_dict(state_dict)
    model, fingerprint = load_strictly(lambda: Pi3(config), state_dict)
    return LoadedPi3(model=model, fingerprint=fingerprint, path=path)
