"""Where map rebuilds run: inline (synchronous mapping) or on one worker thread (asynchronous).

Both modes go through a ``concurrent.futures.Future``, so the tracker handles a finished rebuild the
same way: ``take()`` hands over the result of a finished job exactly once (re-raising the job's
exception on the caller's thread), and the tracker swaps the new map in with one reference
assignment — readers see the old map or the new one, never a mix. At most one job is pending:
a rebuild always starts from the latest installed map, never from another rebuild in flight.

``discard()`` forgets the pending job (after ``reset()`` or a map load): the worker finishes it in
the background and its result is dropped. The worker thread is named ``kvtracker-mapper``.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import Generic, TypeVar

from kvtracker_sdk.errors import StateError

__all__ = ["Mapper"]

T = TypeVar("T")


class Mapper(Generic[T]):
    """Runs one rebuild job at a time, inline or on a worker thread."""

    def __init__(self, *, asynchronous: bool) -> None:
        self.asynchronous = asynchronous
        self._executor = (
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="kvtracker-mapper")
            if asynchronous
            else None
        )
        self._pending: Future[T] | None = None
        self._closed = False

    @property
    def pending(self) -> bool:
        """A job was submitted and its result not taken yet (running or finished)."""
        return self._pending is not None

    @property
    def running(self) -> bool:
        """A job is still computing."""
        pending = self._pending
        return pending is not None and not pending.done()

    def submit(self, job: Callable[[], T]) -> None:
        """Start ``job``; inline it runs to completion before this returns."""
        if self._closed:
            raise StateError("the mapper is closed")
        if self._pending is not None:
            raise StateError("a map rebuild is already pending; take() its result first")
        if self._executor is None:
            future: Future[T] = Future()
            try:
                future.set_result(job())
            except Exception as exc:  # handed to take(), like a worker's exception
                future.set_exception(exc)
            self._pending = future
        else:
            self._pending = self._executor.submit(job)

    def take(self, *, timeout: float | None = 0.0) -> T | None:
        """The finished job's result (once), or None if nothing finished within ``timeout``.

        ``timeout=0`` polls; ``None`` waits as long as it takes. Re-raises the job's exception.
        """
        pending = self._pending
        if pending is None:
            return None
        if not pending.done() and not wait([pending], timeout=timeout).done:
            return None
        self._pending = None
        return pending.result()  # re-raises the job's exception on this thread

    def wait(self, timeout: float | None) -> bool:
        """Wait (without taking it) until the job pending now has finished; True if it has, or if
        none is pending. Needs no lock: the tracker calls it without holding its own."""
        pending = self._pending
        return pending is None or wait([pending], timeout=timeout).done != set()

    def discard(self) -> None:
        """Forget the pending job; its result (or error) will never be taken."""
        self._pending = None

    def close(self) -> None:
        """Stop the worker after its current job (idempotent)."""
        self._closed = True
        self._pending = None
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
