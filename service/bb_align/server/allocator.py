"""The service's C heap: two glibc malloc settings that keep its resident size flat over hours.

Measured in the tracking soak (docs/tracking.md, "RSS after warm-up"): after warm-up the Python objects
(gc counts, tracemalloc) and the bytes malloc had handed out (mallinfo2 ``uordblks``) were flat, while the
resident size grew with the *free* bytes glibc kept in its heaps (``fordblks``). Two glibc defaults make that:

- the mmap threshold adapts: once a large block (a filter response, a decoded image, a few MB) is freed, blocks
  up to that size come from the heaps instead of their own mapping, and the heaps keep up to twice that size free
  at their top; big short-lived arrays interleaved with longer-lived ones leave holes the heaps never give back.
  A fixed threshold (setting it turns the adaptation off) maps every block from ``mmap_threshold_kb`` up on its
  own and returns it to the system when it is freed;
- one arena per thread up to 8 per core (Zenoh alone runs over a hundred receive threads here): each arena keeps
  its own free memory. A couple are enough for two engine workers.

Applied at start (``bb-align serve``), before any thread exists: glibc only limits arenas it has not made yet.
An operator's ``MALLOC_ARENA_MAX`` / ``MALLOC_MMAP_THRESHOLD_`` in the environment is kept. Other C libraries
(musl, macOS): nothing is changed.
"""

from __future__ import annotations

import ctypes
import logging
import os

log = logging.getLogger("bb_align.server")

M_MMAP_THRESHOLD = -3  # glibc malloc.h
M_ARENA_MAX = -8


def _glibc() -> ctypes.CDLL | None:
    """The process's own C library when it is glibc (it has gnu_get_libc_version), else None."""
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # noqa: B018 (only glibc has it)
        return libc
    except (OSError, AttributeError):
        return None


def configure_malloc(arena_max: int | None, mmap_threshold_kb: int | None) -> dict[str, int]:
    """Set glibc's arena limit and a fixed mmap threshold (None: leave glibc's default); returns what was set,
    by its glibc environment name. Call it before the process starts its threads."""
    libc = _glibc()
    if libc is None:
        return {}
    applied = {}
    for env, param, value in (
        ("MALLOC_ARENA_MAX", M_ARENA_MAX, arena_max),
        ("MALLOC_MMAP_THRESHOLD_", M_MMAP_THRESHOLD, None if mmap_threshold_kb is None else mmap_threshold_kb * 1024),
    ):
        if value is None or env in os.environ:
            continue
        if libc.mallopt(param, ctypes.c_int(value)) == 1:
            applied[env] = value
        else:
            log.warning("glibc refused mallopt(%s=%d)", env, value)
    return applied
