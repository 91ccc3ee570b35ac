"""A worker's backends: each opened from its spec (weights by shared path) on first use, then
reused by every task the worker runs (weights never travel through a task queue or Ray's object
store). A manifest whose configs name several runtimes gives a worker one backend per runtime."""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.runs.backends import BackendSpec

if TYPE_CHECKING:
    from kvtracker_sdk.backends.base import Backend

__all__ = ["ModelCache"]


class ModelCache:
    """``get(spec)`` returns the one backend for ``spec`` (default: the cache's own ``spec``);
    thread-safe, each spec opened at most once. ``threads`` is given to a spec that sets none."""

    def __init__(self, spec: BackendSpec | None, *, threads: int | None = None) -> None:
        self.spec = spec
        self.threads = threads
        self.loads = 0  # how many times weights were read (tests check: once per spec at most)
        self._backends: dict[str, Backend] = {}
        self._lock = threading.Lock()

    def get(self, spec: BackendSpec | None = None) -> Backend:
        chosen = spec if spec is not None else self.spec
        if chosen is None:
            raise ConfigError("this task needs a model but the manifest names none")
        key = chosen.model_dump_json()
        with self._lock:
            backend = self._backends.get(key)
            if backend is None:
                backend = chosen.open(threads=self.threads)
                self._backends[key] = backend
                self.loads += 1
            return backend

    def close(self) -> None:
        with self._lock:
            backends, self._backends = list(self._backends.values()), {}
        for backend in backends:
            backend.close()
