"""A worker's model: loaded from the shared path on first use, then reused by every task the
worker runs (weights never travel through a task queue or Ray's object store)."""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.scale.manifest import ModelSpec

if TYPE_CHECKING:
    from kvtracker_sdk.backends.base import Backend

__all__ = ["ModelCache"]


class ModelCache:
    """``get()`` returns the one backend for ``spec`` (thread-safe; loads at most once)."""

    def __init__(self, spec: ModelSpec | None) -> None:
        self.spec = spec
        self.loads = 0  # how many times weights were read (tests check it stays at most 1)
        self._backend: Backend | None = None
        self._lock = threading.Lock()

    def get(self) -> Backend:
        with self._lock:
            if self._backend is None:
                if self.spec is None:
                    raise ConfigError("this task needs a model but the manifest names none")
                from kvtracker_sdk.backends.torch_backend import TorchBackend

                self._backend = TorchBackend.from_pretrained(self.spec.weights, dtype=self.spec.dtype)
                self.loads += 1
            return self._backend

    def close(self) -> None:
        with self._lock:
            if self._backend is not None:
                self._backend.close()
                self._backend = None
