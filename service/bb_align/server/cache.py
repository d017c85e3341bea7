"""The ego-frame cache: the last K ego frames, each with its engine features computed at most once.

An ego frame enters the cache as soon as it is decoded (cheap, done with priority), so a peer frame always finds
the ego frame nearest in time even while the engine is busy. Its features are computed once, by whichever comes
first: the eager job queued for the newest ego frame, or the first peer frame that needs them (later users wait
for that one computation instead of repeating it).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable

import numpy as np

from bb_align.engine.bev import BevImage
from bb_align.engine.frame import PreparedFrame
from bb_align.protocol import Frame


class EgoEntry:
    def __init__(self, frame: Frame, bev: BevImage):
        self.frame = frame
        self.bev = bev
        self._prepared: PreparedFrame | None = None
        self._lock = threading.Lock()

    @property
    def stamp(self) -> float:
        return self.frame.stamp

    @property
    def ready(self) -> bool:
        return self._prepared is not None

    @property
    def busy(self) -> bool:
        """Whether another thread is computing the features right now (whoever asks would wait for it)."""
        return self._prepared is None and self._lock.locked()

    def features(self, prepare: Callable[[EgoEntry], PreparedFrame], wait: bool = True) -> PreparedFrame | None:
        """The entry's features, computed by the first caller; concurrent callers wait for that result, or with
        ``wait=False`` return None at once (another thread is computing them)."""
        if not self._lock.acquire(blocking=wait):
            return None
        try:
            if self._prepared is None:
                self._prepared = prepare(self)
            return self._prepared
        finally:
            self._lock.release()


class EgoCache:
    def __init__(self, size: int):
        self._entries: deque[EgoEntry] = deque(maxlen=size)
        self._lock = threading.Lock()
        self._added = threading.Condition(self._lock)

    def add(self, frame: Frame, bev: BevImage) -> EgoEntry:
        entry = EgoEntry(frame, bev)
        with self._lock:
            self._entries.append(entry)
            self._added.notify_all()
        return entry

    def wait_for(self, stamp: float, same_sweep_s: float, timeout: float) -> bool:
        """Wait at most ``timeout`` seconds until the ego stream has reached ``stamp``: an entry stamped no earlier
        than ``stamp - same_sweep_s`` is cached (only then is the nearest in time known; an older frame within the
        skew may be a whole sweep away while the sweep's own frame is still in flight). Whether it has (at once
        when it already has). Not at all when the ego's next frame, due one ego period (the median of the cached
        frames') after its newest, is stamped later than ``stamp + same_sweep_s``: that frame is of a later sweep (a
        peer whose LiDAR is not synchronised with the ego's), and waiting for it would hold the caller for up to a
        period."""
        with self._added:
            reached = lambda: any(e.stamp >= stamp - same_sweep_s for e in self._entries)  # noqa: E731
            if reached() or self._later_sweep_next(stamp + same_sweep_s):
                return reached()
            return self._added.wait_for(reached, timeout)

    def _later_sweep_next(self, latest_s: float) -> bool:
        """Whether the ego's next frame is due after ``latest_s`` (stamp), judged by its period; the lock is held."""
        stamps = sorted(e.stamp for e in self._entries)
        steps = [b - a for a, b in zip(stamps, stamps[1:]) if b > a]
        return bool(steps) and stamps[-1] + float(np.median(steps)) > latest_s

    def rewind(self, stamp: float) -> int:
        """The ego's recording started over at ``stamp`` (replay profile): frames of the previous pass stamped
        later are dropped, so the nearest-in-time choice never reaches across passes. Returns how many."""
        with self._lock:
            keep = [e for e in self._entries if e.stamp <= stamp]
            dropped = len(self._entries) - len(keep)
            self._entries = deque(keep, maxlen=self._entries.maxlen)
        return dropped

    def nearest(self, stamp: float) -> EgoEntry | None:
        """The entry nearest in time to ``stamp`` (the newer one on a tie); None when the cache is empty."""
        with self._lock:
            entries = list(self._entries)
        best = None
        for e in entries:  # arrival order, so '<=' prefers the later of equally near frames
            if best is None or abs(e.stamp - stamp) <= abs(best.stamp - stamp):
                best = e
        return best

    def nearest_ready(self, stamp: float, max_skew: float) -> EgoEntry | None:
        """The entry nearest in time to ``stamp`` among those whose features are computed, within ``max_skew``."""
        with self._lock:
            entries = [e for e in self._entries if e.ready and abs(e.stamp - stamp) <= max_skew]
        return min(reversed(entries), key=lambda e: abs(e.stamp - stamp), default=None)

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)

    def prepared(self) -> int:
        with self._lock:
            return sum(e.ready for e in self._entries)

    def stamps(self) -> list[float]:
        with self._lock:
            return [e.stamp for e in self._entries]
