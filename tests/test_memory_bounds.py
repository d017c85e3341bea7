"""Structures the service keeps per sender or per message stay at their bound however many messages pass, and
the allocator settings the service applies at start are applied (glibc) or skipped (elsewhere)."""

from __future__ import annotations

import pytest

from bb_align.server.bandwidth import BandwidthMeter


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
