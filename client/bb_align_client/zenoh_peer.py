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
    Refusal,
    Result,
    TrustStore,
    ZenohSettings,
    ZenohTls,
    align_key,
    frames_key,
    poses_key,
)

from .encode import sign_frame
from .errors import FrameRefused, ServiceError
from .trust import answer_trust, read_answer


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
    key carries the service's refusals of this car's signed frames: ``get`` raises them as FrameRefused."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        capacity: int = 1000,
        trust: AnswerTrust | None = None,
        ego_id: str | None = None,
    ):
        self.key = key
        self._trust, self._ego_id = trust, ego_id
        self._queue: queue.Queue[bytes] = queue.Queue(capacity)
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:  # Zenoh thread: enqueue only
        try:
            self._queue.put_nowait(sample.payload.to_bytes())
        except queue.Full:
            pass

    def get(self, timeout: float | None = None) -> Result:
        """The next result, verified (WireError 401/403 for an unsigned or forged one, unless the peer was made
        with ``verify_answers=False``). Raises FrameRefused (a ServiceError: ``.body.field``, ``.body.limit``,
        ``.body.setting``, ``.peer_seq``) when the next answer is the service's refusal of one of this car's
        frames, and TimeoutError after ``timeout`` seconds without an answer."""
        try:
            data = self._queue.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"no result on {self.key} within {timeout} s") from None
        answer = read_answer(data, self._trust, self._ego_id, refusals=True)
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
    ):
        self._trust = answer_trust(key, key_id, trust, verify_answers)
        self.vehicle_id = vehicle_id
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

    def open(self) -> ZenohPeer:
        self.session = zenoh.open(self._config.to_zenoh_config())
        cc = zenoh.CongestionControl.BLOCK if self.block_when_congested else zenoh.CongestionControl.DROP
        self._publisher = self.session.declare_publisher(
            frames_key(self.prefix, self.vehicle_id), congestion_control=cc
        )
        return self

    def publish(self, frame: bytes) -> None:
        """Send an encoded frame on ``<prefix>/frames/<vehicle_id>`` (signed first when this car has a key)."""
        self._publisher.put(self._signed(frame))

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
        TimeoutError if nobody answered)."""
        key = align_key(self.prefix, ego_id)
        for reply in self.session.get(key, payload=self._signed(frame), timeout=timeout):
            if reply.ok is not None:
                return read_answer(reply.ok.payload.to_bytes(), self._trust, ego_id)
            raise ServiceError(None, _error_body(reply.err.payload.to_bytes()))
        raise TimeoutError(f"no reply on {key} within {timeout} s (service absent, overloaded or too slow)")

    def poses(self, ego_id: str, peer_id: str | None = None) -> PoseStream:
        """Subscribe to the results the ego service publishes for ``peer_id`` (default: this car; "*": all)."""
        key = poses_key(self.prefix, ego_id, peer_id or self.vehicle_id)
        stream = PoseStream(self.session, key, trust=self._trust, ego_id=ego_id)
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
