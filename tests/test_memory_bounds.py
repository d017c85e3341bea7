"""Structures the service keeps per sender or per message stay at their bound however many messages pass, and
the allocator settings the service applies at start are applied (glibc) or skipped (elsewhere)."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys

import pytest

from bb_align.server.allocator import _glibc, configure_malloc, heap_bytes
from bb_align.server.bandwidth import BandwidthMeter
from bb_align.server.metrics import Metrics
from bb_align.server.settings import Settings


class _Clock:
    def __init__(self, t: float):
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_bandwidth_window_stays_at_its_bound_when_nobody_reads_the_rate():
    """30 minutes of 3 senders at 10 Hz, the rate never read (no /metrics scrape): each tally keeps only the
    buckets of its window. Hand count: messages at t = 1000.05 + 0.1 k fall in bucket j = 10000 + k (0.1 s long);
    at the last message (bucket N) a bucket stays while its end j*0.1 + 0.1 is after now - 5 s = (N - 50)*0.1 +
    0.05, i.e. j >= N - 50: 51 buckets."""
    clock = _Clock(1000.05)
    meter = BandwidthMeter(window_s=5.0, clock=clock)
    peers = ("car1", "car2", "car3")
    for k in range(18_000):
        clock.t = 1000.05 + 0.1 * k
        for p in peers:
            meter.record_message(p, 1000)
    tallies = [meter._peers[p] for p in peers] + [meter._total]  # the structure itself, not a timing
    assert [len(t.window) for t in tallies] == [51, 51, 51, 51]
    # and the rate still counts exactly those buckets: 51 x 1000 B per sender over 5 s, three senders in the total
    rep = meter.report()
    assert rep.peers["car2"].kbit_s == pytest.approx(51 * 1000 * 8 / 1000 / 5.0)
    assert rep.total.kbit_s == pytest.approx(3 * 51 * 1000 * 8 / 1000 / 5.0)
    assert rep.total.messages == 3 * 18_000 and rep.peers["car1"].bytes == 18_000 * 1000


# ---- glibc malloc settings (server/allocator.py), each in a fresh process: they act on the process's allocator --
_PROBE = """
import ctypes, os, sys, tempfile, threading
from bb_align.server.allocator import _MallInfo2 as MI2, configure_malloc
arena_max, mmap_kb = (None if v == "-" else int(v) for v in sys.argv[1:3])
print(sorted(configure_malloc(arena_max, mmap_kb)))
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
libc.fopen.restype = ctypes.c_void_p
libc.mallinfo2.restype = MI2
# a 4 MiB block freed, then another: is the second one mapped on its own?
libc.free(libc.malloc(4 << 20))
before = libc.mallinfo2().hblks
p = libc.malloc(4 << 20)
print(libc.mallinfo2().hblks - before)
libc.free(p)
# six threads, each holding a malloc'd block at once: how many heaps (arenas) does malloc_info list?
barrier, held = threading.Barrier(7), []
def hold():
    held.append(libc.malloc(1000))
    barrier.wait()
    barrier.wait()
threads = [threading.Thread(target=hold) for _ in range(6)]
for t in threads:
    t.start()
barrier.wait()
path = tempfile.mktemp()
fp = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, ctypes.c_void_p(fp))
libc.fclose(ctypes.c_void_p(fp))
barrier.wait()
print(open(path).read().count("<heap nr="))
os.remove(path)
"""


def _probe(arena_max: str, mmap_kb: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, arena_max, mmap_kb], capture_output=True, text=True, env=env, timeout=60
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.split("\n")[:3]


@pytest.mark.skipif(_glibc() is None, reason="glibc's malloc settings")
def test_glibc_defaults_adapt_the_threshold_and_make_an_arena_per_thread():
    """The behaviour the settings change, shown on glibc's defaults: a freed 4 MiB mapping raises the mmap
    threshold, so the next 4 MiB block comes from a heap (0 new mappings); each of 6 threads gets an arena of
    its own (main + 6 = 7 heaps; glibc allows 8 per core)."""
    assert _probe("-", "-") == ["[]", "0", "7"]


@pytest.mark.skipif(_glibc() is None, reason="glibc's malloc settings")
def test_service_malloc_settings_map_large_blocks_and_cap_the_arenas():
    """With the service's defaults (2 arenas, 256 KiB): the second 4 MiB block is mapped on its own again (given
    back when freed) and the six threads share the 2 arenas."""
    s = Settings()
    assert (s.malloc_arena_max, s.malloc_mmap_threshold_kb) == (2, 256)
    applied = "['MALLOC_ARENA_MAX', 'MALLOC_MMAP_THRESHOLD_']"
    assert _probe(str(s.malloc_arena_max), str(s.malloc_mmap_threshold_kb)) == [applied, "1", "2"]


@pytest.mark.skipif(_glibc() is None, reason="glibc's malloc settings")
def test_an_operators_malloc_environment_is_kept(monkeypatch):
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    assert configure_malloc(None, None) == {}  # nothing asked, nothing set
    assert list(configure_malloc(2, None)) == []  # the operator's MALLOC_ARENA_MAX stands


@pytest.mark.skipif(getattr(_glibc(), "mallinfo2", None) is None, reason="glibc 2.33+'s mallinfo2")
def test_heap_bytes_count_a_known_block_and_reach_the_metrics():
    """A 64 MiB block from malloc shows in the bytes in use while it is held and leaves them when freed; the
    service's /metrics text carries both states and Python's block count."""
    libc = _glibc()
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    before = heap_bytes()["in_use"]
    p = libc.malloc(64 << 20)
    held = heap_bytes()["in_use"]
    libc.free(p)
    after = heap_bytes()["in_use"]
    assert held - before >= 64 << 20 and held - before < (64 << 20) + (1 << 20)
    assert abs(after - before) < 1 << 20
    text = Metrics(bandwidth=BandwidthMeter().report, ego_frames=lambda: 0, queued=lambda: 0).exposition().decode()
    for name in ('bbalign_heap_bytes{state="in_use"}', 'bbalign_heap_bytes{state="free"}', "bbalign_python_blocks "):
        assert name in text
