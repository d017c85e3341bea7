"""Which refusals are told to their sender over Zenoh pub/sub, and what the notice says.

A stream frame (``<prefix>/frames/<vehicle_id>``) has no reply channel: when the gate refuses one, the sender
would only ever see a timeout. So a refused frame whose signature was valid for its sender (checked at the door,
Ed25519 certificate or HMAC key) gets a :class:`~bb_align.protocol.Refusal` on that sender's results key, signed
like a Result. Nothing else is answered: unsigned or wrongly signed junk gets no answer (a keyless flood cannot
make the service publish), and a sender gets at most one notice per ``min_interval_s`` (someone replaying a
car's recorded frames makes the service publish no faster than that, each notice smaller than the frame).
"""

from __future__ import annotations

import threading
import time

from bb_align.protocol import Limits, Refusal, WireError, peek_frame, peek_seq_stamp

from .scheduler import Job


class RefusalNotices:
    def __init__(self, ego_id: str, min_interval_s: float, max_tracked: int, clock=time.monotonic):
        self.ego_id, self.min_interval_s, self.max_tracked = ego_id, min_interval_s, max_tracked
        self._clock = clock
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}  # sender -> when its last notice went out

    def notice(self, job: Job, error: WireError, limits: Limits) -> Refusal | None:
        """The notice for a refused stream frame, or None when it must not be answered (not a stream frame, its
        signature was not verified for its sender, or that sender had a notice less than min_interval_s ago)."""
        if job.reply is not None or job.meta.get("signer") is None or not self._allow(job.sender):
            return None
        if job.frame is not None:
            seq, stamp = job.frame.seq, job.frame.stamp
        else:
            seq, stamp = peek_seq_stamp(job.data or b"", limits)
        return Refusal(
            ego_id=self.ego_id,
            peer_id=job.sender,
            peer_seq=seq,
            peer_stamp=stamp,
            status=error.status,
            refused=error.body(),
        )

    def for_query(self, job: Job, error: WireError, limits: Limits) -> Refusal | None:
        """A refused query's error reply, signed like a Result when the query's signature was verified (so a car
        can tell the ego's refusal from a rogue queryable's); None for an unauthenticated query (its error reply
        stays unsigned: a keyless query flood makes the service sign nothing). A query has its own reply channel:
        no rate limit here."""
        if job.reply is None or job.meta.get("signer") is None:
            return None
        if job.frame is not None:
            vid, seq, stamp = job.frame.vehicle_id, job.frame.seq, job.frame.stamp
        else:
            vid, seq, stamp = peek_frame(job.data or b"", limits)
        if vid is None:
            return None
        return Refusal(
            ego_id=self.ego_id, peer_id=vid, peer_seq=seq, peer_stamp=stamp, status=error.status, refused=error.body()
        )

    def _allow(self, sender: str) -> bool:
        now = self._clock()
        with self._lock:
            last = self._last.get(sender)
            if last is not None and now - last < self.min_interval_s:
                return False
            if len(self._last) >= self.max_tracked:  # only senders within the interval matter: forget the rest
                self._last = {s: t for s, t in self._last.items() if now - t < self.min_interval_s}
                if len(self._last) >= self.max_tracked:  # that many senders refused at once: stay bounded
                    return False
            self._last[sender] = now
            return True
