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


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (2.33+): byte counts over every arena, as size_t."""

    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost"
        )
    ]  # fmt: skip


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


def heap_bytes() -> dict[str, int] | None:
    """The C heap as malloc sees it: ``in_use`` (bytes handed out, from the heaps and mapped on their own) and
    ``free`` (bytes the heaps keep free). A leak grows ``in_use``; fragmentation grows ``free`` and the resident
    size, not ``in_use``. None where the C library has no mallinfo2 (glibc before 2.33, musl, macOS)."""
    libc = _glibc()
    fn = getattr(libc, "mallinfo2", None) if libc is not None else None
    if fn is None:
        return None
    fn.restype = _MallInfo2
    info = fn()
    return {"in_use": int(info.uordblks + info.hblkhd), "free": int(info.fordblks)}
