"""Work queues of the service: latest-only per sender, bounded request queues, the engine's time fair per car,
heavy jobs capped.

Stream frames (Zenoh ``frames/*``, REST ``/v1/frames``) wait in a per-sender queue of ``depth`` entries (1:
latest only); a newer frame pushes the oldest out and the push reports it as dropped. Requests (REST
``/v1/align``, Zenoh queries) must each be answered, so they wait in a FIFO per sender, ``max_requests`` in all;
when full, a request of a sender holding fewer than the one holding most pushes out that one's newest (answered
"overloaded", ``on_pushed_out``), otherwise it is refused. ``priority`` senders go first; among the others a
worker takes the ready one whose car has had the least of the workers' time lately (``usage``: the CPU seconds
of its stream frames, requests and cross-checks together, their engine threads included, as the worker measured
them (``Job.cpu_s``; else the job's wall time), halving every ``half_life_s``), in order of readiness
among equals. A car's next request also waits, although a worker is free, while another car active in the
last ``active_s`` had less of the workers' time by more than ``fair_slack_s`` (frames are never held: they come
at the car's own rate). So both doors feed one fair schedule: a car's burst of REST requests waits behind the
other cars' frames, and costs its own latency and refusals, not the other cars' results (issue 47: served one
request per round-robin turn, 8 threads posting one car's frames took 54 % of the engine and the other cars kept
0.61-0.63 of their results). A sender's frames are handled by one worker at a time, so its results come out in
order; so are its requests (one car's burst holds one worker at most, the others stay free for the other cars).

Heavy jobs (a peer without a track: a full acquisition, ~0.3-0.5 s; a track's cross-check, keys starting with
``background_prefix``; whatever ``heavy(key)`` says at the moment a worker looks) take their turn in the same
round-robin as light ones (a tracked frame, ~20-30 ms; ego features), but at most ``max_background`` of them run
at once (all workers but one; every worker while no peer is tracked, ``light_expected``): the other workers are
left to the light jobs, so a tracked frame never waits behind an acquisition, and an acquisition still gets a
worker however many tracked frames are waiting. This is
what keeps the service out of congestion collapse (issue 47): served in plain readiness order, 16 peers' frames
waited behind each other's acquisitions until their tracks ran out (``max_gap_s``) and every frame became an
acquisition again (results fell from 15.5/s with 8 peers to 4.0/s with 16, measured, docs/performance.md).
When the light frames' turn comes, one that waited longer than ``overdue_s`` (when set: the service's
unmeasured_after_s, after which it answers a tracked frame from its track's stream in a few ms) goes before the
fresh ones, in the same fair order: at capacity with unsynchronised peers the car that had used the most saw its
frame passed over by every newer frame of the others until its next one pushed it out. A frame that waited
longer than ``max_wait_s`` (when set) is dropped before any work (reported through ``on_expired``): for
deployments where an answer that late is of no use.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

_REQUEST = "@request"  # a ready key (_REQUEST, sender): that sender's requests


@dataclass
class Job:
    sender: str  # vehicle id (from the Zenoh key or the decoded frame)
    received: float  # time.perf_counter() at arrival
    door: str  # "zenoh" or "rest"
    data: bytes | None = None  # the raw message, decoded by the worker ...
    encoding: str = "application/msgpack"
    frame: Any = None  # ... or the frame already decoded (REST)
    ego: Any = None  # a request's own ego frame (REST /v1/align with "ego")
    nbytes: int = 0
    reply: Callable[[Any], None] | None = None  # requests: called once with a Result or an exception
    task: str = "frame"  # or "ego_features": compute the features of the cache entry in ``meta["entry"]``
    meta: dict = field(default_factory=dict)
    heavy: bool = False  # taken as a heavy job (counted against max_background until done)
    started: float | None = None  # when a worker took it (background jobs: charged to background_share)
    cpu_s: float | None = None  # the CPU it used, its engine threads included (charged instead of its wall time)


class Scheduler:
    def __init__(
        self,
        depth: int = 1,
        max_requests: int = 8,
        priority: frozenset[str] = frozenset(),
        background_prefix: str | None = None,
        max_background: int = 1,
        heavy: Callable[[str], bool] | None = None,
        light_expected: Callable[[], bool] | None = None,
        workers: int | None = None,
        max_wait_s: float | None = None,
        on_expired: Callable[[Job], None] | None = None,
        background_share: float | None = None,
        clock: Callable[[], float] = time.perf_counter,
        half_life_s: float = 2.0,
        on_pushed_out: Callable[[Job], None] | None = None,
        active_s: float = 1.0,
        fair_slack_s: float = 0.2,
        overdue_s: float | None = None,
    ):
        self.depth = depth
        self.background_prefix, self.max_background = background_prefix, max_background
        self._heavy = heavy
        self._light_expected, self.workers = light_expected, workers
        self.max_wait_s, self._on_expired, self._clock = max_wait_s, on_expired, clock
        self._running_background = 0  # heavy jobs running (acquisitions, cross-checks)
        self._expired_job: Job | None = None
        # background jobs (cross-checks) while light jobs wait: at most this share of the workers' time, a bucket
        # of worker-seconds (one second's worth at most); with nothing light waiting they run freely
        self.background_share = background_share
        self._bg_tokens, self._bg_then = 0.0, clock()
        self.priority = priority  # senders served before the others (cheap jobs only, or they starve the rest)
        self.max_requests = max_requests
        self.half_life_s, self._on_pushed_out = half_life_s, on_pushed_out
        self.active_s, self.fair_slack_s, self.hold_tick_s = active_s, fair_slack_s, 0.02
        # a light stream frame that waited this long goes before fresh ones (the service answers it in a few ms from
        # its track's stream: unmeasured_after_s); in the fair order alone a busy car's frame waited behind every
        # newer frame of the others until its next one pushed it out
        self.overdue_s = overdue_s
        self._usage: dict[str, tuple[float, float]] = {}  # car -> (worker-seconds, when), halving every half_life_s
        self._last_done: dict[str, float] = {}  # car (not a priority sender) -> when a job of it last finished
        self._holding = False  # a request is held for fairness (get() looks again every hold_tick_s)
        self._cv = threading.Condition()
        self._streams: dict[str, deque[Job]] = {}
        self._requests: dict[str, deque[Job]] = {}  # sender -> its requests
        self._n_requests = 0
        self._ready: deque = deque()  # senders with work and not busy, (_REQUEST, sender), in order of readiness
        self._busy: set[str] = set()
        self._closed = False

    def put_frame(self, job: Job, depth: int | None = None) -> Job | None:
        """Queue a stream frame; returns the frame it pushed out (dropped), if any."""
        with self._cv:
            if self._closed:
                return job
            q = self._streams.setdefault(job.sender, deque())
            dropped = q.popleft() if len(q) >= (depth or self.depth) else None
            q.append(job)
            if job.sender not in self._busy and job.sender not in self._ready:
                self._ready.append(job.sender)
                self._cv.notify()
            return dropped

    def put_request(self, job: Job) -> bool:
        """Queue a request; False when the queues are full (and ``job``'s sender holds as many as any) or closed:
        the caller answers 'overloaded'. Full, a sender holding fewer pushes out the newest request of the sender
        holding most, handed to ``on_pushed_out`` (to be answered) after the lock is released."""
        pushed = None
        with self._cv:
            if self._closed:
                return False
            if self._n_requests >= self.max_requests:
                heaviest = max(self._requests, key=lambda s: len(self._requests[s]))
                if len(self._requests[heaviest]) <= len(self._requests.get(job.sender, ())) + 1:
                    return False
                pushed = self._requests[heaviest].pop()
                self._n_requests -= 1
                if not self._requests[heaviest]:
                    del self._requests[heaviest]
                    if (_REQUEST, heaviest) in self._ready:
                        self._ready.remove((_REQUEST, heaviest))
            self._requests.setdefault(job.sender, deque()).append(job)
            self._n_requests += 1
            if (_REQUEST, job.sender) not in self._ready and (_REQUEST, job.sender) not in self._busy:
                self._ready.append((_REQUEST, job.sender))
            self._cv.notify()
        if pushed is not None and self._on_pushed_out is not None:
            self._on_pushed_out(pushed)
        return True

    def get(self, timeout: float | None = None) -> Job | None:
        """The next job in round-robin order (heavy ones capped); None on timeout or once closed. Stream
        frames that waited past ``max_wait_s`` are dropped on the way (``on_expired``), never worked on."""
        expired: list[Job] = []
        try:
            with self._cv:
                deadline = None if timeout is None else time.monotonic() + timeout
                while True:
                    while self._next_key() is None and not self._closed:
                        left = None if deadline is None else deadline - time.monotonic()
                        if left is not None and left <= 0:
                            return None
                        # a request held for fairness becomes free as usage decays, with no notify: look again soon
                        tick = self.hold_tick_s if self._holding else None
                        self._cv.wait(left if tick is None else tick if left is None else min(left, tick))
                    key = self._next_key()
                    if key is None:  # closed
                        return None
                    job = self._take(key)
                    if job is not None:
                        return job
                    expired.append(self._expired_job)
        finally:
            for old in expired:
                if self._on_expired is not None:
                    self._on_expired(old)

    def _take(self, key) -> Job | None:
        """Take the key's next job (lock held); None when it was a stream frame too old to work on (kept in
        ``_expired_job``; the sender is let go)."""
        heavy = self._is_heavy(key)  # before the job leaves its queue (a request's is the queue's first)
        self._ready.remove(key)
        if isinstance(key, tuple):  # a sender's requests: one at a time, like its frames
            queue = self._requests[key[1]]
            job = queue.popleft()
            self._n_requests -= 1
            if not queue:
                del self._requests[key[1]]
            self._busy.add(key)
        else:
            job = self._streams[key].popleft()
            if self._too_old(job):
                self._expired_job = job
                if self._streams[key]:
                    self._ready.append(key)
                else:
                    self._streams.pop(key, None)
                return None
            self._busy.add(key)
        if heavy:
            self._running_background += 1
            job.heavy = True
        job.started = self._clock()
        return job

    def _too_old(self, job: Job) -> bool:
        return (
            self.max_wait_s is not None
            and job.task == "frame"
            and job.reply is None
            and self._clock() - job.received > self.max_wait_s
        )

    def _background(self, key) -> bool:
        return self.background_prefix is not None and isinstance(key, str) and key.startswith(self.background_prefix)

    def _is_heavy(self, key) -> bool:
        if self._background(key):
            return True
        if self._heavy is None:
            return False
        if isinstance(key, tuple):
            return self._heavy(key[1])
        return self._heavy(key)

    def _owner(self, key) -> str:
        """The car whose share of the workers' time a ready key (or a job's sender) spends."""
        if isinstance(key, tuple):
            return key[1]
        if self._background(key):
            return key[len(self.background_prefix) :]
        return key

    def usage(self, car: str) -> float:
        """Worker-seconds ``car``'s jobs took lately (each halving every ``half_life_s``)."""
        spent, then = self._usage.get(car, (0.0, 0.0))
        return spent * 0.5 ** ((self._clock() - then) / self.half_life_s)

    def _charge(self, car: str, seconds: float) -> None:
        self._usage[car] = (self.usage(car) + seconds, self._clock())
        if len(self._usage) > 4096:  # bounded: the cars that used least lately are forgotten (they start at 0)
            for c in sorted(self._usage, key=self.usage)[: len(self._usage) - 4096]:
                del self._usage[c]

    def _next_key(self):
        """The ready key to serve next: a priority sender, else the first in readiness order that may run now (a
        heavy one only while fewer than ``max_background`` heavy jobs run)."""
        key = next((k for k in self._ready if k in self.priority), None)
        if key is None:
            full = self._running_background >= self._heavy_cap()
            held = self._background_held()
            ready = [k for k in self._ready if not ((full and self._is_heavy(k)) or (held and self._background(k)))]
            ready.sort(key=lambda k: self.usage(self._owner(k)))  # stable: readiness order among equals
            self._holding = False
            for k in ready:
                if isinstance(k, tuple) and self._request_held(k[1]):
                    self._holding = True
                    continue
                # the light frames' turn: an overdue one before fresh ones (heavy jobs and requests keep their turns)
                return (self._overdue(ready) or k) if self._light_frame(k) else k
            key = None
        return key

    def _light_frame(self, key) -> bool:
        return isinstance(key, str) and not self._background(key) and key in self._streams and not self._is_heavy(key)

    def _overdue(self, ready: list):
        """The first ready light stream frame (a tracked peer's) in ``ready`` (the fair order) that waited over
        ``overdue_s``; None when none did (or no ``overdue_s``). Among overdue frames the fair order stands: a sweep's
        frames that arrived together become overdue together, and the oldest first would always serve them in the
        order the cars happened to publish, leaving the last ones' tracks unmeasured until they must be measured
        late."""
        if self.overdue_s is None:
            return None
        now = self._clock()
        return next(
            (k for k in ready if self._light_frame(k) and now - self._streams[k][0].received > self.overdue_s), None
        )

    def _request_held(self, car: str) -> bool:
        """Whether ``car``'s next request waits although a worker is free: another car active lately (a job done
        in the last ``active_s``) had less of the workers' time than ``car`` by more than ``fair_slack_s``. Stream
        frames are never held (latest-only, they come at the car's own rate); a burst of requests has no such
        bound, and run whenever no other car was ready at that instant it took a worker from cars whose next frame
        was due a moment later (issue 47: one car's 8 REST threads kept a worker to themselves)."""
        now, mine = self._clock(), self.usage(car)
        others = [self.usage(c) for c, t in self._last_done.items() if c != car and now - t <= self.active_s]
        return bool(others) and mine > min(others) + self.fair_slack_s

    def _background_held(self) -> bool:
        """Whether background jobs must let light ones go first: their share of the workers' time is spent and a
        light job is waiting. Their number grows with the tracks (a cross-check per track every few seconds, each
        ~0.3 s); unbounded, 16 peers' cross-checks took a whole worker from the tracked frames (issue 47). A job
        is charged its CPU (``Job.cpu_s``) as a car is: a cross-check keeps both cores busy for much of its wall
        time, and charged wall time the share let cross-checks take about half again as much CPU."""
        if self.background_share is None:
            return False
        now = self._clock()
        workers = self.workers or 1
        cap = self.background_share * workers
        self._bg_tokens = min(cap, self._bg_tokens + (now - self._bg_then) * cap)
        self._bg_then = now
        if self._bg_tokens > 0.0:
            return False
        return any(not self._is_heavy(k) for k in self._ready)

    def _heavy_cap(self) -> int:
        """``max_background``; every worker while no light stream job can come (no peer is tracked yet:
        ``light_expected`` says so), so that a fleet starting up acquires on every worker."""
        if self._light_expected is not None and self.workers is not None and not self._light_expected():
            return max(self.max_background, self.workers)
        return self.max_background

    def done(self, job: Job) -> None:
        """A worker finished a job; its car is charged what it used (``cpu_s``, else the time it took) and its
        sender may be scheduled again (an empty queue is let go)."""
        with self._cv:
            if job.started is not None and job.sender:
                car = self._owner(job.sender)
                self._charge(car, job.cpu_s if job.cpu_s is not None else self._clock() - job.started)
                if car not in self.priority and not car.startswith("@"):
                    self._last_done[car] = self._clock()
                    if len(self._last_done) > 4096:  # bounded: the longest idle are forgotten
                        for c in sorted(self._last_done, key=self._last_done.get)[: len(self._last_done) - 4096]:
                            del self._last_done[c]
                if self._holding:
                    self._cv.notify_all()
            if job.heavy:
                job.heavy = False
                self._running_background -= 1
                if self.background_share is not None and self._background(job.sender) and job.started is not None:
                    self._background_held()  # refill up to now, then charge what the job used
                    self._bg_tokens -= job.cpu_s if job.cpu_s is not None else self._clock() - job.started
                self._cv.notify()  # a heavy job held back may run now
            if job.reply is not None:
                key = (_REQUEST, job.sender)
                self._busy.discard(key)
                if self._requests.get(job.sender) and key not in self._ready:
                    self._ready.append(key)
                    self._cv.notify()
                return
            self._busy.discard(job.sender)
            if self._streams.get(job.sender):
                if job.sender not in self._ready:
                    self._ready.append(job.sender)
                    self._cv.notify()
            else:
                self._streams.pop(job.sender, None)

    def forget(self, sender: str) -> list[Job]:
        """Drop a sender's queue (an evicted peer); returns the frames that never ran."""
        with self._cv:
            left = list(self._streams.get(sender, ()))
            if sender not in self._busy:
                self._streams.pop(sender, None)
            elif sender in self._streams:
                self._streams[sender].clear()
            if sender in self._ready:
                self._ready.remove(sender)
            return left

    def backlog(self) -> bool:
        """Whether work is waiting for a worker now (a worker that would wait for something holds it up)."""
        with self._cv:
            return bool(self._ready)

    def senders(self) -> int:
        """Senders with a queue (waiting or being served)."""
        with self._cv:
            return len(self._streams)

    def pending(self) -> int:
        with self._cv:
            return self._n_requests + sum(len(q) for q in self._streams.values())

    def close(self, drain: bool = False) -> list[Job]:
        """Refuse new work. ``drain``: workers still get what is queued (then None); otherwise the queues are
        emptied and their jobs returned, never to run (requests among them must be answered)."""
        with self._cv:
            self._closed = True
            if drain:
                self._cv.notify_all()
                return []
            left = [j for q in self._requests.values() for j in q] + [j for q in self._streams.values() for j in q]
            self._requests.clear()
            self._n_requests = 0
            self._streams.clear()
            self._ready.clear()
            self._cv.notify_all()
            return left


EGO, SIGNED, UNVERIFIED_LANE = "ego", "signed", "unverified"  # intake lanes, served in this order


class _Lane:
    """One bounded lane. Full, it pushes out its oldest message; a ``fair`` lane the oldest of the sender holding
    the most (messages, or bytes when over the byte bound), so a sender's burst only displaces its own frames."""

    def __init__(self, max_jobs: int, max_bytes: int, fair: bool = False):
        self.max_jobs, self.max_bytes, self.fair = max_jobs, max_bytes, fair
        self.jobs: deque[Job] = deque()
        self.bytes = 0
        self._count: Counter[str] = Counter()
        self._bytes: Counter[str] = Counter()

    def push(self, job: Job) -> list[Job]:
        """Append ``job``; returns the messages pushed out to stay within the bounds."""
        self.jobs.append(job)
        self._account(job, +1)
        out = []
        while len(self.jobs) > self.max_jobs or (self.bytes > self.max_bytes and len(self.jobs) > 1):
            old = self._victim(by_bytes=len(self.jobs) <= self.max_jobs)
            self.jobs.remove(old)
            self._account(old, -1)
            out.append(old)
        return out

    def pop(self) -> Job:
        job = self.jobs.popleft()
        self._account(job, -1)
        return job

    def clear(self) -> list[Job]:
        left = list(self.jobs)
        self.jobs.clear()
        self.bytes = 0
        self._count.clear()
        self._bytes.clear()
        return left

    def _account(self, job: Job, sign: int) -> None:
        self.bytes += sign * job.nbytes
        if self.fair:
            self._count[job.sender] += sign
            self._bytes[job.sender] += sign * job.nbytes
            if not self._count[job.sender]:
                del self._count[job.sender], self._bytes[job.sender]

    def _victim(self, by_bytes: bool) -> Job:
        if not self.fair:
            return self.jobs[0]
        weight = self._bytes if by_bytes else self._count
        heaviest = max(weight, key=weight.__getitem__)
        return next(j for j in self.jobs if j.sender == heaviest)


class Intake:
    """Raw messages from the Zenoh door waiting for the gate (full authentication and validation), in separate
    lanes bounded by count and bytes: the ego's own (reserved), signed (the signature verified at the door), and
    unverified (queries that failed it, a genuine signer under another's key chunk; stream junk is refused at the
    door and never gets here). A lane that is full pushes out its own oldest message and returns it (the caller
    counts it): an unverified message only ever displaces another, and a signed frame never waits behind one
    (lanes are served ego first, then signed, then unverified). ``fair``: lanes whose full state pushes out the
    heaviest sender's oldest message rather than the oldest of all."""

    def __init__(
        self,
        max_jobs: int,
        max_bytes: int,
        lanes: dict[str, tuple[int, int]] | None = None,
        fair: frozenset[str] = frozenset(),
    ):
        self.max_jobs, self.max_bytes = max_jobs, max_bytes
        lanes = lanes or {
            EGO: (max_jobs, max_bytes),
            SIGNED: (max_jobs, max_bytes),
            UNVERIFIED_LANE: (max_jobs, max_bytes),
        }
        self._lanes = {name: _Lane(n, b, name in fair) for name, (n, b) in lanes.items()}
        self._cv = threading.Condition()
        self._closed = False

    def put(self, job: Job, lane: str = UNVERIFIED_LANE) -> list[Job]:
        """Queue a message in ``lane``; returns the messages of that lane pushed out to make room (``[job]``
        itself once closed)."""
        with self._cv:
            if self._closed:
                return [job]
            job.meta["lane"] = lane
            out = self._lanes[lane].push(job)
            self._cv.notify()
            return out

    def get(self, timeout: float | None = None) -> Job | None:
        """The oldest message of the first non-empty lane; None on timeout or once closed and empty."""
        with self._cv:
            if not self._cv.wait_for(lambda: self._any() or self._closed, timeout) or not self._any():
                return None
            return next(q for q in self._lanes.values() if q.jobs).pop()

    def _any(self) -> bool:
        return any(q.jobs for q in self._lanes.values())

    def __len__(self) -> int:
        with self._cv:
            return sum(len(q.jobs) for q in self._lanes.values())

    def lengths(self) -> dict[str, int]:
        with self._cv:
            return {name: len(q.jobs) for name, q in self._lanes.items()}

    @property
    def closed(self) -> bool:
        with self._cv:
            return self._closed

    def close(self) -> list[Job]:
        """Refuse new messages; returns those still waiting."""
        with self._cv:
            self._closed = True
            left = [j for q in self._lanes.values() for j in q.clear()]
            self._cv.notify_all()
            return left
