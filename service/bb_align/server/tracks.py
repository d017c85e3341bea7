"""The service's tracks: one engine Follower per peer, bounded, forgotten with the peer.

A peer's frames may reach two workers at once; each track is stepped under its own lock, in arrival order (the
tracker answers a frame older than its last one with ``out_of_order``, never moves backwards).

Every admitted stream frame's odometry is heard (the gate's thread), stepped or not: a busy service replaces a
peer's frames unread, and the odometry check must still see each car's every step (``Follower.observe_odometry``),
or a relocalisation could hide in the gap and each gap would cost a full acquisition to vouch for it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict, deque

import numpy as np

from bb_align.engine.follow import Follower
from bb_align.engine.pipeline import Aligner

HEARD = 64  # odometry poses kept per car: 6.4 s at 10 Hz (a longer gap is a gap the check cannot vouch for)
Heard = tuple[float, np.ndarray]  # (frame stamp s, 4x4 odometry pose)


class _Heard:
    """One car's odometry poses of recent frames, appended by the gate, read by the workers."""

    def __init__(self):
        self._poses: deque[Heard] = deque(maxlen=HEARD)
        self._lock = threading.Lock()

    def add(self, stamp: float, O: np.ndarray) -> None:
        with self._lock:
            self._poses.append((stamp, O))

    def before(self, stamp: float) -> list[Heard]:
        """The poses of frames stamped before ``stamp``, in time order."""
        with self._lock:
            return sorted((p for p in self._poses if p[0] < stamp), key=lambda p: p[0])

    def clear(self) -> None:
        with self._lock:
            self._poses.clear()


class _Track:
    def __init__(self, follower: Follower):
        self.follower = follower
        self.lock = threading.Lock()
        self.heard = _Heard()  # the peer's frames' odometry

    def observe(self, ego: _Heard, ego_stamp: float, peer_stamp: float) -> None:
        """Before stepping the frame pair at these stamps (track lock held): the two cars' frames heard since."""
        self.follower.observe_odometry(ego=ego.before(ego_stamp), peer=self.heard.before(peer_stamp))


class PeerTracks:
    def __init__(self, aligner: Aligner, max_tracks: int):
        self.aligner, self.max_tracks = aligner, max_tracks
        self._tracks: OrderedDict[str, _Track] = OrderedDict()
        self._lock = threading.Lock()
        self.ego_heard = _Heard()  # the ego's frames' odometry, shared by every track

    def hear(self, vehicle_id: str, stamp: float, O: np.ndarray, ego: bool) -> None:
        """An admitted stream frame's odometry pose (4x4): the ego's, or a peer's (its track made if it has none)."""
        (self.ego_heard if ego else self.get(vehicle_id).heard).add(stamp, O)

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
        self.ego_heard.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._tracks)

    def states(self) -> dict[str, str]:
        with self._lock:
            return {p: t.follower.track.state.value for p, t in self._tracks.items()}
