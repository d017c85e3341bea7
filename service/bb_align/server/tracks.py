"""The service's tracks: one engine Follower per peer, bounded, forgotten with the peer.

A peer's frames may reach two workers at once; each track is stepped under its own lock, in arrival order (the
tracker answers a frame older than its last one with ``out_of_order``, never moves backwards).
"""

from __future__ import annotations

import threading
from collections import OrderedDict

from bb_align.engine.follow import Follower
from bb_align.engine.pipeline import Aligner


class _Track:
    def __init__(self, follower: Follower):
        self.follower = follower
        self.lock = threading.Lock()


class PeerTracks:
    def __init__(self, aligner: Aligner, max_tracks: int):
        self.aligner, self.max_tracks = aligner, max_tracks
        self._tracks: OrderedDict[str, _Track] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, peer_id: str) -> _Track:
        """The peer's track (a new one when it has none); the least recently used goes beyond max_tracks."""
        with self._lock:
            track = self._tracks.pop(peer_id, None) or _Track(Follower(self.aligner))
            self._tracks[peer_id] = track
            while len(self._tracks) > self.max_tracks:
                self._tracks.popitem(last=False)
            return track

    def state(self, peer_id: str) -> str | None:
        """The peer's track state (``tracking``, ``acquiring``, ``lost``), None without a track; creates nothing
        (the scheduler asks it to tell a tracked frame from an acquisition)."""
        with self._lock:
            track = self._tracks.get(peer_id)
        return None if track is None else track.follower.track.state.value

    def any_tracking(self) -> bool:
        """Whether some peer is tracked (its frames are light work, ~20-30 ms, that must not wait)."""
        with self._lock:
            return any(t.follower.track.state.value == "tracking" for t in self._tracks.values())

    def forget(self, peer_id: str) -> None:
        with self._lock:
            self._tracks.pop(peer_id, None)

    def clear(self) -> None:
        with self._lock:
            self._tracks.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._tracks)

    def states(self) -> dict[str, str]:
        with self._lock:
            return {p: t.follower.track.state.value for p, t in self._tracks.items()}
