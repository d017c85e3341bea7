"""The engine's few parallel sections share small thread pools (OpenCV and numpy release the GIL in the
heavy calls: inverse DFTs, gathers, histograms). ``metered`` counts the CPU a call costs, its parts on the pools
included: a caller that shares the machine fairly (the service's scheduler) charges a job what it used, not its
wall time (an acquisition keeps two cores busy, a tracked frame mostly one)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from functools import lru_cache
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


@lru_cache(maxsize=4)
def _pool(threads: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=threads, thread_name_prefix="bb-align-engine")


def contiguous(items: Sequence[T], parts: int) -> list[Sequence[T]]:
    """``items`` cut into at most ``parts`` contiguous, non-empty slices of near-equal length, in order."""
    bounds = [round(i * len(items) / max(1, min(parts, len(items)))) for i in range(min(parts, len(items)) + 1)]
    return [items[lo:hi] for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]


class CpuMeter:
    """CPU seconds of the thread that opened it (``metered``) and of the pool parts it ran, since it opened."""

    def __init__(self):
        self._start, self._parts, self._lock = time.thread_time(), 0.0, threading.Lock()

    def add(self, seconds: float) -> None:
        with self._lock:
            self._parts += seconds

    @property
    def seconds(self) -> float:
        with self._lock:
            return time.thread_time() - self._start + self._parts


_local = threading.local()


@contextmanager
def metered() -> Iterator[CpuMeter]:
    """Count the CPU this thread spends inside the block, with the pool parts it runs (``run_parts``)."""
    meter, outer = CpuMeter(), getattr(_local, "meter", None)
    _local.meter = meter
    try:
        yield meter
    finally:
        _local.meter = outer


def run_parts(fn: Callable[[T], R], parts: Sequence[T]) -> list[R]:
    """fn over each part, in order: the first on the calling thread, the others on a shared pool. The pool is
    shared by every caller (the service's workers): a caller that only waited for its parts sat idle while they
    queued behind another caller's, and at 8 peers the workers used 1.6 of the 2 cores with frames waiting."""
    if len(parts) <= 1:
        return [fn(p) for p in parts]
    meter = getattr(_local, "meter", None)

    def counted(part: T) -> R:
        t0 = time.thread_time()
        try:
            return fn(part)
        finally:
            meter.add(time.thread_time() - t0)

    pool = _pool(len(parts))
    futures = [pool.submit(fn if meter is None else counted, p) for p in parts[1:]]
    first = fn(parts[0])  # counted by the caller's own thread time
    return [first, *(f.result() for f in futures)]
