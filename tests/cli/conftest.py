"""Fixtures of the CLI tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers import shared_path


@pytest.fixture(scope="session")
def golden_weights() -> Path:
    """The small Pi3 checkpoint with the official key layout (random weights)."""
    return shared_path("golden", "pi3", "weights.safetensors")


SIMULATED_FRAMES = 24  # frames of the simulated orbit written as PNGs for `kvtracker track`
SIMULATED_SIZE = (196, 252)  # Pi3's model resolution of d = 224 for 4:3 frames: no resize


@pytest.fixture(scope="module")
def simulated_frames(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of the simulated orbit's frames (lossless PNG: the simulated backend reads each
    frame's index from its pixels), for ``kvtracker track`` runs without a network."""
    import cv2

    from kvtracker_sdk.backends.simulated import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import orbit

    folder = tmp_path_factory.mktemp("simulated-frames")
    backend = SimulatedBackend(orbit(SIMULATED_FRAMES))
    for frame in backend.frames(SIMULATED_SIZE, textured=False):
        cv2.imwrite(str(folder / f"{frame.index:03d}.png"), frame.image[..., ::-1])
    return folder


@pytest.fixture
def simulated_backend(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """``kvtracker track`` gets a simulated backend over ``simulated_frames``' orbit instead of
    loading weights; the returned list records each opening (its weights argument)."""
    from kvtracker_sdk.backends.simulated import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import orbit

    opened: list[str] = []

    def open_backend(kind: object, weights: str, **_: object) -> SimulatedBackend:
        opened.append(str(weights))
        return SimulatedBackend(orbit(SIMULATED_FRAMES))

    monkeypatch.setattr("kvtracker_sdk.cli.track.open_backend", open_backend)
    return opened
