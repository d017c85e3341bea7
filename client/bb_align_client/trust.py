"""What a car trusts for the service's answers: every Result is verified by default (docs/security.md)."""

from __future__ import annotations

import threading
import time
from collections import Counter, OrderedDict
from pathlib import Path

from bb_align.protocol import (
    FLEET_KEY_ID,
    AnswerTrust,
    Credential,
    Limits,
    Refusal,
    Result,
    TrustStore,
    WireError,
    load_answer,
    load_result,
    peek_frame,
)


def answer_trust(
    key: bytes | str | Credential | None,
    key_id: str,
    trust: AnswerTrust | TrustStore | Path | str | None,
    verify_answers: bool,
) -> AnswerTrust | None:
    """``trust``: the fleet authority's ``ca.pub`` (a path or a TrustStore; answers must then be signed with the
    ego's certificate) or an AnswerTrust. Without it, a fleet HMAC ``key`` verifies HMAC-signed answers.
    ``verify_answers=False``: accept unsigned answers (the demo profile only). Otherwise: ValueError, so that
    a car never takes unverified poses by accident. A path's authority comes with its revocation list when
    ``revoked.json`` lies beside ``ca.pub`` (``bb-align keys revoke`` writes it there): answers signed with a
    revoked key are refused, and the list is read again when it changes (never an older version)."""
    if not verify_answers:
        return None
    fleet = key if isinstance(key, (bytes, str)) and key_id == FLEET_KEY_ID else None
    if isinstance(trust, AnswerTrust):
        return trust
    if isinstance(trust, (str, Path)):
        trust = trust_store(trust)
    if trust is not None or fleet is not None:
        return AnswerTrust(trust, fleet)
    raise ValueError(
        "answers are verified by default: pass trust=<the fleet authority's ca.pub> (or the fleet key as key=), "
        "or verify_answers=False for the unauthenticated demo profile"
    )


def trust_store(ca_pub: Path | str, revocations: Path | str | None = None) -> TrustStore:
    """The authority of ``ca_pub`` with its revocation list: ``revocations``, else ``revoked.json`` beside
    ``ca_pub`` when there is one. ValueError when the list is not signed by that authority."""
    store = TrustStore.load(ca_pub)
    listed = Path(revocations) if revocations is not None else Path(ca_pub).with_name("revoked.json")
    if revocations is not None or listed.exists():
        store.use_revocations(listed)
    return store


def read_answer(
    data: bytes, trust: AnswerTrust | None, ego_id: str | None = None, refusals: bool = False
) -> Result | Refusal:
    """Decode (and, with ``trust``, verify) one answer; with ``ego_id``, it must come from that ego.
    ``refusals``: a Refusal is a valid answer too (a results key carries them); otherwise only a Result is."""
    answer = load_answer(data, trust) if refusals else load_result(data, trust)
    if trust is not None and ego_id is not None and answer.ego_id != ego_id:
        raise WireError(403, "forbidden", f"answer from {answer.ego_id!r}, expected {ego_id!r}", "ego_id", ego_id)
    return answer


# ---- binding answers to what was asked ---------------------------------------------------------------------------
# A signature says who made an answer, not which question it answers: a recorder can play a genuine answer again, on
# another car's key or later, and a rogue queryable can reply to a query with another car's genuine answer. So an
# answer is taken only for this car's id, for a frame it sent (its seq and stamp), once, within max_delay_s of
# sending it, and never older than an answer already taken (docs/security.md, "Answers bound to their request").

_LIMITS = Limits()


class Rejected(Counter):
    """Answers dropped by a car, by reason (``unverified``, ``another_ego``, ``another_peer``, ``not_sent``,
    ``stale``, ``backwards``): what a recorder or a rogue queryable tried."""


class SentFrames:
    """The frames a car sent lately, ``(seq, stamp) -> when sent`` (bounded): an answer must name one of them, and
    takes it (each frame is answered once); older entries go with it, since the stream never goes back."""

    def __init__(self, capacity: int = 1024, max_delay_s: float = 30.0, clock=time.monotonic):
        self.capacity, self.max_delay_s, self._clock = capacity, max_delay_s, clock
        self._sent: OrderedDict[tuple[int, float], float] = OrderedDict()
        self._lock = threading.Lock()

    def remember(self, data: bytes) -> tuple[int | None, float | None]:
        """Note an encoded (signed or not) frame as sent; returns its (seq, stamp)."""
        _, seq, stamp = peek_frame(data, _LIMITS)
        if seq is not None and stamp is not None:
            with self._lock:
                self._sent[(seq, stamp)] = self._clock()
                self._sent.move_to_end((seq, stamp))
                while len(self._sent) > self.capacity:
                    self._sent.popitem(last=False)
        return seq, stamp

    def claim(self, seq: int | None, stamp: float | None) -> str | None:
        """Take the frame (seq, stamp) as answered; None when it was sent and is fresh, else the reason."""
        with self._lock:
            sent = self._sent.pop((seq, stamp), None)
            if sent is None:
                return "not_sent"
            for key in [k for k in self._sent if (k[1], k[0]) < (stamp, seq)]:
                del self._sent[key]
        return "stale" if self._clock() - sent > self.max_delay_s else None


class AnswerFilter:
    """What a car's pose stream takes: verified answers from ``ego_id``, for ``peer_id`` (None: any peer), with
    ``sent`` (the car's own stream) only for frames it sent, and never one older than an answer already taken from
    the same peer (``max_age_s``: on a stream of other cars' answers, also not stamped more than that before this
    clock; None for recorded data)."""

    def __init__(
        self,
        trust: AnswerTrust,
        ego_id: str,
        peer_id: str | None,
        sent: SentFrames | None = None,
        max_age_s: float | None = 30.0,
        max_peers: int = 4096,
    ):
        self.trust, self.ego_id, self.peer_id, self.sent = trust, ego_id, peer_id, sent
        self.max_age_s, self.max_peers = max_age_s, max_peers
        self.rejected = Rejected()
        self._newest: OrderedDict[str, tuple[float, int]] = OrderedDict()

    def take(self, data: bytes) -> Result | Refusal | None:
        """The answer, or None (counted in ``rejected``) when it is not for this car's stream."""
        try:
            answer = read_answer(data, self.trust, self.ego_id, refusals=True)
        except WireError as e:
            return self._reject("another_ego" if e.field == "ego_id" else "unverified")
        if self.peer_id is not None and answer.peer_id != self.peer_id:
            return self._reject("another_peer")
        if answer.peer_seq is None or answer.peer_stamp is None:
            return self._reject("not_sent")
        key = (answer.peer_stamp, answer.peer_seq)
        newest = self._newest.get(answer.peer_id)
        if newest is not None and key <= newest:
            return self._reject("backwards")
        if self.sent is not None:
            why = self.sent.claim(answer.peer_seq, answer.peer_stamp)
            if why is not None:
                return self._reject(why)
        elif self.max_age_s is not None and answer.peer_stamp < time.time() - self.max_age_s:
            return self._reject("stale")
        self._newest[answer.peer_id] = key
        self._newest.move_to_end(answer.peer_id)
        while len(self._newest) > self.max_peers:
            self._newest.popitem(last=False)
        return answer

    def _reject(self, reason: str) -> None:
        self.rejected[reason] += 1
        return None


def bound_to(answer: Result | Refusal, vehicle_id: str | None, seq: int | None, stamp: float | None) -> bool:
    """Whether an answer names exactly the frame that was asked about (its sender, seq and stamp)."""
    return (
        seq is not None
        and stamp is not None
        and answer.peer_id == vehicle_id
        and answer.peer_seq == seq
        and answer.peer_stamp == stamp
    )
