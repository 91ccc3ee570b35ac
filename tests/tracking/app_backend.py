"""A backend written the way an app writes one: outside the package, with its own model family.

``AcmeBackend`` is an app's runtime for a model the SDK has never heard of ("acme-depth"). Its
network here is the SDK's simulated one (so poses have a known truth), but everything the tracker
sees is the app's: its own ``BackendInfo`` (runtime, model, family, fingerprint) and, when asked,
its own preprocessing. Nothing in kvtracker_sdk names this family.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from kvtracker_sdk.backends.base import BackendInfo, HeadSet, KVCache, MapResult, TrackResult
from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.preprocess import PI3_KVTRACKER, Preprocessing

# the app's pipeline: Pi3's sizing under the app's own name (what its saved maps record)
ACME_PREPROCESSING = replace(PI3_KVTRACKER, name="acme-resize-v1")


class AcmeBackend:
    """The Backend protocol, nothing more: ``info``, ``map``, ``track``, ``close`` (and, when
    ``declare_preprocessing``, a ``preprocessing`` attribute)."""

    def __init__(self, network: SimulatedBackend, *, family: str,
                 declare_preprocessing: bool = False) -> None:
        self._network = network
        self._info = replace(network.info, backend="acme-runtime", model="acme-depth-s",
                             family=family)
        if declare_preprocessing:
            self.preprocessing: Preprocessing = ACME_PREPROCESSING
        self.closed = False

    @property
    def info(self) -> BackendInfo:
        return self._info

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        return self._network.map(images, masks)

    def track(self, image: np.ndarray, cache: KVCache, *,
              heads: HeadSet = HeadSet.CONFIDENCE) -> TrackResult:
        return self._network.track(image, cache, heads=heads)

    def close(self) -> None:
        self.closed = True
