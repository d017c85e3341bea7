"""The service's Zenoh door.

- subscribers ``<prefix>/frames/<ego_id>`` and ``<prefix>/frames/*``: the ego's frames (they fill the ego cache)
  and every car's (aligned); the key's last chunk is the sender's vehicle id. Samples wait in Zenoh's own bounded
  rings (``limits.door_queue`` each; the ego's key has its own, so a flood on the cars' keys cannot push an ego
  frame out, nor one on the ego's key a car's) for a door thread each, which checks them (bb_align.server.door)
  within a CPU budget for what it refuses (``limits.door_share`` of a core). A full ring drops its oldest sample in
  Zenoh; nothing here blocks Zenoh's receive threads. (A blocking FIFO did: each flooding session whose sample
  waited for a place held one of Zenoh's receive threads, 2 by default, so two flooding sessions left none to read
  the cars' links: measured, docs/security.md, Floods.) A Python callback per sample could not be bounded: each
  one takes the GIL;
- ingress downsampling (Zenoh's own, in its receive threads, per remote session): at most
  ``limits.zenoh_frame_rate_hz`` frames and ``limits.zenoh_query_rate_hz`` queries a second from each session, so
  the messages a flood can bring to Python grow with its number of sessions, not with its links' speed;
- publisher ``<prefix>/poses/<ego_id>/<peer_id>``: one msgpack Result per aligned peer frame, and a Refusal for a
  refused stream frame whose signature was valid for that peer (core.py, refusals.py);
- queryable ``<prefix>/align/<ego_id>``: a query carrying a peer frame is answered with a Result (or an error
  reply: a signed Refusal when the query was authenticated, else an ErrorBody). Queries wait in Zenoh's own
  bounded ring (``limits.query_queue``) for one thread of ours, which hands them to the intake.

The door and the query thread only hand bytes to the service's intake; the gate thread authenticates and
validates them; replies and publications happen on the gate and worker threads. Connecting never gives up (a
router restart is survived); Zenoh's own reassembly limit (the message limit + 64 KiB) drops far larger messages
before they are assembled (a backstop: measured here, 8 MiB dropped by Zenoh, 5-6 MiB reach the door's size
check).
"""

from __future__ import annotations

import json
import logging
import threading
import time

import zenoh

from bb_align.protocol import ErrorBody, Refusal, Result, WireError, align_key, frames_key, pack, poses_key

from .core import AlignService, Unavailable
from .door import Budget
from .settings import Settings

log = logging.getLogger("bb_align.zenoh")


class ZenohLink:
    def __init__(self, service: AlignService, settings: Settings):
        self.service = service
        self.settings = settings
        self.prefix = settings.zenoh.prefix
        self.session: zenoh.Session | None = None
        self._subscribers: list = []
        self._queryable = None
        self._doors: list[threading.Thread] = []
        self._query_thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def align_key(self) -> str:
        return align_key(self.prefix, self.settings.ego_id)

    def open(self) -> None:
        cfg = self.settings.zenoh.to_zenoh_config()
        limits = self.settings.limits
        # Per remote session: meaningful when the cars connect to the service itself; a client of a router sees every
        # car through one session (put the same rules into the router's config, docs/security.md). Not in the demo
        # profile (no authentication), whose tools publish in bursts
        rules = ingress_limits(self.prefix, self.settings.ego_id, limits)
        if rules and self.settings.zenoh.mode != "client" and self.settings.auth.mode != "off":
            cfg.insert_json5("downsampling", json.dumps(rules))
        self.session = zenoh.open(cfg)
        self.service.publishers.append(self.publish)
        ego = self.settings.ego_id
        budgets = []
        # The ego's key gets its own subscriber and ring; the wildcard one skips it (the same samples again)
        for key, skip in ((frames_key(self.prefix, ego), None), (frames_key(self.prefix, "*"), ego)):
            sub = self.session.declare_subscriber(key, zenoh.handlers.RingChannel(limits.door_queue))
            budget = Budget(limits.door_share, limits.door_window_s)
            door = threading.Thread(
                target=self._door_loop, args=(sub.handler, budget, skip), name="bbalign-door", daemon=True
            )
            self._subscribers.append(sub)
            self._doors.append(door)
            budgets.append(budget)
            door.start()
        self.service.metrics.door_throttled.set_function(lambda: sum(b.throttled_s for b in budgets))
        # Queries wait in a bounded ring for a thread of ours, as frames do: a Python callback would be fed through
        # Zenoh's unbounded channel to its own thread (measured: a keyless 4 MB query flood grew RSS by 1.1 GB)
        self._queryable = self.session.declare_queryable(self.align_key, zenoh.handlers.RingChannel(limits.query_queue))
        self._query_thread = threading.Thread(
            target=self._query_loop, args=(self._queryable.handler,), name="bbalign-queries", daemon=True
        )
        self._query_thread.start()

    @property
    def is_open(self) -> bool:
        return self.session is not None and not self.session.is_closed()

    def stop_intake(self) -> None:
        """No new frames or queries (call before stopping the service's workers)."""
        for entity in (*self._subscribers, self._queryable):
            if entity is not None:
                entity.undeclare()  # closes the ring: the door thread's recv ends
        self._subscribers, self._queryable = [], None
        for door in self._doors:
            door.join(5.0 + self.settings.limits.door_window_s)
        self._doors = []
        if self._query_thread is not None:
            self._query_thread.join(5.0)
            self._query_thread = None

    def close(self) -> None:
        self.stop_intake()
        if self.publish in self.service.publishers:
            self.service.publishers.remove(self.publish)
        with self._lock:
            session, self.session = self.session, None
        if session is not None:
            session.close()

    # ---- the door thread and the query callback (enqueue only) ----------------------------------------------
    def _door_loop(self, ring, budget: Budget, skip: str | None) -> None:
        """Take samples from Zenoh's ring (waiting in recv releases the GIL), check them in batches and account
        the CPU time (this thread's own) spent on the ones refused against the budget: junk is what must not take
        the engine's CPU; a frame that passes costs what the fleet's own traffic costs. Samples for ``skip``'s key
        are another door's. Ends when the subscriber is undeclared."""
        batch = self.settings.limits.door_batch
        while True:
            try:
                sample = ring.recv()
            except zenoh.ZError:  # undeclared: the ring is closed
                return
            junk_s = 0.0
            for _ in range(batch):
                t0 = time.thread_time()
                try:
                    queued = self._on_frame(sample, skip)
                except Exception:  # a bug must not end the door; the message is lost, and logged
                    log.exception("the Zenoh door failed on a message")
                    queued = False
                if not queued:
                    junk_s += time.thread_time() - t0
                try:
                    sample = ring.try_recv()
                except zenoh.ZError:
                    sample = None
                if sample is None:
                    break
            budget.spend(junk_s)

    def _on_frame(self, sample: zenoh.Sample, skip: str | None = None) -> bool:
        sender = str(sample.key_expr).rsplit("/", 1)[-1]
        if sender == skip:
            return True  # the other door's sample (not junk: no budget charged)
        if len(sample.payload) > self.settings.limits.max_message_bytes:  # refused before it is even copied
            self.service.metrics.rejected.labels("zenoh", "too_large").inc()
            return False
        return self.service.submit_message(sender, sample.payload.to_bytes(), door="zenoh")

    def _query_loop(self, ring) -> None:
        """Take queries from Zenoh's ring and hand them to the service; ends when the queryable is undeclared."""
        while True:
            try:
                query = ring.recv()
            except zenoh.ZError:  # undeclared: the ring is closed
                return
            try:
                self._on_query(query)
            except Exception:  # a bug must not end the loop; the query is dropped (Zenoh answers it as final)
                log.exception("the Zenoh query door failed on a query")

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
                elif getattr(outcome, "refusal", None) is not None:  # an authenticated query: a signed Refusal
                    query.reply_err(self.service.encode_answer(outcome.refusal))
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


def ingress_limits(prefix: str, ego_id: str, limits) -> list[dict]:
    """Zenoh ``downsampling`` rules (ingress, applied per remote session in Zenoh's receive threads): each session
    may bring at most ``zenoh_frame_rate_hz`` frames and ``zenoh_query_rate_hz`` queries a second."""
    rules = []
    for messages, key, rate in (
        ("put", frames_key(prefix, "*"), limits.zenoh_frame_rate_hz),
        ("query", align_key(prefix, ego_id), limits.zenoh_query_rate_hz),
    ):
        if rate > 0:
            rules.append({"flows": ["ingress"], "messages": [messages], "rules": [{"key_expr": key, "freq": rate}]})
    return rules
