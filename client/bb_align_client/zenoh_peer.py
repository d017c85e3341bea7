"""A car on the Zenoh side: publish frames, ask the ego service for an alignment, receive published poses."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import zenoh

from bb_align.protocol import (
    FLEET_KEY_ID,
    AnswerTrust,
    Credential,
    ErrorBody,
    Limits,
    Refusal,
    Result,
    TrustStore,
    WireError,
    ZenohSettings,
    ZenohTls,
    align_key,
    frames_key,
    is_signed,
    peek_frame,
    poses_key,
)

from .encode import sign_frame
from .errors import FrameRefused, ServiceError
from .trust import AnswerFilter, Rejected, SentFrames, answer_trust, bound_to, read_answer


@dataclass
class ArrivalLog:
    """A subscriber callback for harnesses: records (arrival time, payload bytes) of every sample, nothing else
    (callbacks run on Zenoh's threads). ``items`` is read under ``lock``."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    items: list[tuple[float, bytes]] = field(default_factory=list)

    def __call__(self, sample) -> None:
        t = time.perf_counter()
        data = sample.payload.to_bytes()
        with self.lock:
            self.items.append((t, data))


class PoseStream:
    """Results the ego service publishes (``<prefix>/poses/<ego_id>/<peer_id>``), buffered for ``get``. The same
    key carries the service's refusals of this car's signed frames: ``get`` raises them as FrameRefused.

    With answers verified (the default), ``get`` returns only answers signed by the pinned ego, for this stream's
    peer, and on a car's own stream only for a frame the car sent, each once, fresh, never older than the last
    taken (AnswerFilter); anything else (a forgery, another car's answer, a recording played again) is dropped
    and counted in ``rejected`` by reason, and ``get`` goes on waiting."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        capacity: int = 1000,
        trust: AnswerTrust | None = None,
        ego_id: str | None = None,
        peer_id: str | None = None,
        sent: SentFrames | None = None,
        max_age_s: float | None = 30.0,
    ):
        self.key = key
        self._trust, self._ego_id = trust, ego_id
        self._filter = None if trust is None else AnswerFilter(trust, ego_id, peer_id, sent, max_age_s)
        self.rejected = self._filter.rejected if self._filter is not None else Rejected()
        self._queue: queue.Queue[bytes] = queue.Queue(capacity)
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:  # Zenoh thread: enqueue only
        try:
            self._queue.put_nowait(sample.payload.to_bytes())
        except queue.Full:
            pass

    def get(self, timeout: float | None = None) -> Result:
        """The next answer for this stream (see the class). Raises FrameRefused (a ServiceError: ``.body.field``,
        ``.body.limit``, ``.body.setting``, ``.peer_seq``) when it is the service's refusal of one of this car's
        frames, and TimeoutError after ``timeout`` seconds without one. Unverified (``verify_answers=False``): the
        next answer as it comes."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                data = self._queue.get(timeout=wait)
            except queue.Empty:
                raise TimeoutError(f"no result on {self.key} within {timeout} s") from None
            if self._filter is None:
                answer = read_answer(data, None, self._ego_id, refusals=True)
            else:
                answer = self._filter.take(data)
                if answer is None:
                    continue
            if isinstance(answer, Refusal):
                raise FrameRefused(answer)
            return answer

    def close(self) -> None:
        self._subscriber.undeclare()


class ZenohPeer:
    """``with ZenohPeer("car1", connect=["tcp/127.0.0.1:7447"]) as peer: peer.publish(frame)``.

    By default the session listens nowhere and connects to the given endpoints, multicast scouting off. Frames
    are dropped when the link is congested (a newer sweep follows anyway); ``block_when_congested=True`` makes
    ``publish`` wait instead (every frame reaches the service; for tests and recordings).

    ``key``: sign every unsigned frame: this car's Credential (Ed25519, ``bb-align keys issue``), or an HMAC key:
    the fleet key (``key_id="fleet"``, the default) or this car's own (``key_id=vehicle_id``). ``trust``: the
    fleet authority's ``ca.pub`` (path or TrustStore): every answer (published pose, query reply) must be signed
    by the ego's certificate, else ``WireError`` (401 unsigned/forged, 403 another vehicle). With the fleet HMAC
    key and no ``trust``, HMAC-signed answers are verified with it. ``verify_answers=False``: the demo profile's
    unsigned answers. ``tls``: certificates for ``tls/`` endpoints (bb_align.protocol.ZenohTls or a dict)."""

    def __init__(
        self,
        vehicle_id: str,
        connect: Sequence[str] = ("tcp/127.0.0.1:7447",),
        *,
        listen: Sequence[str] = (),
        prefix: str = "bbalign",
        mode: str = "peer",
        multicast_scouting: bool = False,
        block_when_congested: bool = False,
        key: bytes | str | Credential | None = None,
        key_id: str = FLEET_KEY_ID,
        tls: ZenohTls | dict | None = None,
        trust: AnswerTrust | TrustStore | str | None = None,
        verify_answers: bool = True,
        answer_max_delay_s: float = 30.0,
    ):
        self._trust = answer_trust(key, key_id, trust, verify_answers)
        self.vehicle_id = vehicle_id
        self.sent = SentFrames(max_delay_s=answer_max_delay_s)  # what this car's answers must name
        self.block_when_congested = block_when_congested
        self.prefix = prefix
        self._key, self._key_id = key, key_id
        self._config = ZenohSettings(
            mode=mode,
            listen=list(listen),
            connect=list(connect),
            multicast_scouting=multicast_scouting,
            prefix=prefix,
            tls=tls if tls is not None else ZenohTls(),
        )
        self.session: zenoh.Session | None = None
        self._publisher = None
        self._streams: list[PoseStream] = []
        self.rejected = Rejected()  # query replies dropped by request_align, by reason

    def open(self) -> ZenohPeer:
        self.session = zenoh.open(self._config.to_zenoh_config())
        cc = zenoh.CongestionControl.BLOCK if self.block_when_congested else zenoh.CongestionControl.DROP
        self._publisher = self.session.declare_publisher(
            frames_key(self.prefix, self.vehicle_id), congestion_control=cc
        )
        return self

    def publish(self, frame: bytes) -> None:
        """Send an encoded frame on ``<prefix>/frames/<vehicle_id>`` (signed first when this car has a key)."""
        data = self._signed(frame)
        self.sent.remember(data)
        self._publisher.put(data)

    def expect(self, frame: bytes) -> None:
        """Note a frame this car sent by other means (e.g. REST ``post_frame``): its answer on this car's pose
        stream is then taken."""
        self.sent.remember(self._signed(frame))

    def _signed(self, frame: bytes) -> bytes:
        return frame if self._key is None else sign_frame(frame, self._key, self._key_id)

    def wait_for_subscriber(self, timeout: float = 5.0) -> bool:
        """Wait (bounded) until some subscriber, e.g. the ego service, matches this car's frame key."""
        deadline = time.monotonic() + timeout
        while not self._publisher.matching_status.matching:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        return True

    def request_align(self, frame: bytes, ego_id: str, timeout: float = 10.0) -> Result:
        """Query ``<prefix>/align/<ego_id>`` with a frame and wait for its Result (ServiceError if refused,
        TimeoutError if nobody answered).

        Every queryable on the key is asked (a rogue one cannot make itself the only one) and replies are read as
        they come: with answers verified, the first Result signed by ``ego_id`` for exactly this frame (this car's
        id, the frame's seq and stamp) is returned, and a Refusal signed the same way raised (FrameRefused); other
        replies are dropped (counted in ``rejected``). An unsigned error (what the service says to a query it could
        not authenticate) is raised only when no such answer came before the queryables were done or ``timeout``."""
        key = align_key(self.prefix, ego_id)
        data = self._signed(frame)
        vehicle_id, seq, stamp = peek_frame(data, Limits())
        unverified: ErrorBody | None = None
        replies = self.session.get(
            key,
            payload=data,
            timeout=timeout,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
        )
        for reply in replies:
            if self._trust is None:  # the demo profile: the first reply, as it is
                if reply.ok is not None:
                    return read_answer(reply.ok.payload.to_bytes(), None, ego_id)
                raise ServiceError(None, _error_body(reply.err.payload.to_bytes()))
            payload = (reply.ok if reply.ok is not None else reply.err).payload.to_bytes()
            if reply.err is not None and not is_signed(payload):
                unverified = unverified or _error_body(payload)
                self.rejected["unsigned_error"] += 1
                continue
            try:
                answer = read_answer(payload, self._trust, ego_id, refusals=True)
            except WireError as e:
                self.rejected["another_ego" if e.field == "ego_id" else "unverified"] += 1
                continue
            if not bound_to(answer, vehicle_id, seq, stamp):
                self.rejected["not_sent"] += 1
                continue
            if isinstance(answer, Refusal):
                raise FrameRefused(answer)
            return answer
        if unverified is not None:
            raise ServiceError(None, unverified)
        raise TimeoutError(f"no reply on {key} within {timeout} s (service absent, overloaded or too slow)")

    def poses(self, ego_id: str, peer_id: str | None = None, max_age_s: float | None = 30.0) -> PoseStream:
        """Subscribe to the results the ego service publishes for ``peer_id`` (default: this car; "*": all). On
        this car's own stream an answer must name a frame it sent (``publish``, ``request_align``, ``expect``);
        on another's ("*" included), be stamped within ``max_age_s`` of this clock (None: recorded data)."""
        peer = peer_id or self.vehicle_id
        key = poses_key(self.prefix, ego_id, peer)
        own = peer == self.vehicle_id
        stream = PoseStream(
            self.session,
            key,
            trust=self._trust,
            ego_id=ego_id,
            peer_id=None if peer == "*" else peer,
            sent=self.sent if own else None,
            max_age_s=max_age_s,
        )
        self._streams.append(stream)
        return stream

    def close(self) -> None:
        for s in self._streams:
            s.close()
        self._streams.clear()
        if self._publisher is not None:
            self._publisher.undeclare()
            self._publisher = None
        if self.session is not None:
            self.session.close()
            self.session = None

    def __enter__(self) -> ZenohPeer:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()


def _error_body(data: bytes) -> ErrorBody:
    import msgpack

    try:
        return ErrorBody.model_validate(msgpack.unpackb(data, raw=False))
    except Exception:
        return ErrorBody(error="unavailable", detail=data[:300].decode("utf-8", "replace"))
