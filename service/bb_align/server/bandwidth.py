"""Bandwidth accounting: what each peer's frames cost on the air, against raw points and a raw BV image.

Every received message counts (bytes, messages, a sliding-window kbit/s) the moment it arrives, dropped or not;
decoded frames also count by part (PNG, boxes, header) and against what the same sweep would cost as raw points
(16 B per point: float32 x, y, z, intensity; from the sender's ``num_points``) and as an uncompressed uint8 BV
image (H x W bytes).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import deque
from dataclasses import dataclass

import msgpack
from pydantic import BaseModel, Field

from bb_align.protocol import MSGPACK, Frame

RAW_POINT_BYTES = 16
_BUCKET_S = 0.1  # the sliding window counts bytes in buckets this long


@dataclass(frozen=True)
class FrameBytes:
    """One decoded frame's size, split by part, and its raw equivalents."""

    total: int
    png: int
    boxes: int
    header: int
    raw_points: int | None  # 16 B x num_points, None when the sender did not say
    raw_bev: int  # H x W bytes

    @classmethod
    def of(cls, frame: Frame, total: int, encoding: str = MSGPACK) -> FrameBytes:
        box_part = [frame.boxes, frame.scores] if frame.scores is not None else frame.boxes
        if encoding == MSGPACK:
            png = len(frame.png)
            boxes = len(msgpack.packb(box_part)) if frame.boxes else 0
        else:  # JSON: base64 text
            png = 4 * math.ceil(len(frame.png) / 3)
            boxes = len(json.dumps(box_part, separators=(",", ":"))) if frame.boxes else 0
        side = round(2 * frame.bev.range_m / frame.bev.resolution_m)
        raw_points = None if frame.num_points is None else RAW_POINT_BYTES * frame.num_points
        return cls(total, png, boxes, max(0, total - png - boxes), raw_points, side * side)


class BytesByPart(BaseModel):
    png: int = 0
    boxes: int = 0
    header: int = 0


class PeerBandwidth(BaseModel):
    messages: int = Field(0, description="messages received (dropped and refused ones included)")
    bytes: int = Field(0, description="bytes received")
    kbit_s: float = Field(0.0, description="rate over the last window_s seconds")
    frames_decoded: int = 0
    bytes_per_frame: float | None = Field(None, description="mean size of a decoded frame")
    by_part: BytesByPart = Field(default_factory=BytesByPart, description="decoded frames, by part")
    raw_points_bytes: int = Field(0, description="what the decoded frames would cost as raw points")
    ratio_vs_points: float | None = Field(None, description="frame bytes / raw point bytes (frames with a count)")
    raw_bev_bytes: int = 0
    ratio_vs_raw_bev: float | None = Field(None, description="frame bytes / uncompressed uint8 BV image bytes")


class BandwidthReport(BaseModel):
    window_s: float
    total: PeerBandwidth
    peers: dict[str, PeerBandwidth]


class _Tally:
    def __init__(self) -> None:
        self.messages = self.bytes = self.frames = self.frame_bytes = 0
        self.png = self.boxes = self.header = 0
        self.raw_points = self.bytes_with_points = self.raw_bev = 0
        self.window: deque[tuple[float, int]] = deque()

    def add_message(self, nbytes: int, now: float, window_s: float) -> None:
        self.messages += 1
        self.bytes += nbytes
        bucket = math.floor(now / _BUCKET_S) * _BUCKET_S  # bounded memory under any message rate
        if self.window and self.window[-1][0] == bucket:
            self.window[-1] = (bucket, self.window[-1][1] + nbytes)
        else:
            self.window.append((bucket, nbytes))
            # Old buckets go as new ones come, not only when someone reads the rate: a service nobody scrapes
            # kept one bucket per 0.1 s per sender for ever (measured in the tracking soak).
            self._expire(now, window_s)

    def _expire(self, now: float, window_s: float) -> None:
        while self.window and self.window[0][0] + _BUCKET_S <= now - window_s:
            self.window.popleft()

    def add_frame(self, fb: FrameBytes) -> None:
        self.frames += 1
        self.frame_bytes += fb.total
        self.png, self.boxes, self.header = self.png + fb.png, self.boxes + fb.boxes, self.header + fb.header
        self.raw_bev += fb.raw_bev
        if fb.raw_points:
            self.raw_points += fb.raw_points
            self.bytes_with_points += fb.total

    def report(self, now: float, window_s: float) -> PeerBandwidth:
        self._expire(now, window_s)
        in_window = sum(n for _, n in self.window)
        return PeerBandwidth(
            messages=self.messages,
            bytes=self.bytes,
            kbit_s=in_window * 8 / 1000 / window_s,
            frames_decoded=self.frames,
            bytes_per_frame=self.frame_bytes / self.frames if self.frames else None,
            by_part=BytesByPart(png=self.png, boxes=self.boxes, header=self.header),
            raw_points_bytes=self.raw_points,
            ratio_vs_points=self.bytes_with_points / self.raw_points if self.raw_points else None,
            raw_bev_bytes=self.raw_bev,
            ratio_vs_raw_bev=self.frame_bytes / self.raw_bev if self.raw_bev else None,
        )


class BandwidthMeter:
    """Thread-safe per-peer and total tallies. ``clock`` is injectable for tests."""

    def __init__(self, window_s: float = 5.0, clock=time.monotonic):
        self.window_s = window_s
        self._clock = clock
        self._lock = threading.Lock()
        self._total = _Tally()
        self._peers: dict[str, _Tally] = {}

    def record_message(self, peer_id: str, nbytes: int) -> None:
        """A message arrived (call once per message, before it can be dropped)."""
        now = self._clock()
        with self._lock:
            self._peers.setdefault(peer_id, _Tally()).add_message(nbytes, now, self.window_s)
            self._total.add_message(nbytes, now, self.window_s)

    def record_frame(self, peer_id: str, fb: FrameBytes) -> None:
        """A message decoded into a valid frame."""
        with self._lock:
            self._peers.setdefault(peer_id, _Tally()).add_frame(fb)
            self._total.add_frame(fb)

    def forget(self, peer_id: str) -> None:
        """Drop a peer's tally (an evicted peer); the total keeps its bytes."""
        with self._lock:
            self._peers.pop(peer_id, None)

    def peer(self, peer_id: str) -> PeerBandwidth | None:
        now = self._clock()
        with self._lock:
            tally = self._peers.get(peer_id)
            return None if tally is None else tally.report(now, self.window_s)

    def report(self) -> BandwidthReport:
        now = self._clock()
        with self._lock:
            return BandwidthReport(
                window_s=self.window_s,
                total=self._total.report(now, self.window_s),
                peers={p: t.report(now, self.window_s) for p, t in sorted(self._peers.items())},
            )
