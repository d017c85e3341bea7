"""The ego-frame cache: the last K ego frames, each with its engine features computed once.

An entry is added as soon as its frame is decoded and becomes ready when a worker has prepared it, so a peer
frame that arrives together with the ego frame of the same instant waits for those features instead of taking
an older frame.
"""

from __future__ import annotations

import threading
from collections import deque

from ..pipeline import PreparedFrame
from ..wire import Frame


class EgoEntry:
    def __init__(self, frame: Frame):
        self.frame = frame
        self.prepared: PreparedFrame | None = None
        self._done = threading.Event()

    @property
    def stamp(self) -> float:
        return self.frame.stamp

    def set(self, prepared: PreparedFrame | None) -> None:
        """Features computed (or None: preparation failed, the entry is useless)."""
        self.prepared = prepared
        self._done.set()

    def wait(self, timeout: float) -> PreparedFrame | None:
        self._done.wait(timeout)
        return self.prepared


class EgoCache:
    def __init__(self, size: int):
        self._entries: deque[EgoEntry] = deque(maxlen=size)
        self._lock = threading.Lock()

    def add(self, frame: Frame) -> EgoEntry:
        entry = EgoEntry(frame)
        with self._lock:
            self._entries.append(entry)
        return entry

    def remove(self, entry: EgoEntry) -> None:
        with self._lock:
            if entry in self._entries:
                self._entries.remove(entry)

    def nearest(self, stamp: float) -> EgoEntry | None:
        """The entry nearest in time to ``stamp`` (the newer one on a tie); None when the cache is empty."""
        with self._lock:
            entries = list(self._entries)
        best = None
        for e in entries:  # arrival order, so '<=' prefers the later of equally near frames
            if best is None or abs(e.stamp - stamp) <= abs(best.stamp - stamp):
                best = e
        return best

    def __len__(self) -> int:
        with self._lock:
            return sum(1 for e in self._entries if e.prepared is not None)

    def stamps(self) -> list[float]:
        with self._lock:
            return [e.stamp for e in self._entries]
