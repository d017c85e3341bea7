"""The service's Zenoh door.

- subscriber ``<prefix>/frames/*``: every car's frames; the key's last chunk is the sender's vehicle id (the ego
  id's frames fill the ego cache, all others are aligned). Samples wait in Zenoh's own bounded FIFO
  (``limits.door_queue``; pushing into it needs no Python) for one door thread, which checks them
  (bb_align.server.door) within a CPU share for what it refuses (``limits.door_share`` of a core, door.DoorShare):
  past it, large messages under key chunks refused lately or never accepted are dropped unread and the rest read
  as they come, so junk can take no more than that share from the engine and a forged 1 MB frame never holds up
  the cars' frames (a flood of small junk fast enough to spend the share meets waits of 1 ms at most, and Zenoh's
  push-back on the senders' links). A Python callback per sample could not be bounded: each one takes the GIL;
- Zenoh's receive threads: a sample waiting for a place in the full FIFO holds the receive thread of its
  session's link (that is the push-back); Zenoh has 2 by default, so two flooding sessions left no thread to read
  the cars' links (issue 31, F7: measured, docs/security.md, Floods). The service takes at most
  ``limits.zenoh_max_sessions`` sessions and gives Zenoh one receive thread more (``ZENOH_RUNTIME``, set before
  the process's first Zenoh session unless the operator set it), so a link is always read;
- publisher ``<prefix>/poses/<ego_id>/<peer_id>``: one msgpack Result per aligned peer frame, and a Refusal for a
  refused stream frame whose signature was valid for that peer (core.py, refusals.py);
- queryable ``<prefix>/align/<ego_id>``: a query carrying a peer frame is answered with a Result (or an error
  reply: a signed Refusal when the query was authenticated, else an ErrorBody). Queries wait in Zenoh's own
  bounded FIFO (``limits.query_queue``) for one thread of ours, which hands them to the intake.

The door and the query callback only hand bytes to the service's intake; the gate thread authenticates and
validates them; replies and publications happen on the gate and worker threads. Connecting never gives up (a
router restart is survived); Zenoh's own reassembly limit (the message limit + 64 KiB) drops far larger messages
before they are assembled (a backstop: measured here, 8 MiB dropped by Zenoh, 5-6 MiB reach the door's size
check).
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import threading
import time

import zenoh

from bb_align.protocol import ErrorBody, Refusal, Result, WireError, align_key, frames_key, pack, poses_key

from .core import AlignService, Unavailable
from .door import DoorShare
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
        self._door: threading.Thread | None = None
        self._query_thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def align_key(self) -> str:
        return align_key(self.prefix, self.settings.ego_id)

    def open(self) -> None:
        limits = self.settings.limits
        runtime = reserve_receive_threads(limits.zenoh_max_sessions)
        if "rx" not in runtime:
            log.warning(
                "ZENOH_RUNTIME=%s sets no receive threads (rx): Zenoh keeps 2, and two flooding sessions can leave "
                "the cars' links unread (docs/security.md, Floods)",
                runtime,
            )
        cfg = self.settings.zenoh.to_zenoh_config()
        cfg.insert_json5("transport/unicast/max_sessions", json.dumps(limits.zenoh_max_sessions))
        self.session = zenoh.open(cfg)
        self.service.publishers.append(self.publish)
        fifo = zenoh.handlers.FifoChannel(limits.door_queue)
        self._subscriber = self.session.declare_subscriber(frames_key(self.prefix, "*"), fifo)
        share = DoorShare(limits.door_share, limits.door_burst_s, limits.door_unread_bytes)
        self.door_share = share
        self.service.metrics.door_throttled.set_function(lambda: share.throttled_s)
        self._door = threading.Thread(
            target=self._door_loop,
            args=(self._subscriber.handler, share, lambda: self.service.door.signature_cpu_s),
            name="bbalign-door",
            daemon=True,
        )
        self._door.start()
        # Queries wait in a bounded FIFO for a thread of ours, as frames do: a Python callback would be fed through
        # Zenoh's unbounded channel to its own thread (measured: a keyless 4 MB query flood grew RSS by 1.1 GB)
        self._queryable = self.session.declare_queryable(self.align_key, zenoh.handlers.FifoChannel(limits.query_queue))
        self._query_thread = threading.Thread(
            target=self._query_loop, args=(self._queryable.handler,), name="bbalign-queries", daemon=True
        )
        self._query_thread.start()

    @property
    def is_open(self) -> bool:
        return self.session is not None and not self.session.is_closed()

    def stop_intake(self) -> None:
        """No new frames or queries (call before stopping the service's workers)."""
        for entity in (self._subscriber, self._queryable):
            if entity is not None:
                entity.undeclare()  # closes the FIFO: the door thread's recv ends
        self._subscriber = self._queryable = None
        if self._door is not None:
            self._door.join(5.0)
            self._door = None
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
    def _door_loop(self, fifo, share: DoorShare, signature_cpu=lambda: 0.0) -> None:
        """Take samples from Zenoh's FIFO one at a time (waiting in recv releases the GIL) and account the CPU time
        (this thread's own, signature checks left out: they have their own ``SignatureBudget``) of each one refused
        against the door's share (``DoorShare``), which refuses and never pauses the door for it: once the share
        is spent, a message under a key chunk refused lately or never accepted is dropped before it is even copied
        out of Zenoh, and every other is read as it comes. Paid by sleeping instead (the door's earlier
        ``Budget``), each forged 1 MB frame (~2 ms: its copy out of Zenoh, its envelope decoded) slept ~110 ms at a
        0.02 share, and the other cars' frames waited behind it in Zenoh's FIFO: 0.47 of their results under a
        full-speed forgery (issue 47). One message at a time, never a batch (issue 31, F7: a batch bought one long
        pause and lost the sample taken last). Ends when the subscriber is undeclared."""
        name_os_thread("bbalign-door")
        while True:
            try:
                sample = fifo.recv()
            except zenoh.ZError:  # undeclared: the FIFO is closed
                return
            t0, sig0 = time.thread_time(), signature_cpu()
            sender = str(sample.key_expr).rsplit("/", 1)[-1]
            if not share.admit(sender, len(sample.payload)):
                self.service.door_dropped(sender, share.error())
                share.drop(time.thread_time() - t0)
                continue
            try:
                queued = self._on_frame(sender, sample)
            except Exception:  # a bug must not end the door; the message is lost, and logged
                log.exception("the Zenoh door failed on a message")
                queued = False
            share.spent(sender, max(0.0, time.thread_time() - t0 - (signature_cpu() - sig0)), queued)

    def _on_frame(self, sender: str, sample: zenoh.Sample) -> bool:
        if len(sample.payload) > self.settings.limits.max_message_bytes:  # refused before it is even copied
            self.service.metrics.rejected.labels("zenoh", "too_large").inc()
            return False
        return self.service.submit_message(sender, sample.payload.to_bytes(), door="zenoh")

    def _query_loop(self, fifo) -> None:
        """Take queries from Zenoh's FIFO and hand them to the service; ends when the queryable is undeclared."""
        name_os_thread("bbalign-query")
        while True:
            try:
                query = fifo.recv()
            except zenoh.ZError:  # undeclared: the FIFO is closed
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


def reserve_receive_threads(max_sessions: int) -> str:
    """Give Zenoh's receive runtime one worker thread more than the sessions it may take (a session blocked on the
    door's full FIFO holds one; with fewer threads than flooding sessions no link is read). Takes effect when set
    before the process's first Zenoh session (the runtime starts with it); an operator's ``ZENOH_RUNTIME`` is
    kept. Returns the value in force."""
    return os.environ.setdefault("ZENOH_RUNTIME", f"(rx: (worker_threads: {max_sessions + 1}))")


def name_os_thread(name: str) -> None:
    """Name the calling thread in the OS too (``top -H``, ``/proc/<pid>/task/*/comm``; Linux, 15 bytes), so the
    door's CPU time can be told from the engine's and from Zenoh's own threads (rx-N, tx-N). Elsewhere a no-op."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(15, name.encode()[:15], 0, 0, 0)  # 15: PR_SET_NAME
    except (OSError, AttributeError):
        pass
