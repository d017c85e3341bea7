"""The service's Zenoh door.

- subscriber ``<prefix>/frames/*``: every car's frames; the key's last chunk is the sender's vehicle id (the ego
  id's frames fill the ego cache, all others are aligned);
- publisher ``<prefix>/poses/<ego_id>/<peer_id>``: one msgpack Result per aligned peer frame, and a Refusal for a
  refused stream frame whose signature was valid for that peer (core.py, refusals.py);
- queryable ``<prefix>/align/<ego_id>``: a query carrying a peer frame is answered with a Result (or an error
  reply holding an ErrorBody).

Callbacks only hand bytes to the service's intake; the gate thread authenticates and validates them; replies
and publications happen on the gate and worker threads. Connecting never gives up (a router restart is
survived); Zenoh's own reassembly limit (the message limit + 64 KiB) drops far larger messages before they are
assembled (a backstop: measured here, 8 MiB dropped by Zenoh, 5-6 MiB reach the callback's size check).
"""

from __future__ import annotations

import logging
import threading

import zenoh

from bb_align.protocol import ErrorBody, Refusal, Result, WireError, align_key, frames_key, pack, poses_key

from .core import AlignService, Unavailable
from .settings import Settings

log = logging.getLogger("bb_align.zenoh")


class ZenohLink:
    def __init__(self, service: AlignService, settings: Settings):
        self.service = service
        self.settings = settings
        self.prefix = settings.zenoh.prefix
        self.session: zenoh.Session | None = None
        self._subscriber = None
        self._queryable = None
        self._lock = threading.Lock()

    @property
    def align_key(self) -> str:
        return align_key(self.prefix, self.settings.ego_id)

    def open(self) -> None:
        self.session = zenoh.open(self.settings.zenoh.to_zenoh_config())
        self.service.publishers.append(self.publish)
        self._subscriber = self.session.declare_subscriber(frames_key(self.prefix, "*"), self._on_frame)
        self._queryable = self.session.declare_queryable(self.align_key, self._on_query)

    @property
    def is_open(self) -> bool:
        return self.session is not None and not self.session.is_closed()

    def stop_intake(self) -> None:
        """No new frames or queries (call before stopping the service's workers)."""
        for entity in (self._subscriber, self._queryable):
            if entity is not None:
                entity.undeclare()
        self._subscriber = self._queryable = None

    def close(self) -> None:
        self.stop_intake()
        if self.publish in self.service.publishers:
            self.service.publishers.remove(self.publish)
        with self._lock:
            session, self.session = self.session, None
        if session is not None:
            session.close()

    # ---- callbacks (Zenoh threads: enqueue only) -----------------------------------------------------------
    def _on_frame(self, sample: zenoh.Sample) -> None:
        sender = str(sample.key_expr).rsplit("/", 1)[-1]
        if len(sample.payload) > self.settings.limits.max_message_bytes:  # refused before it is even copied
            self.service.metrics.rejected.labels("zenoh", "too_large").inc()
            return
        self.service.submit_message(sender, sample.payload.to_bytes(), door="zenoh")

    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        size, limit = (len(payload) if payload is not None else 0), self.settings.limits.max_message_bytes
        refused = (
            WireError(413, "too_large", f"{size} bytes exceed the limit of {limit} bytes", "message", limit)
            if size > limit
            else None
        )  # answered by the gate, never copied
        data = payload.to_bytes() if payload is not None and refused is None else b""
        self.service.submit_query(lambda outcome: self._reply(query, outcome), data, door="zenoh", refused=refused)

    # ---- worker side -----------------------------------------------------------------------------------------
    def _reply(self, query: zenoh.Query, outcome: object) -> None:
        try:
            with query:
                if isinstance(outcome, Result):
                    query.reply(self.align_key, self.service.encode_answer(outcome))
                else:
                    query.reply_err(pack(_error_body(outcome)))
        except Exception:
            log.exception("replying to a query failed")

    def publish(self, answer: Result | Refusal) -> None:
        """Put a result (or a refusal notice) on ``<prefix>/poses/<ego_id>/<peer_id>`` (no per-peer publisher state
        to leak)."""
        with self._lock:
            session = self.session
        if session is not None:
            session.put(poses_key(self.prefix, answer.ego_id, answer.peer_id), self.service.encode_answer(answer))


def _error_body(outcome: object) -> ErrorBody:
    if isinstance(outcome, WireError):
        return outcome.body()
    if isinstance(outcome, Unavailable):
        return ErrorBody(error="unavailable", detail=str(outcome))
    return ErrorBody(error="unavailable", detail=f"internal error: {type(outcome).__name__}")
