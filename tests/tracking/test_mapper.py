"""Mapper: inline and worker-thread rebuilds behind one interface."""

from __future__ import annotations

import threading

import pytest

from kvtracker_sdk.errors import StateError
from kvtracker_sdk.tracking.mapping.mapper import Mapper


def test_inline_job_runs_before_submit_returns_and_is_taken_once() -> None:
    mapper: Mapper[int] = Mapper(asynchronous=False)
    mapper.submit(lambda: 41 + 1)
    assert mapper.pending and not mapper.running
    assert mapper.take() == 42
    assert mapper.take() is None and not mapper.pending


def test_worker_job_runs_on_the_mapper_thread() -> None:
    mapper: Mapper[str] = Mapper(asynchronous=True)
    release = threading.Event()

    def job() -> str:
        release.wait(5)
        return threading.current_thread().name

    mapper.submit(job)
    assert mapper.take(timeout=0.0) is None  # still running: a poll returns nothing
    assert mapper.running
    release.set()
    name = mapper.take(timeout=5)
    assert name is not None and name.startswith("kvtracker-mapper")
    mapper.close()


@pytest.mark.parametrize("asynchronous", [False, True])
def test_job_errors_are_raised_by_take_on_the_callers_thread(asynchronous: bool) -> None:
    mapper: Mapper[int] = Mapper(asynchronous=asynchronous)

    def job() -> int:
        raise ValueError("backend failed")

    mapper.submit(job)
    with pytest.raises(ValueError, match="backend failed"):
        mapper.take(timeout=5)
    assert not mapper.pending  # the failed job is consumed
    mapper.close()


def test_one_job_at_a_time_and_discard() -> None:
    mapper: Mapper[int] = Mapper(asynchronous=False)
    mapper.submit(lambda: 1)
    with pytest.raises(StateError):
        mapper.submit(lambda: 2)
    mapper.discard()
    assert mapper.take() is None
    mapper.submit(lambda: 3)
    assert mapper.take() == 3


def test_close_waits_for_the_running_job_and_is_idempotent() -> None:
    mapper: Mapper[int] = Mapper(asynchronous=True)
    started, release, finished = threading.Event(), threading.Event(), threading.Event()

    def job() -> int:
        started.set()
        release.wait(120)
        finished.set()
        return 1

    mapper.submit(job)
    assert started.wait(120)
    closer = threading.Thread(target=mapper.close)
    closer.start()
    release.set()
    closer.join(timeout=120)
    assert not closer.is_alive() and finished.is_set() and not mapper.pending
    mapper.close()  # a second close returns at once
    with pytest.raises(StateError, match="closed"):  # nothing runs after close
        mapper.submit(lambda: 2)
