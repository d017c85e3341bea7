"""The senders the service tracks: admission, replay refusal, idle eviction, per-peer counters.

Only a frame that passed the whole validator (and its signature check) creates or refreshes a sender's entry,
so junk ids cannot fill the table. At most ``max_peers`` senders besides the ego are tracked; a sender silent for
``peer_idle_s`` is forgotten (its queue, replay state, bandwidth tally and metric labels go with it, through
``on_evict``). With replay refusal on (authentication on), each sender's frames must come with ever newer
``(stamp, seq)``, one window across both doors and both REST routes: a signed frame sent again is refused. A
forgotten sender's old frames are older than ``max_stamp_age_s`` (Limits requires peer_idle_s >=
max_stamp_age_s), so the stamp window refuses them.

The replay window survives a restart without any state on disk: a frame accepted before the service last
stopped (crashed, killed) was stamped at most ``max_stamp_lead_s`` after that moment, which is before this process
started; so every frame stamped before the process start (when the server's modules were imported) +
``max_stamp_lead_s`` is refused (``not_before``). Genuine frames of the first ``max_stamp_lead_s`` after that are
refused too; the process spends about that long importing and warming up. It assumes the receiver's clock does
not go back across a restart (the stamp checks already assume a synchronised clock).

The replay profile (``limits.replay``, recorded or simulated data) takes a ``(stamp, seq)`` that goes back as
the start of a new pass over the recording: accepted, counted (``sequence_restarts``), and the window starts
again from it. It gives up replay protection (docs/security.md).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from pydantic import BaseModel, Field

from bb_align.protocol import Frame, Result, WireError, limit_env
from bb_align.protocol.limits import REPLAY_HINT

from .bandwidth import PeerBandwidth

_IMPORTED = time.time()


def process_started_at() -> float:
    """A wall-clock time after this process started and before it took any frame: when the server's modules were
    imported. (/proc's start tick is earlier but counted from a boot time rounded to the second and drifting from
    the wall clock: measured 1.1 s off here, enough to let a fast restart take a frame again.)"""
    return _IMPORTED


class PeerStatus(BaseModel):
    last_result: Result | None = None
    frames_accepted: int = Field(0, description="stream frames that passed the validator and were queued")
    frames_dropped: int = Field(
        0, description="accepted stream frames replaced by a newer one (latest-only) or still queued at shutdown"
    )
    intake_dropped: int = Field(
        0,
        description="messages pushed out of the full intake before the gate "
        "checked them (while this sender was tracked)",
    )
    results: int = Field(0, description="results produced for this sender's frames (streams and requests)")
    failed: int = Field(
        0,
        description="accepted frames whose processing raised (logged; their result says "
        "invalid_frame or internal_error)",
    )
    sequence_restarts: int = Field(
        0,
        description="replay profile: frames whose (stamp, seq) went back and started a new pass over a recording",
    )
    bandwidth: PeerBandwidth | None = None


class _Entry:
    def __init__(self, now: float):
        self.status = PeerStatus()
        self.last_seen = now
        # (channel, signer's key) -> newest (stamp, seq) accepted: one window per key, so that a car's old key,
        # still valid during a rotation, cannot stamp ahead and lock its new key out
        self.newest: dict[tuple[str, bytes | None], tuple[float, int]] = {}
        self.outcomes: set[str] = set()  # metric label values used, removed on eviction


KEYS_PER_SENDER = 4  # replay windows kept per sender and channel (keys valid at once: a rotation needs 2)


def _bound_keys(newest: dict, channel: str) -> None:
    """At most KEYS_PER_SENDER windows per channel: the one whose newest frame is oldest goes (only the authority
    makes keys, so a sender has more valid at once only by the authority's choice)."""
    slots = [slot for slot in newest if slot[0] == channel]
    while len(slots) > KEYS_PER_SENDER:
        oldest = min(slots, key=newest.__getitem__)
        del newest[oldest]
        slots.remove(oldest)


class PeerTable:
    def __init__(
        self,
        max_peers: int,
        idle_s: float,
        *,
        reserved: str,
        refuse_replays: bool,
        new_pass_on_rewind: bool = False,
        on_evict: Callable[[str, _Entry], None] = lambda vid, entry: None,
        clock=time.monotonic,
        not_before: float | None = None,
    ):
        self.max_peers, self.idle_s, self.reserved = max_peers, idle_s, reserved
        # frames stamped earlier may have been accepted before a restart (only with replays refused)
        self.not_before = not_before if refuse_replays and not new_pass_on_rewind else None
        self.refuse_replays, self.new_pass_on_rewind = refuse_replays, new_pass_on_rewind
        self._on_evict = on_evict
        self._clock = clock
        self._lock = threading.Lock()
        self._entries: dict[str, _Entry] = {}

    def admit(self, frame: Frame, channel: str) -> bool:
        """Track ``frame``'s sender (or refresh it); raises WireError 409 (replayed) or 503 (table full). True
        when the frame starts a new pass (replay profile: its (stamp, seq) went back)."""
        if self.not_before is not None and frame.stamp < self.not_before:
            raise WireError(
                409,
                "replayed",
                f"stamp {frame.stamp} is before this service started ({self.not_before:.3f} with the stamp lead): "
                "it may have been accepted before a restart, so it is refused as a replay",
                "stamp",
                self.not_before,
                limit_env("max_stamp_lead_s"),
            )
        now = self._clock()
        evicted = []
        with self._lock:
            entry = self._entries.get(frame.vehicle_id)
            if entry is None:
                evicted = self._evict_idle(now)
                if frame.vehicle_id != self.reserved and self._count() >= self.max_peers:
                    self._notify(evicted)
                    raise WireError(
                        503,
                        "overloaded",
                        f"already tracking {self.max_peers} peers, none idle for {self.idle_s} s",
                        "vehicle_id",
                        self.max_peers,
                        limit_env("max_peers"),
                    )
                entry = self._entries[frame.vehicle_id] = _Entry(now)
            key, slot = (frame.stamp, frame.seq), (channel, frame.signer_key)
            newest = entry.newest.get(slot)
            rewound = newest is not None and key <= newest
            if rewound and self.new_pass_on_rewind:  # a recording played again: its window starts over
                entry.newest[slot] = key
                entry.status.sequence_restarts += 1
            elif rewound and self.refuse_replays:
                self._notify(evicted)
                raise WireError(
                    409,
                    "replayed",
                    f"(stamp, seq) = ({frame.stamp}, {frame.seq}) is not newer than the last accepted from "
                    f"{frame.vehicle_id!r} ({newest[0]}, {newest[1]}): refused as a replay ({limit_env('replay')} "
                    f"is false); {REPLAY_HINT}",
                    "stamp",
                    newest[0],
                    limit_env("replay"),
                )
            else:
                entry.newest[slot] = max(key, newest) if newest is not None else key
                _bound_keys(entry.newest, channel)
            entry.last_seen = now
        self._notify(evicted)
        return rewound and self.new_pass_on_rewind

    def newest(self, vehicle_id: str, channel: str, key: bytes | None = None) -> tuple[float, int] | None:
        """The newest (stamp, seq) accepted from a tracked sender on ``channel`` signed with ``key`` (None: none,
        or not tracked). The restart floor (``not_before``) is not part of it: the gate refuses those frames and
        tells their sender."""
        with self._lock:
            entry = self._entries.get(vehicle_id)
            return None if entry is None else entry.newest.get((channel, key))

    def sweep(self) -> list[str]:
        """Forget every sender idle for longer than idle_s; returns their ids."""
        with self._lock:
            evicted = self._evict_idle(self._clock())
        self._notify(evicted)
        return [vid for vid, _ in evicted]

    def update(self, vehicle_id: str, fn: Callable[[_Entry], None]) -> bool:
        """Apply ``fn`` to a tracked sender's entry under the lock; False when it is not tracked (evicted)."""
        with self._lock:
            entry = self._entries.get(vehicle_id)
            if entry is None:
                return False
            fn(entry)
            return True

    def statuses(self) -> dict[str, PeerStatus]:
        with self._lock:
            return {vid: e.status.model_copy() for vid, e in self._entries.items()}

    def __contains__(self, vehicle_id: str) -> bool:
        with self._lock:
            return vehicle_id in self._entries

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)

    def _count(self) -> int:
        return sum(1 for vid in self._entries if vid != self.reserved)

    def _evict_idle(self, now: float) -> list[tuple[str, _Entry]]:
        idle = [vid for vid, e in self._entries.items() if now - e.last_seen > self.idle_s]
        return [(vid, self._entries.pop(vid)) for vid in idle]

    def _notify(self, evicted: list[tuple[str, _Entry]]) -> None:
        for vid, entry in evicted:  # outside the lock: the callback takes other locks
            self._on_evict(vid, entry)
