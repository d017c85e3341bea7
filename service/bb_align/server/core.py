"""The ego-side service without its doors: the gate, admission, queues, the worker pool running the engine.

The doors (Zenoh link, REST app) only hand messages over:

- ``submit_message`` (raw stream bytes, from the Zenoh door thread; what the gate would certainly refuse is refused
  there, door.py) and ``submit_query`` (a raw query payload) go to the bounded intake; the **gate** thread
  authenticates and validates them (bb_align.protocol.load_frame), so no unauthenticated or invalid message ever
  creates peer state or reaches a worker;
- ``submit_frame`` (REST /v1/frames) and ``submit_request`` (REST /v1/align) carry frames the REST door already
  loaded through the same validator, in a thread of its own.

Checked frames are admitted by the peer table (replays refused, at most ``max_peers`` senders, idle ones
evicted). Ego frames go into the cache at once (a PNG decode; their engine features are computed once, by a
worker, see cache.py); peer frames wait in per-sender latest-only queues, requests in one bounded FIFO. Workers
(at most ``settings.workers``, the only threads that run the engine) align peer frames against the cached ego
frame nearest in time; each result (success or not, never a pose from a stale ego frame) goes to the publishers
(the Zenoh link) or to the request's reply. A stream frame the gate refuses is answered only when its signature
was valid for its sender: a Refusal on that sender's results key (refusals.py).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from enum import Enum

import numpy as np

from bb_align.engine.frame import PreparedFrame
from bb_align.engine.parallel import metered
from bb_align.engine.pipeline import Aligner
from bb_align.engine.result import AlignResult
from bb_align.protocol import (
    FLEET_KEY_ID,
    JSON,
    MSGPACK,
    Frame,
    Pose,
    Refusal,
    Result,
    WireError,
    limit_env,
    load_frame,
    pack,
    setting_env,
    sign_result,
    to_json,
)

from .bandwidth import BandwidthMeter, FrameBytes
from .cache import EgoCache
from .door import Door, SignatureBudget
from .metrics import Metrics
from .peers import PeerStatus, PeerTable, process_started_at
from .refusals import RefusalNotices
from .scheduler import EGO, SIGNED, UNVERIFIED_LANE, Intake, Job, Scheduler
from .settings import Settings
from .tracks import PeerTracks

log = logging.getLogger("bb_align.server")


EGO_REFUSAL_NOTE_S = 10.0  # an ego frame refused this recently is named in peers' results without an ego frame


class ServiceReason(str, Enum):
    """Why the service could not align a peer frame at all (Result.reason; the engine's own reasons are
    bb_align.engine.FailureReason values)."""

    no_ego_frame = "no_ego_frame"  # no ego frame cached yet
    stale_ego_frame = "stale_ego_frame"  # no cached ego frame within max_ego_skew_s of the peer frame


_EGO_FEATURES = "@ego-features"  # the scheduler key of the eager ego-feature job (never a vehicle id)
_CROSSCHECK = "@crosscheck:"  # + peer id: the scheduler key of a peer's cross-check beside its track
UNVERIFIED = "(unverified)"  # metric label of messages dropped before the gate knew their sender
# One replay window per sender across both doors and both REST routes: a frame taken from the Zenoh stream is not
# accepted again as a query or by /v1/align, nor the other way round.
STREAM = REQUEST = "frames"


class Unavailable(RuntimeError):
    """The service is shutting down or overloaded; the request was not run."""


class ConfigurationError(RuntimeError):
    """The settings are not safe to start with (e.g. authentication on without a key)."""


def reported_relative_pose(ego: Frame, peer: Frame) -> np.ndarray | None:
    """T_ego_peer (4x4) as the two cars' reported poses say; None without both."""
    if ego.pose is None or peer.pose is None:
        return None
    return np.linalg.inv(ego.pose.matrix()) @ peer.pose.matrix()


def relative_prior(ego: Frame, peer: Frame) -> tuple[float, float, float] | None:
    """(tz, roll, pitch) of T_ego_peer from the two reported poses (Eq. 1's constants); None without both."""
    T = reported_relative_pose(ego, peer)
    if T is None:
        return None
    rel = Pose.from_matrix(T)
    return rel.z, rel.roll, rel.pitch


class _RateLimitedLog:
    """One log line per (door, error) per ``period_s``, saying how many were not logged in between."""

    def __init__(self, period_s: float = 10.0):
        self.period_s = period_s
        self._lock = threading.Lock()
        self._last: dict[tuple[str, str], tuple[float, int]] = {}

    def __call__(self, door: str, error: str, msg: str, *args) -> None:
        now = time.monotonic()
        with self._lock:
            t, suppressed = self._last.get((door, error), (-1e18, 0))
            if now - t < self.period_s:
                self._last[(door, error)] = (t, suppressed + 1)
                return
            self._last[(door, error)] = (now, 0)
        log.warning(msg + (f" (+{suppressed} more like it)" if suppressed else ""), *args)


class AlignService:
    def __init__(self, settings: Settings):
        problem = settings.startup_problem()
        if problem is not None:
            raise ConfigurationError(problem)
        self.settings = settings
        limits = settings.limits
        self.aligner = Aligner(settings.align)
        self.cache = EgoCache(settings.ego_cache_size)
        self.keyring = settings.auth.keyring()
        self._answer_key, self._answer_key_id = settings.auth.answer_key()
        self.scheduler = self._scheduler(settings)
        self.intake = Intake(
            limits.intake_queue,
            limits.intake_bytes,
            lanes={
                EGO: (limits.intake_ego_queue, limits.intake_bytes),
                SIGNED: (limits.intake_queue, limits.intake_bytes),
                UNVERIFIED_LANE: (limits.intake_unverified_queue, limits.intake_unverified_bytes),
            },
            fair=frozenset({SIGNED}),  # one sender's burst (or a keyed flood) pushes out its own frames first
        )
        self.meter = BandwidthMeter(settings.bandwidth_window_s)
        self.peer_table = PeerTable(
            limits.max_peers,
            limits.peer_idle_s,
            reserved=settings.ego_id,
            refuse_replays=self.keyring.required,
            new_pass_on_rewind=limits.replay,
            on_evict=self._forget,
            not_before=process_started_at() + limits.max_stamp_lead_s if limits.clock_checked else None,
        )
        self.notices = RefusalNotices(settings.ego_id, settings.refusal_notice_interval_s, limits.max_peers + 1)
        self.metrics = Metrics(
            self.meter.report,
            lambda: len(self.cache),
            self.scheduler.pending,
            lambda: len(self.peer_table),
            lambda: len(self.intake),
        )
        self.tracks = PeerTracks(self.aligner, limits.max_peers)  # bounded like the peer table, forgotten with it
        self.door, self.query_door = self._doors(settings)
        self._door_counters: dict[tuple[str, str], tuple] = {}
        self.publishers: list[Callable[[Result | Refusal], None]] = []  # results and refusal notices
        self._threads: list[threading.Thread] = []
        self._log_refusal = _RateLimitedLog()
        self._ego_refusal: tuple[float, str] | None = None  # (monotonic time, why) of the last ego frame refused

    def _doors(self, settings: Settings) -> tuple[Door, Door]:
        """The stream's door and the query door: the same checks, each its own signature budget (a query flood
        cannot spend the stream's)."""
        limits = settings.limits

        def door(channel: str, budget: SignatureBudget | None = None) -> Door:
            newest = lambda vid, key: self.peer_table.newest(vid, channel, key)  # noqa: E731
            return Door(self.keyring, limits, settings.ego_id, newest, limits.intake_recent_signatures, budget=budget)

        return door(STREAM), door(REQUEST, SignatureBudget(limits.signature_share, limits.signature_burst_s))

    def _scheduler(self, settings: Settings) -> Scheduler:
        """The newest ego frame's features go first (every tracked frame of its sweep needs them, 20-60 ms once
        per ego frame; a peer frame that finds them in the making takes the newest prepared ego frame within
        max_ego_skew_s instead of waiting, _pick_ego). Heavy jobs
        (acquisitions of peers without a track, cross-checks beside tracks) go after every tracked frame that is
        ready and use at most all workers but one: tracked frames keep one to themselves (scheduler.py)."""
        return Scheduler(
            settings.peer_queue_depth,
            settings.max_pending_requests,
            priority=frozenset({settings.ego_id, _EGO_FEATURES}),
            background_prefix=_CROSSCHECK,
            max_background=max(1, settings.workers - 1),
            heavy=self._acquires,
            light_expected=lambda: self.tracking and self.tracks.any_tracking(),
            workers=settings.workers,
            max_wait_s=settings.max_frame_wait_s,
            background_share=settings.crosscheck_share,
            on_expired=lambda job: self._count_drop(job.sender),
            on_pushed_out=self._pushed_out,
            overdue_s=settings.unmeasured_after_s if settings.align.track.enabled else None,
        )

    def _pushed_out(self, job: Job) -> None:
        """A queued request pushed out by another sender's (its sender held the most of the full request queues):
        answered 'overloaded', so a car's burst costs its own refusals (scheduler.py)."""
        e = WireError(
            503,
            "overloaded",
            f"the request queues are full and {job.sender!r} holds the most of them; retry later",
            "requests",
            self.settings.max_pending_requests,
            setting_env("max_pending_requests"),
        )
        e.counted = True
        self.metrics.rejected.labels(job.door, "overloaded").inc()
        _answer(job, e)

    def _acquires(self, sender: str) -> bool:
        """Whether a peer's next frame runs a full acquisition (tracking on, and the peer has no track)."""
        if not self.tracking or sender.startswith("@"):
            return False
        return self.tracks.state(sender) != "tracking"

    # ---- lifecycle ---------------------------------------------------------------------------------------------
    def start(self) -> None:
        self.aligner.warm_up()  # compiled loops and caches ready before the first frame
        gate = threading.Thread(target=self._gate, name="bbalign-gate", daemon=True)
        gate.start()
        self._threads.append(gate)
        for i in range(self.settings.workers):
            t = threading.Thread(target=self._work, name=f"bbalign-worker-{i}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self, timeout: float | None = None) -> None:
        """Graceful drain: refuse new messages, let the gate and the workers finish what was already accepted
        (results still go out) for up to ``timeout`` s, then answer what is left (requests: Unavailable; stream
        frames: counted as dropped) and join every thread."""
        timeout = self.settings.shutdown_timeout_s if timeout is None else timeout
        deadline = time.monotonic() + timeout
        for job in self.intake.close():
            self._never_ran(job)
        self._join(self._threads[:1], deadline)  # the gate: everything it passes on is queued
        self.scheduler.close(drain=True)
        self._join(self._threads[1:], deadline)
        for job in self.scheduler.close():
            self._never_ran(job)
        self._join(self._threads, time.monotonic() + 5.0)
        self._threads = [t for t in self._threads if t.is_alive()]
        if self._threads:
            log.warning("%d thread(s) still busy after %.0f s", len(self._threads), timeout)

    @staticmethod
    def _join(threads: list[threading.Thread], deadline: float) -> None:
        for t in threads:
            t.join(max(0.0, deadline - time.monotonic()))

    def _never_ran(self, job: Job) -> None:
        if job.reply is not None:
            _answer(job, Unavailable("the service is shutting down"))
        elif job.task == "frame":
            self._count_drop(job.sender if job.frame is not None else UNVERIFIED)

    @property
    def running(self) -> bool:
        return bool(self._threads) and all(t.is_alive() for t in self._threads)

    def encode_answer(self, answer: Result | Refusal, encoding: str = MSGPACK) -> bytes:
        """A Result (or a Refusal notice) as it leaves the service: signed with the ego's credential (or the fleet
        key), any door."""
        return sign_result(answer, self._answer_key, encoding, self._answer_key_id)

    # ---- doors -------------------------------------------------------------------------------------------------
    def submit_message(self, sender: str, data: bytes, door: str = "zenoh") -> bool:
        """A raw stream message (msgpack Frame or Signed frame) from ``sender`` (the key's last chunk, not yet
        trusted); cheap enough for a Zenoh callback. With authentication on, what the gate would certainly refuse
        is refused here (door.py), counted and never queued. True when it was queued for the gate; False when it
        was refused here or the intake is closed."""
        lane, signer = EGO if sender == self.settings.ego_id else SIGNED, None
        if self.keyring.required:  # demo: nothing is signed, lanes by the claimed sender
            try:
                lane, signer = self.door.lane(sender, data)
            except WireError as e:
                self._door_refused(sender, door, e)
                return False
        job = Job(sender, time.perf_counter(), door, data=data, nbytes=len(data))
        if signer is not None:
            job.meta["signer"] = signer
        return self._to_intake(job, lane)

    def door_dropped(self, sender: str, e: WireError) -> None:
        """A stream message the Zenoh door dropped unread (its share for refusals spent, door.DoorShare)."""
        self._door_refused(sender, "zenoh", e)

    def _door_refused(self, sender: str, door: str, e: WireError) -> None:
        """Count and (rate-limited) log a refusal at the door: per message a flood pays only this, so the
        labelled counters are looked up once per (door, error)."""
        counters = self._door_counters.get((door, e.error))
        if counters is None:
            counters = (self.metrics.rejected.labels(door, e.error), self.metrics.door_refused.labels(e.error))
            self._door_counters[(door, e.error)] = counters
        for c in counters:
            c.inc()
        if sender == self.settings.ego_id:
            self._ego_refusal = (time.monotonic(), f"{e.error}: {e.detail}")
        self._log_refusal(door, e.error, "refused a message from %r on %s: %s", sender, door, e)

    def submit_query(
        self, reply: Callable[[object], None], data: bytes, door: str = "zenoh", refused: WireError | None = None
    ) -> bool:
        """A raw query payload to align and answer through ``reply`` (called once, with a Result or an
        exception); ``refused``: the door already knows the answer is this error. With authentication on, the
        query door (door.py: cheap checks first, the signature under its own budget) refuses here, on the
        caller's thread: a refused query is answered at once with an unsigned error and never waits in the
        intake, so a keyless query flood takes no place there and makes the service sign nothing."""
        if refused is None and self.keyring.required:
            try:
                signer = self.query_door.query(data)
            except WireError as e:
                self._door_refused("", door, e)
                try:
                    reply(e)
                except Exception:
                    log.info("a refused query could not be answered")
                return False
            job = Job("", time.perf_counter(), door, data=data, nbytes=len(data), reply=reply, meta={"signer": signer})
            return self._to_intake(job, SIGNED)
        job = Job(
            "",
            time.perf_counter(),
            door,
            data=data,
            nbytes=len(data),
            reply=reply,
            meta={"refused": refused} if refused is not None else {},
        )
        return self._to_intake(job, SIGNED if refused is None else UNVERIFIED_LANE)

    def submit_frame(
        self, frame: Frame, nbytes: int, encoding: str = MSGPACK, door: str = "rest", received: float | None = None
    ) -> bool:
        """A checked stream frame (REST /v1/frames). Raises WireError when its sender is refused."""
        job = Job(
            frame.vehicle_id, received or time.perf_counter(), door, frame=frame, encoding=encoding, nbytes=nbytes
        )
        try:
            self._admit(job, STREAM)
        except WireError as e:
            self._refused(job, e)
            raise
        return self._accept_stream(job)

    def submit_request(
        self,
        reply: Callable[[object], None],
        *,
        frame: Frame,
        ego: Frame | None = None,
        nbytes: int = 0,
        encoding: str = MSGPACK,
        door: str = "rest",
        received: float | None = None,
    ) -> bool:
        """A checked frame (REST /v1/align) to align and answer through ``reply``. Raises WireError when its
        sender is refused; False when the request queue is full (the caller answers 'overloaded')."""
        job = Job(
            frame.vehicle_id,
            received or time.perf_counter(),
            door,
            frame=frame,
            ego=ego,
            encoding=encoding,
            reply=reply,
        )
        job.nbytes = len(_encode(frame, encoding))  # the peer frame alone, as it would go on the air
        try:
            if ego is not None:  # an inline ego frame: the ego's own, and replay-checked like any other
                if ego.vehicle_id != self.settings.ego_id:
                    raise WireError(
                        422,
                        "invalid",
                        f"the ego frame's vehicle_id {ego.vehicle_id!r} is not this service's ego id",
                        "ego.vehicle_id",
                        self.settings.ego_id,
                        setting_env("ego_id"),
                    )
                self.peer_table.admit(ego, REQUEST)
                self._count_inline_ego(ego, encoding)
            self._admit(job, REQUEST)
        except WireError as e:
            self._refused(job, e)
            raise
        return self._queue_request(job)

    def _to_intake(self, job: Job, lane: str) -> bool:
        pushed_out = self.intake.put(job, lane)
        for old in pushed_out:
            if old is job and self.intake.closed:
                if job.reply is not None:
                    _answer(job, Unavailable("the service is shutting down"))
                return False
            if old.reply is not None:
                _answer(
                    old,
                    WireError(
                        503,
                        "overloaded",
                        "the intake queue is full, retry later",
                        "intake",
                        self.settings.limits.intake_queue,
                        limit_env("intake_queue"),
                    ),
                )
                self.metrics.rejected.labels(old.door, "overloaded").inc()
            elif old.meta.get("signer") in (old.sender, FLEET_KEY_ID) and old.sender in self.peer_table:
                self._count_drop(old.sender, "intake_dropped")  # only a drop of a frame signed for that id
            else:
                self._count_drop(UNVERIFIED)
            if not (old is job and self.intake.closed):
                self.metrics.intake_dropped.labels(old.meta.get("lane", UNVERIFIED_LANE)).inc()
        return True

    # ---- the gate (one thread): authenticate, validate, admit, queue -----------------------------------------
    def _gate(self) -> None:
        limits, last_sweep = self.settings.limits, time.monotonic()
        while True:
            job = self.intake.get(timeout=1.0)
            if time.monotonic() - last_sweep > 1.0:
                self.peer_table.sweep()
                last_sweep = time.monotonic()
            if job is None:
                if self.intake.closed:
                    return
                continue
            try:
                if "refused" in job.meta:
                    raise job.meta["refused"]
                # a stream frame's PNG data is inflated by the worker: a busy car's frames are mostly replaced unread
                checks = dict(keyring=self.keyring, now=time.time(), inflate_png=job.reply is not None)
                job.frame = load_frame(job.data, limits, job.encoding, **checks)
                job.data = None
                if job.reply is None:
                    if job.frame.vehicle_id != job.sender:
                        raise WireError(
                            422,
                            "invalid",
                            f"vehicle_id {job.frame.vehicle_id!r} differs from the key's {job.sender!r}",
                            "vehicle_id",
                        )
                    self._admit(job, STREAM)
                    self._accept_stream(job)
                else:
                    job.sender = job.frame.vehicle_id
                    self._admit(job, REQUEST)
                    if not self._queue_request(job):
                        _answer(
                            job,
                            WireError(
                                503,
                                "overloaded",
                                "the request queue is full, retry later",
                                "requests",
                                self.settings.max_pending_requests,
                                setting_env("max_pending_requests"),
                            ),
                        )
            except WireError as e:
                self._refused(job, e)
                if job.reply is not None:
                    e.refusal = self.notices.for_query(job, e, limits)  # signed when the query was authenticated
                    _answer(job, e)
                else:
                    self._tell_sender(job, e)
            except Exception as e:  # a bug must not stop the gate; the message is refused and logged
                log.exception("the gate failed on a message from %s", job.sender or "?")
                self.metrics.rejected.labels(job.door, "internal").inc()
                if job.reply is not None:
                    _answer(job, e)

    def _admit(self, job: Job, channel: str) -> None:
        """Track the sender (replays and a full table refused) and account the message's bytes."""
        job.meta["new_pass"] = self.peer_table.admit(job.frame, channel)
        if job.meta["new_pass"] and job.frame.vehicle_id == self.settings.ego_id:
            self.tracks.clear()  # the ego's recording started over: every track starts afresh
        elif job.meta["new_pass"]:
            self.tracks.forget(job.frame.vehicle_id)  # a peer's recording played again: its track starts afresh
        self.meter.record_message(job.frame.vehicle_id, job.nbytes)

    def _count_inline_ego(self, ego: Frame, encoding: str) -> None:
        """An admitted ego frame sent inline in /v1/align: its bytes count under the ego id like a streamed ego
        frame's (the frame alone, as it would go on the air, as the request's peer frame is counted)."""
        nbytes = len(_encode(ego, encoding))
        self.meter.record_message(ego.vehicle_id, nbytes)
        self.meter.record_frame(ego.vehicle_id, FrameBytes.of(ego, nbytes, encoding))

    def _tell_sender(self, job: Job, e: WireError) -> None:
        """A refused stream frame signed for its sender: that sender learns why on its results key."""
        notice = self.notices.notice(job, e, self.settings.limits)
        if notice is None:
            return
        self.metrics.refusal_notices.labels(e.error).inc()
        self._publish(notice)

    def _publish(self, answer: Result | Refusal) -> None:
        for publish in self.publishers:
            try:
                publish(answer)
            except Exception:
                log.exception("publishing an answer failed")

    def _refused(self, job: Job, e: WireError) -> None:
        e.counted = True  # the REST door counts the refusals it raises itself, not these again
        self.metrics.rejected.labels(job.door, e.error).inc()
        if job.sender == self.settings.ego_id and job.reply is None:  # an ego stream frame
            self._ego_refusal = (time.monotonic(), f"{e.error}: {e.detail}")
        self._log_refusal(job.door, e.error, "refused a message from %r on %s: %s", job.sender or "?", job.door, e)

    def _ego_refusal_notes(self) -> list[str]:
        """For a peer's result without a usable ego frame: why, when the ego's own frames were refused lately (a
        peer cannot see the service's log)."""
        last = self._ego_refusal
        if last is None or time.monotonic() - last[0] > EGO_REFUSAL_NOTE_S:
            return []
        return [
            f"the ego's own frames were refused ({time.monotonic() - last[0]:.1f} s ago: {last[1]}); the ego signs "
            "its frames with the service's credential (auth.credential)"
        ]

    def _accept_stream(self, job: Job) -> bool:
        """An admitted stream frame: the ego's goes into the cache at once (a PNG decode, on the caller's thread,
        so the cache stays current however busy the workers are); a peer's waits in its latest-only queue."""
        ego = job.frame.vehicle_id == self.settings.ego_id
        if not ego:
            self._hear(job.frame, ego)
            return self._queue_frame(job)
        if self.intake.closed and job.door == "rest":
            return False
        frame = job.frame
        if job.meta.get("new_pass"):  # the ego's recording started over (replay profile)
            self.cache.rewind(frame.stamp)
        self.metrics.frames.labels(job.door, "ego").inc()
        self.meter.record_frame(frame.vehicle_id, FrameBytes.of(frame, job.nbytes, job.encoding))
        try:
            entry = self.cache.add(frame, frame.bev_image(self.settings.limits))  # corrupt images never enter
        except WireError:
            self.peer_table.update(frame.vehicle_id, lambda e: setattr(e.status, "failed", e.status.failed + 1))
            raise
        self._hear(frame, ego)
        self.peer_table.update(
            frame.vehicle_id, lambda e: setattr(e.status, "frames_accepted", e.status.frames_accepted + 1)
        )
        # Features of the newest ego frame, computed when a worker is free (or by the first peer needing them).
        self.scheduler.put_frame(
            Job(_EGO_FEATURES, time.perf_counter(), job.door, task="ego_features", meta={"entry": entry}), depth=1
        )
        return True

    def _hear(self, frame: Frame, ego: bool) -> None:
        """A stream frame's odometry, for its car's odometry check whether or not a worker steps the frame."""
        if self.tracking and frame.odometry is not None:
            self.tracks.hear(frame.vehicle_id, frame.stamp, frame.odometry.matrix(), ego)

    def _queue_frame(self, job: Job) -> bool:
        dropped = self.scheduler.put_frame(job)
        if dropped is job:  # closed
            self._count_drop(job.sender)
            return False
        self.peer_table.update(job.sender, lambda e: setattr(e.status, "frames_accepted", e.status.frames_accepted + 1))
        if dropped is not None:
            self._count_drop(dropped.sender)
        return True

    def _queue_request(self, job: Job) -> bool:
        if not self.scheduler.put_request(job):
            self.metrics.rejected.labels(job.door, "overloaded").inc()
            return False
        return True

    def _count_drop(self, sender: str, counter: str = "frames_dropped") -> None:
        self.metrics.dropped.labels(sender).inc()
        self.peer_table.update(sender, lambda e: setattr(e.status, counter, getattr(e.status, counter) + 1))

    def _forget(self, vehicle_id: str, entry) -> None:
        """An evicted sender: its queue, bandwidth tally and metric labels go too."""
        for _ in self.scheduler.forget(vehicle_id):
            self.metrics.dropped.labels(UNVERIFIED).inc()  # its own label is about to go
        self.meter.forget(vehicle_id)
        self.tracks.forget(vehicle_id)
        self.metrics.forget_peer(vehicle_id, entry.outcomes)
        log.info("forgot peer %s (idle for more than %.0f s)", vehicle_id, self.settings.limits.peer_idle_s)

    # ---- queries -----------------------------------------------------------------------------------------------
    def peers(self) -> dict[str, PeerStatus]:
        status = {p: s for p, s in self.peer_table.statuses().items() if p != self.settings.ego_id}
        for p, s in status.items():
            s.bandwidth = self.meter.peer(p)
        return dict(sorted(status.items()))

    # ---- workers -----------------------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            job = self.scheduler.get()
            if job is None:
                return
            try:
                with metered() as cpu:  # charged to the car: an acquisition keeps both cores busy
                    self._handle(job)
                job.cpu_s = cpu.seconds
            finally:  # only after the answer left: the sender's next frame cannot overtake it
                self.scheduler.done(job)

    def _handle(self, job: Job) -> None:
        """Run one job and send its answer (a request's reply, or a stream frame's published result)."""
        try:
            outcome = self._run(job)
        except WireError as e:
            self._refused(job, e)
            outcome = e
        except Exception as e:  # a bug must not kill the worker; the request still gets an answer
            log.exception("job from %s failed", job.sender or "?")
            outcome = e
        if isinstance(outcome, Exception) and job.task == "frame":
            self.peer_table.update(job.sender, lambda e: setattr(e.status, "failed", e.status.failed + 1))
            if job.reply is None:  # a stream frame still gets a result, saying that it failed
                outcome = self._failed(job, outcome)
        if job.reply is not None:
            _answer(job, outcome)
        elif isinstance(outcome, Result):
            self._publish(outcome)

    def _run(self, job: Job) -> Result | None:
        if job.task == "ego_features":  # a worker already computing them for a peer frame is not waited for
            job.meta["entry"].features(self._prepare_entry, wait=False)
            return None
        if job.task == "crosscheck":
            self._crosscheck(**job.meta)
            return None
        self.metrics.frames.labels(job.door, "peer").inc()
        return self._align(job.frame, job)

    def _failed(self, job: Job, error: Exception) -> Result:
        """The result of a stream frame whose processing raised: success=False, never a pose."""
        f = job.frame
        reason = "invalid_frame" if isinstance(error, WireError) else "internal_error"
        return self._finish(
            job,
            Result(
                ego_id=self.settings.ego_id,
                peer_id=f.vehicle_id,
                peer_seq=f.seq,
                peer_stamp=f.stamp,
                success=False,
                reason=reason,
                notes=[f"{type(error).__name__}: {error}"[:300]],
                bytes_received=job.nbytes,
            ),
        )

    @property
    def tracking(self) -> bool:
        return self.settings.align.track.enabled

    def _prepare_entry(self, entry) -> PreparedFrame:
        """An ego frame: with tracking, only what a tracked frame uses (the refinement's cloud, the landscape's
        fields; MIM and descriptors are built if and when an acquisition needs them); without, everything an
        alignment against it needs."""
        prepared = self._prepare(entry.frame, "prepare_ego", entry.bev)
        if self.tracking:
            return self.aligner.ready_to_track(prepared)
        return self.aligner.warm(prepared)

    def _prepare(self, frame: Frame, step: str, bev=None) -> PreparedFrame:
        t0 = time.perf_counter()
        bev = bev if bev is not None else frame.bev_image(self.settings.limits)
        t_png = (time.perf_counter() - t0) * 1e3
        prepared = self.aligner.prepare(bev, frame.boxes_array(), features=not self.tracking)
        prepared = dataclasses.replace(
            prepared, num_points=frame.num_points, timings_ms={"decode_png": t_png, **prepared.timings_ms}
        )
        self.metrics.engine.labels(step).observe(time.perf_counter() - t0)
        return prepared

    def _align(self, peer: Frame, job: Job) -> Result:
        """Align one peer frame against the given ego frame, or the cached one nearest in time."""
        s = self.settings
        fb = FrameBytes.of(peer, job.nbytes, job.encoding)
        self.meter.record_frame(peer.vehicle_id, fb)
        timings = {"queue_wait": (time.perf_counter() - job.received) * 1e3}
        base = dict(
            ego_id=s.ego_id,
            peer_id=peer.vehicle_id,
            peer_seq=peer.seq,
            peer_stamp=peer.stamp,
            bytes_received=fb.total,
            raw_points_bytes=fb.raw_points,
            ratio_vs_points=fb.total / fb.raw_points if fb.raw_points else None,
        )

        if (unmeasured := self._unmeasured(peer, job, base, timings)) is not None:
            return unmeasured
        newest_ego = max(self.cache.stamps(), default=None)
        if job.ego is None and newest_ego is not None and newest_ego >= peer.stamp:
            # The ego stream is already past this sweep, so no nearer ego frame can come: when none is usable,
            # answer at once, before any engine work. Otherwise the ego frame of this sweep may still be in
            # flight (it travels in another Zenoh session): prepare the peer first and decide after.
            picked = self._pick_ego(peer, job, base, timings, wait=False)
            if isinstance(picked, Result):
                return picked
        peer_prep = self._prepare(peer, "prepare_peer")
        if job.ego is not None:
            ego_frame, ego_prep = job.ego, self._prepare(job.ego, "prepare_ego")
        else:  # look again: a nearer ego frame may have come in while the peer was prepared. With none within the
            # skew yet, wait briefly for it: a tracked peer frame is prepared in a few ms, sooner than the ego frame
            # of its sweep may land (before tracking, the peer's MIM took longer than that)
            self.cache.wait_for(peer.stamp, s.ego_same_sweep_s, s.ego_wait_s)
            picked = self._pick_ego(peer, job, base, timings, wait=True)
            if isinstance(picked, Result):
                return picked
            ego_frame, ego_prep = picked
        base.update(ego_seq=ego_frame.seq, ego_stamp=ego_frame.stamp, ego_skew_s=peer.stamp - ego_frame.stamp)

        prior = relative_prior(ego_frame, peer)
        tz, roll, pitch = prior if prior is not None else (0.0, 0.0, 0.0)
        t0 = time.perf_counter()
        T_prior = reported_relative_pose(ego_frame, peer) if self.settings.use_pose_prior else None
        if self.tracking:
            res = self._follow(ego_frame, ego_prep, peer, peer_prep, T_prior, tz, roll, pitch)
        else:
            res = self.aligner.align(ego_prep, peer_prep, tz=tz, roll=roll, pitch=pitch, T_prior=T_prior)
        self.metrics.engine.labels("align").observe(time.perf_counter() - t0)
        timings.update({f"peer_{k}": v for k, v in peer_prep.timings_ms.items()}, **res.timings_ms)
        return self._finish(job, _from_engine(res, base, prior is not None, timings))

    def _unmeasured(self, peer: Frame, job: Job, base: dict, timings: dict) -> Result | None:
        """A tracked frame that waited past ``unmeasured_after_s`` for a worker, answered from its track's stream
        without measuring it (no image decoded, no ego frame prepared); None: measure it (the track says the stream
        cannot answer it validly, or it did not wait that long, or it has no odometry or ego frame of its time)."""
        s, waited = self.settings, time.perf_counter() - job.received
        if s.unmeasured_after_s is None or waited < s.unmeasured_after_s or job.reply is not None:
            return None
        if not self.tracking or peer.odometry is None or self.tracks.state(peer.vehicle_id) != "tracking":
            return None
        entry = self.cache.nearest(peer.stamp)
        if entry is None or entry.frame.odometry is None or abs(peer.stamp - entry.stamp) > s.max_ego_skew_s:
            return None
        peer.check_image(s.limits)  # not decoded, but never answered unchecked: a bad image is refused as measured
        ego = entry.frame
        prior = relative_prior(ego, peer)
        tz, roll, pitch = prior if prior is not None else (0.0, 0.0, 0.0)
        track = self.tracks.get(peer.vehicle_id)
        with track.lock:
            track.observe(self.tracks.ego_heard, ego.stamp, peer.stamp)
            res = track.follower.unmeasured(
                peer.stamp,
                O_ego=ego.odometry.matrix(),
                O_peer=peer.odometry.matrix(),
                ego_stamp=ego.stamp,
                tz=tz,
                roll=roll,
                pitch=pitch,
            )
        if res is None:
            return None
        res.notes.insert(
            0,
            f"not measured: the frame waited {waited * 1e3:.0f} ms for a worker (unmeasured_after_s "
            f"{s.unmeasured_after_s:g})",
        )
        self.metrics.engine.labels("unmeasured").observe(time.perf_counter() - job.received - waited)
        base.update(ego_seq=ego.seq, ego_stamp=ego.stamp, ego_skew_s=peer.stamp - ego.stamp)
        return self._finish(job, _from_engine(res, base, prior is not None, timings | res.timings_ms))

    def _follow(self, ego_frame: Frame, ego_prep, peer: Frame, peer_prep, T_prior, tz, roll, pitch) -> AlignResult:
        """The peer's track, one step: acquisition when it has none, else the refinement from its prediction."""
        odometry = ego_frame.odometry is not None and peer.odometry is not None
        O_ego = ego_frame.odometry.matrix() if odometry else None
        O_peer = peer.odometry.matrix() if odometry else None
        aside = self.settings.crosscheck_beside_track and odometry  # without odometry it runs in the step
        track = self.tracks.get(peer.vehicle_id)
        with track.lock:
            if odometry:
                track.observe(self.tracks.ego_heard, ego_frame.stamp, peer.stamp)
            r = track.follower.step(
                ego_prep,
                peer_prep,
                peer.stamp,
                O_ego=O_ego,
                O_peer=O_peer,
                T_prior=T_prior,
                tz=tz,
                roll=roll,
                pitch=pitch,
                crosscheck=not aside,
                ego_stamp=ego_frame.stamp,
            )
            epoch = track.follower.begin_crosscheck(peer.stamp) if aside else None
        if epoch is not None:  # a job of its own: the peer's next frames are tracked meanwhile, not queued behind
            meta = dict(track=track, epoch=epoch, ego=ego_prep, peer=peer_prep, O_ego=O_ego, O_peer=O_peer)
            meta.update(T_prior=T_prior, tz=tz, roll=roll, pitch=pitch)
            job = Job(_CROSSCHECK + peer.vehicle_id, time.perf_counter(), "track", task="crosscheck", meta=meta)
            self.scheduler.put_frame(job, depth=1)
        return r

    def _crosscheck(self, track, epoch, ego, peer, O_ego, O_peer, T_prior, tz, roll, pitch) -> None:
        """A periodic cross-check run beside a peer's track: the full acquisition of an earlier frame pair, then
        applied to the track (fused, or the track dropped; the peer's next answer says so)."""
        t0 = time.perf_counter()
        r = track.follower.crosscheck(ego, peer, T_prior=T_prior, tz=tz, roll=roll, pitch=pitch)
        with track.lock:
            event = track.follower.finish_crosscheck(epoch, r, O_ego, O_peer)
        self.metrics.engine.labels("crosscheck").observe(time.perf_counter() - t0)
        if event:
            log.info("cross-check: %s", event)

    def _pick_ego(self, peer: Frame, job: Job, base: dict, timings: dict, wait: bool):
        """(ego frame, its features) nearest in time to the peer frame, or a failed Result saying why."""
        s = self.settings
        entry = self.cache.nearest(peer.stamp)
        if entry is None:
            return self._finish(
                job,
                Result(
                    **base,
                    success=False,
                    reason=ServiceReason.no_ego_frame.value,
                    timings_ms=timings,
                    notes=self._ego_refusal_notes(),
                ),
            )
        skew = peer.stamp - entry.stamp
        if abs(skew) > s.max_ego_skew_s:
            return self._finish(
                job,
                Result(
                    **base,
                    ego_seq=entry.frame.seq,
                    ego_stamp=entry.stamp,
                    ego_skew_s=skew,
                    success=False,
                    reason=ServiceReason.stale_ego_frame.value,
                    timings_ms=timings,
                    notes=[
                        f"nearest ego frame is {abs(skew):.3f} s away, the limit is {s.max_ego_skew_s} s",
                        *self._ego_refusal_notes(),
                    ],
                ),
            )
        if not wait:
            return entry.frame, None
        if not entry.ready and (s.prefer_prepared_ego or (entry.busy and self.scheduler.backlog())):
            # (busy, with other work waiting: another worker is preparing the nearest one right now; waiting for it
            # left both workers idle behind one ego preparation each sweep, 16 peers: 98 ms p50 of every result,
            # issue 47. With nothing else waiting, the wait costs no one and the nearest frame is used.)
            # An ego frame already prepared and within the skew saves a whole prepare (the result names the
            # ego frame it used): under load the ego stream is then prepared only as often as peers need it.
            entry = self.cache.nearest_ready(peer.stamp, s.max_ego_skew_s) or entry
        t0 = time.perf_counter()
        prepared = entry.features(self._prepare_entry)
        timings["ego_features"] = (time.perf_counter() - t0) * 1e3  # waited for, or computed here
        return entry.frame, prepared

    def _finish(self, job: Job, result: Result) -> Result:
        latency_s = time.perf_counter() - job.received
        result = result.model_copy(update={"latency_ms": latency_s * 1e3})
        outcome = "success" if result.success else result.reason
        self.metrics.latency.labels(job.door).observe(latency_s)

        def record(entry) -> None:
            entry.status.last_result = result
            entry.status.results += 1
            entry.outcomes.add(outcome)

        if self.peer_table.update(result.peer_id, record):  # an evicted peer leaves no labels behind
            self.metrics.alignments.labels(result.peer_id, outcome).inc()
        return result


def _answer(job: Job, outcome: object) -> None:
    """Hand a request its answer; a caller that is gone (e.g. a REST request that timed out) is not an error."""
    try:
        job.reply(outcome)
    except Exception as e:
        log.info("a request from %s could not be answered (%s: %s)", job.sender or "?", type(e).__name__, e)


def _encode(frame: Frame, encoding: str) -> bytes:
    return to_json(frame) if encoding == JSON else pack(frame)


# The wire Result's fields that the engine's result serialises (AlignResult.to_dict) as they are.
_ENGINE_FIELDS = (
    "success",
    "reason",
    "yaw_deg",
    "tx",
    "ty",
    "T_ego_peer",
    "inliers_bv",
    "inliers_box",
    "matches_bv",
    "box_pairs",
    "confidence",
    "stage2_applied",
    "covariance",
    "track_state",
    "track_event",
    "notes",
)


def _from_engine(res: AlignResult, base: dict, prior_used: bool, timings: dict[str, float]) -> Result:
    d = res.to_dict()
    return Result(
        **base,
        **{k: d[k] for k in _ENGINE_FIELDS},
        prior_used=prior_used,
        source=res.source if res.track_state is not None and res.source != "none" else None,  # "none": no pose
        timings_ms={k: float(v) for k, v in timings.items()},
    )
