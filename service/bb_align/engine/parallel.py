"""The engine's few parallel sections share small thread pools (OpenCV and numpy release the GIL in the
heavy calls: inverse DFTs, gathers, histograms)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
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


def run_parts(fn: Callable[[T], R], parts: Sequence[T]) -> list[R]:
    """fn over each part, in order; on a shared pool when there is more than one part."""
    if len(parts) <= 1:
        return [fn(p) for p in parts]
    return list(_pool(len(parts)).map(fn, parts))
