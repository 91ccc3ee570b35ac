"""Seeded edits of an export folder's ``manifest.json`` that keep every sha256 valid: each
changes a claim the backend relies on (weights size, layout, config with its hash kept, graph
specs, patch size, extra tokens, graph files swapped between roles).

Shared by ``test_onnx_claims.py`` and ``benchmarks/fuzz_inputs.py``.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from copy import deepcopy
from pathlib import Path
from typing import Any

import numpy as np

Edit = tuple[str, dict[str, Any]]


def _numeric_paths(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _numeric_paths(v, (*prefix, k))]
    if isinstance(value, list):
        return [p for i, v in enumerate(value) for p in _numeric_paths(v, (*prefix, i))]
    if isinstance(value, int | float) and not isinstance(value, bool):
        return [prefix]
    return []


def _get(document: Any, path: tuple[Any, ...]) -> Any:
    for key in path:
        document = document[key]
    return document


def _set(document: Any, path: tuple[Any, ...], value: Any) -> None:
    _get(document, path[:-1])[path[-1]] = value


def edited_manifests(manifest: dict[str, Any], count: int, seed: int) -> Iterator[Edit]:
    """``count`` seeded (name, edited manifest) pairs, cycling through the kinds of edit."""
    rng = np.random.default_rng(seed)
    roles = sorted(manifest["graphs"])
    config_paths = _numeric_paths(manifest["config"])
    kinds = ["weights_bytes", "layout", "config", "swap", "spec", "patch_size", "extra_tokens",
             "drop_role"]
    for index in range(count):
        kind = kinds[index % len(kinds)]
        edited = deepcopy(manifest)
        if kind == "weights_bytes":
            edited["weights_bytes"] += int(rng.choice([-1, 1, 4096, -manifest["weights_bytes"]]))
        elif kind == "layout":
            field = ["num_heads", "head_dim", "block_indices"][rng.integers(3)]
            if field == "block_indices":
                edited["layout"][field] = edited["layout"][field][:-1]
            else:
                edited["layout"][field] *= int(rng.choice([2, 4]))
        elif kind == "config":
            path = config_paths[rng.integers(len(config_paths))]
            old = _get(edited["config"], path)
            _set(edited["config"], path, old + 1 if isinstance(old, int) else old * 1.5 + 0.1)
        elif kind == "swap":
            first, second = rng.choice(roles, size=2, replace=False)
            graphs = edited["graphs"]
            graphs[first]["file"], graphs[second]["file"] = graphs[second]["file"], graphs[first]["file"]
        elif kind == "spec":
            role = roles[rng.integers(len(roles))]
            tensors = edited["graphs"][role]["inputs" if rng.random() < 0.5 else "outputs"]
            tensor = tensors[rng.integers(len(tensors))]
            fixed = [i for i, d in enumerate(tensor["shape"]) if isinstance(d, int)]
            if fixed and rng.random() < 0.6:
                tensor["shape"][fixed[rng.integers(len(fixed))]] *= 2
            else:
                tensor["name"] += "_renamed"
        elif kind == "patch_size":
            edited["patch_size"] = int(rng.choice([7, 16, 28]))
        elif kind == "extra_tokens":
            edited["extra_tokens_per_frame"] += int(rng.choice([1, 2, -1]))
        else:
            del edited["graphs"][roles[rng.integers(len(roles))]]
            edited["sha256"] = {k: v for k, v in edited["sha256"].items()
                                if k in {g["file"] for g in edited["graphs"].values()}
                                or k == edited["weights_file"]}
        yield f"{index}-{kind}", edited


def edited_folder(source: Path, folder: Path, manifest: dict[str, Any]) -> Path:
    """``folder``: the export ``source`` (files hard-linked: no copy of the weights) with
    ``manifest`` written as its manifest.json."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for item in source.iterdir():
        if item.name != "manifest.json":
            os.link(item, folder / item.name)
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder
