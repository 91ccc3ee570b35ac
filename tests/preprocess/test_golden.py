"""Every key of ``../shared/golden/preprocess``: what the official pipelines feed each network.

Sizes must be equal and pixels within 1 uint8 level (the golden README's tolerance: OpenCV builds
may round differently); masks must be equal.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from safetensors.numpy import load_file

from kvtracker_sdk.preprocess import for_family
from tests.helpers import shared_path

PATCH = 14


@pytest.fixture(scope="module")
def golden() -> dict[str, np.ndarray]:
    return load_file(str(shared_path("golden", "preprocess", "preprocess.safetensors")))


@pytest.fixture(scope="module")
def sizes() -> dict[str, list[int]]:
    return json.loads(shared_path("golden", "preprocess", "sizes.json").read_text())


@pytest.fixture(scope="module")
def inputs() -> dict[str, np.ndarray]:
    """The golden README's inputs: TUM fr2/desk frames 0, 5, 10, a portrait and an odd crop."""
    folder: Path = shared_path("data", "tum_fr2_desk", "rgb")
    names = sorted(p.name for p in folder.iterdir())

    def read(index: int) -> np.ndarray:
        return cv2.cvtColor(cv2.imread(str(folder / names[index])), cv2.COLOR_BGR2RGB)

    frame0 = read(0)
    return {
        "frame0": frame0,
        "frame5": read(5),
        "frame10": read(10),
        "portrait": np.rot90(frame0),  # a view on purpose: preprocessing must accept it
        "odd": frame0[100:359, 20:621],
    }


def _as_image(stored: np.ndarray, height: int, width: int) -> list[np.ndarray]:
    """The golden array as [H, W, 3], read as labelled and, for the DA3 keys whose bytes are
    channel-first ([3, H, W] in memory under an [H, W, 3] label: how the DA3 golden was saved
    from the official tensor), channel-first. A wrong output matches neither reading."""
    readings = [stored]
    if stored.ndim == 3:
        readings.append(stored.reshape(3, height, width).transpose(1, 2, 0))
    return readings


def test_every_golden_key_is_reproduced(
    golden: dict[str, np.ndarray], sizes: dict[str, list[int]], inputs: dict[str, np.ndarray]
) -> None:
    assert len(sizes) == 38 and set(sizes) <= set(golden)
    failures = []
    for key, (height, width) in sorted(sizes.items()):
        family, resolution, name = key.split("/")
        pipeline = for_family(family)
        if name == "frame0_mask":
            source = golden["input/frame0_mask"].astype(bool)
            size = pipeline.model_size(source.shape, int(resolution), PATCH)
            ours = pipeline.resize_mask(source, size).astype(np.uint8)
        else:
            ours = pipeline.resize(inputs[name], int(resolution), PATCH).image
        if ours.shape[:2] != (height, width):
            failures.append(f"{key}: size {ours.shape[:2]} != {(height, width)}")
            continue
        worst = min(
            int(np.abs(ours.astype(np.int16) - ref.astype(np.int16)).max())
            for ref in _as_image(golden[key], height, width)
        )
        limit = 0 if name == "frame0_mask" else 1
        if worst > limit:
            failures.append(f"{key}: {worst} levels off")
    assert not failures, failures
