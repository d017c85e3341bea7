"""Prometheus metrics of one service instance, in its own registry (never the process-global one)."""

from __future__ import annotations

import sys
from collections.abc import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from .allocator import heap_bytes
from .bandwidth import BandwidthReport

_LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class _BandwidthCollector:
    """Per-peer bytes, messages, rates and ratios, read from the bandwidth meter at scrape time."""

    def __init__(self, report: Callable[[], BandwidthReport]):
        self._report = report

    def collect(self):
        rep = self._report()
        msgs = CounterMetricFamily("bbalign_messages", "Messages received per peer", labels=["peer"])
        byts = CounterMetricFamily("bbalign_bytes_received", "Bytes received per peer", labels=["peer"])
        parts = CounterMetricFamily("bbalign_frame_bytes", "Bytes of decoded frames by part", labels=["peer", "part"])
        rate = GaugeMetricFamily("bbalign_bandwidth_kbit_s", "Receive rate over the sliding window", labels=["peer"])
        ratio = GaugeMetricFamily(
            "bbalign_ratio_vs_points", "Frame bytes / raw point bytes (16 B/point)", labels=["peer"]
        )
        for peer, bw in rep.peers.items():
            msgs.add_metric([peer], bw.messages)
            byts.add_metric([peer], bw.bytes)
            for part, n in bw.by_part.model_dump().items():
                parts.add_metric([peer, part], n)
            rate.add_metric([peer], bw.kbit_s)
            if bw.ratio_vs_points is not None:
                ratio.add_metric([peer], bw.ratio_vs_points)
        yield from (msgs, byts, parts, rate, ratio)


class _HeapCollector:
    """The C heap's bytes in use and kept free (glibc's mallinfo2) and the Python objects' memory blocks, read at
    scrape time: a leak shows in the bytes in use or the blocks, fragmentation in the free bytes
    (server/allocator.py). Python's small objects live in its own arenas, outside malloc's count."""

    def collect(self):
        yield GaugeMetricFamily("bbalign_python_blocks", "Memory blocks Python has allocated", sys.getallocatedblocks())
        heap = heap_bytes()
        if heap is None:
            return
        g = GaugeMetricFamily("bbalign_heap_bytes", "C heap bytes by state (glibc mallinfo2)", labels=["state"])
        for state, n in heap.items():
            g.add_metric([state], n)
        yield g


class Metrics:
    def __init__(
        self,
        bandwidth: Callable[[], BandwidthReport],
        ego_frames: Callable[[], int],
        queued: Callable[[], int],
        peers: Callable[[], int] = lambda: 0,
        intake: Callable[[], int] = lambda: 0,
    ):
        self.registry = r = CollectorRegistry(auto_describe=True)
        self._counters(r)
        self.latency = Histogram(
            "bbalign_result_latency_seconds",
            "Message received -> result ready",
            ["door"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
        self.engine = Histogram(
            "bbalign_engine_seconds", "Engine time by step", ["step"], buckets=_LATENCY_BUCKETS, registry=r
        )
        Gauge("bbalign_ego_cache_frames", "Ego frames in the cache", registry=r).set_function(ego_frames)
        Gauge("bbalign_queued_jobs", "Frames and requests waiting for a worker", registry=r).set_function(queued)
        Gauge(
            "bbalign_peers_tracked", "Senders tracked (authenticated, valid frames, not idle)", registry=r
        ).set_function(peers)
        Gauge("bbalign_intake_messages", "Raw messages waiting for the gate", registry=r).set_function(intake)
        self.door_throttled = Gauge(
            "bbalign_door_throttled_seconds",
            "Time the Zenoh door slept because it had spent its CPU share (a flood pushed back on its senders)",
            registry=r,
        )
        r.register(_BandwidthCollector(bandwidth))
        r.register(_HeapCollector())

    def _counters(self, r: CollectorRegistry) -> None:
        self.frames = Counter("bbalign_frames_received", "Frames received", ["door", "kind"], registry=r)
        self.dropped = Counter(
            "bbalign_frames_dropped",
            "Frames never run: replaced by a newer one (latest-only "
            "queues), pushed out of the full intake, or queued at shutdown; peer "
            "'(unverified)': before the gate checked them",
            ["peer"],
            registry=r,
        )
        self.intake_dropped = Counter(
            "bbalign_intake_dropped",
            "Messages pushed out of a full intake lane before the gate (ego, signed, unverified)",
            ["lane"],
            registry=r,
        )
        self.door_refused = Counter(
            "bbalign_door_refused",
            "Zenoh stream messages refused at the door (the callback), never queued: what the gate would refuse "
            "for certain (junk, unsigned, unknown keys, copies, old frames, bad signatures); also counted in "
            "bbalign_frames_rejected_total",
            ["error"],
            registry=r,
        )
        self.rejected = Counter(
            "bbalign_frames_rejected",
            "Messages refused, by error (too_large, undecodable, "
            "invalid, unauthenticated, forbidden, replayed, overloaded, ...)",
            ["door", "error"],
            registry=r,
        )
        self.refusal_notices = Counter(
            "bbalign_refusal_notices",
            "Refusals of signed stream frames told to their sender on its results key, by error",
            ["error"],
            registry=r,
        )
        self.alignments = Counter(
            "bbalign_alignments", "Alignments run, by outcome (success or reason)", ["peer", "outcome"], registry=r
        )

    def forget_peer(self, peer: str, outcomes: set[str]) -> None:
        """Drop an evicted peer's labels (label sets stay bounded by the peers tracked)."""
        for counter, labels in ((self.dropped, [(peer,)]), (self.alignments, [(peer, o) for o in outcomes])):
            for values in labels:
                try:
                    counter.remove(*values)
                except KeyError:
                    pass

    def exposition(self) -> bytes:
        return generate_latest(self.registry)
