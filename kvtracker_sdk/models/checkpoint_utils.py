"""Checkpoint helpers shared by the model families: locating weights, strict key checks, hashing.

- ``resolve_weights(weights)``: a path to a ``.safetensors`` file; a folder containing
  ``model.safetensors`` (the layout of the hub repositories ``yyfz233/Pi3`` and
  ``depth-anything/DA3-*``); or a hub repo id, fetched through ``huggingface_hub`` (imported only
  then; the ``[hub]`` extra). Offline or unknown repos raise ``WeightsNotFoundError`` whose message
  says how to pass a local file instead. Only safetensors are read: pickled checkpoints
  (``.pth``/``.bin``) can run code when loaded.
- ``check_state_dict(model, state_dict)``: ``CheckpointMismatchError`` listing missing,
  unexpected and wrongly shaped keys (run against a model built on the meta device, before any
  tensor is assigned).
- ``weights_fingerprint(state_dict)``: a hash of the tensors' names, dtypes, shapes and bytes
  (not the file path), so the same weights give the same fingerprint wherever they are stored.
"""

from __future__ import annotations

import hashlib
import os
import re
import socket
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypeVar
from urllib.parse import urlparse

import torch
from torch import nn

from kvtracker_sdk.errors import (
    CheckpointMismatchError,
    MissingDependencyError,
    ModelError,
    WeightsNotFoundError,
)
from kvtracker_sdk.models.weights_file import read_safetensors

ModuleT = TypeVar("ModuleT", bound=nn.Module)

__all__ = [
    "DEFAULT_FILENAME",
    "StateDictShapes",
    "check_state_dict",
    "read_state_dict",
    "resolve_weights",
    "weights_fingerprint",
]

DEFAULT_FILENAME = "model.safetensors"
_REPO_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[\w.-]+$")
_LISTED = 20  # keys listed per category in an error message


def resolve_weights(weights: str | os.PathLike[str], *, filename: str = DEFAULT_FILENAME) -> Path:
    """The local safetensors file that ``weights`` (file, folder or hub repo id) designates."""
    candidate = Path(weights).expanduser()
    if candidate.is_file():
        if candidate.suffix != ".safetensors":
            raise ModelError(
                f"{candidate}: only .safetensors checkpoints are supported (pickles can run code)"
            )
        return candidate
    if candidate.is_dir():
        inside = candidate / filename
        if inside.is_file():
            return inside
        raise WeightsNotFoundError(f"folder {candidate} has no {filename}")
    text = os.fspath(weights)
    if _REPO_ID.match(text):
        return _download(text, filename)
    raise WeightsNotFoundError(
        f"{text!r} is neither an existing .safetensors file, a folder containing {filename}, "
        "nor a hub repo id like 'yyfz233/Pi3' or 'depth-anything/DA3-SMALL'"
    )


def _download(repo_id: str, filename: str) -> Path:
    try:
        import huggingface_hub
    except ImportError as exc:
        raise MissingDependencyError.for_extra(
            "hub", f"loading {repo_id!r} from the hub needs huggingface_hub (or pass the path of "
            f"a local {filename})"
        ) from exc
    hint = (
        f"Download it on a machine with network access and pass the local file or its folder "
        f"instead, e.g. TorchBackend.from_pretrained('/path/to/{filename}')"
    )
    try:  # a copy in the local hub cache needs no network
        return Path(huggingface_hub.hf_hub_download(repo_id, filename, local_files_only=True))
    except Exception:  # not cached: fall through to the network
        pass
    # The user said "no network" (huggingface_hub's HF_HUB_OFFLINE): not even a name lookup.
    if huggingface_hub.constants.HF_HUB_OFFLINE:
        raise WeightsNotFoundError(
            f"{filename} of hub repo {repo_id!r} is not in the local cache and HF_HUB_OFFLINE is "
            f"set. {hint}"
        )
    # Without this check huggingface_hub retries an unreachable host for a long time before
    # failing (benchmarks/README.md#figures-behind-the-code).
    if not _hub_reachable(huggingface_hub.constants.ENDPOINT):
        raise WeightsNotFoundError(
            f"{filename} of hub repo {repo_id!r} is not in the local cache and the hub cannot be "
            f"reached (no network). {hint}"
        )
    try:
        return Path(huggingface_hub.hf_hub_download(repo_id, filename))
    # Offline mode, unknown repo or file, auth: for the caller all mean "not found".
    except Exception as exc:
        raise WeightsNotFoundError(
            f"could not get {filename} of hub repo {repo_id!r} ({type(exc).__name__}: {exc}). {hint}"
        ) from exc


def _hub_reachable(endpoint: str) -> bool:
    """True if the hub's host name resolves (a fast, offline-safe proxy for 'network is up')."""
    host = urlparse(endpoint).hostname
    if not host:
        return False
    try:
        socket.getaddrinfo(host, 443)
    except OSError:
        return False
    return True


def check_state_dict(model: nn.Module, state_dict: Mapping[str, torch.Tensor]) -> None:
    """Raise ``CheckpointMismatchError`` unless keys and shapes equal the model's exactly."""
    expected = {key: tuple(value.shape) for key, value in model.state_dict().items()}
    missing = sorted(set(expected) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(expected))
    mismatched = [
        (key, tuple(state_dict[key].shape), shape)
        for key, shape in expected.items()
        if key in state_dict and tuple(state_dict[key].shape) != shape
    ]
    if not (missing or unexpected or mismatched):
        return
    lines = [f"checkpoint does not match the model ({type(model).__name__})"]
    for title, items in (
        ("missing", missing),
        ("unexpected", unexpected),
        (
            "wrong shape (checkpoint vs model)",
            [f"{k}: {got} vs {want}" for k, got, want in mismatched],
        ),
    ):
        if items:
            more = f" (+{len(items) - _LISTED} more)" if len(items) > _LISTED else ""
            lines.append(f"  {title} [{len(items)}]: {', '.join(items[:_LISTED])}{more}")
    raise CheckpointMismatchError(
        "\n".join(lines), missing=missing, unexpected=unexpected, shape_mismatches=mismatched
    )


def weights_fingerprint(state_dict: Mapping[str, torch.Tensor]) -> str:
    """Content hash (32 hex chars) of names, dtypes, shapes and bytes, independent of key order."""
    digest = hashlib.blake2b(digest_size=16)
    for key in sorted(state_dict):
        tensor = state_dict[key].detach().to("cpu").contiguous()
        digest.update(f"{key}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().data)
    return digest.hexdigest()


class StateDictShapes:
    """Reads an architecture off a checkpoint's tensor shapes (the families' ``from_state_dict``).

    ``shape(key)`` is a tensor's shape (``CheckpointMismatchError`` naming the key when it is
    absent); ``count(prefix)`` the number of indexed modules ``prefix{i}.*`` (0 if none).
    """

    def __init__(self, state_dict: Mapping[str, torch.Tensor], family: str) -> None:
        self._state_dict = state_dict
        self._family = family

    def shape(self, key: str) -> tuple[int, ...]:
        if key not in self._state_dict:
            raise CheckpointMismatchError(
                f"cannot infer a {self._family} config: key {key!r} is missing", missing=[key]
            )
        return tuple(self._state_dict[key].shape)

    def count(self, prefix: str) -> int:
        pattern = re.compile(rf"^{re.escape(prefix)}(\d+)\.")
        indices = {int(m.group(1)) for key in self._state_dict if (m := pattern.match(key))}
        return max(indices) + 1 if indices else 0


def read_state_dict(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """Every tensor of a ``.safetensors`` checkpoint; ``ModelError`` for a file that is not one
    (a pickle, a zip, an empty or truncated file, a FIFO) or that changes while being read
    (read without a memory map: ``weights_file.py`` says why)."""
    return read_safetensors(path)


def load_strictly(
    make: Callable[[], ModuleT], state_dict: Mapping[str, torch.Tensor]
) -> tuple[ModuleT, str]:
    """The network ``make()`` builds, holding ``state_dict`` exactly (``CheckpointMismatchError``
    lists any missing, unexpected or wrongly shaped key), in eval mode, and the weights'
    fingerprint. The network is built on the meta device, so no memory is spent on a random init
    that the checkpoint overwrites."""
    with torch.device("meta"):
        model = make()
    check_state_dict(model, state_dict)
    fingerprint = weights_fingerprint(state_dict)
    model.load_state_dict(state_dict, strict=True, assign=True)
    return model.eval(), fingerprint
