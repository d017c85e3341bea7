"""The ego-side service without its doors: admission, queues, the worker pool running the engine, results.

The doors (Zenoh link, REST app) only hand messages over: ``submit_message`` (raw stream bytes, from a Zenoh
callback), ``submit_frame`` (a decoded stream frame, REST) and ``submit_request`` (a frame to answer, REST or a
Zenoh query). Workers decode and validate; ego frames enter the cache (their features computed once, see
cache.py); peer frames are aligned against the cached ego frame nearest in time, and each result goes to the
publishers (the Zenoh link) or to the request's reply.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import threading
import time
from typing import Callable

import numpy as np
from pydantic import BaseModel

from ..bandwidth import BandwidthMeter, FrameBytes, PeerBandwidth
from ..pipeline import Aligner, PreparedFrame
from ..result import AlignResult, FailureReason
from ..settings import VEHICLE_ID_PATTERN, Settings
from ..wire import JSON, MSGPACK, Frame, Pose, Result, WireError, load_frame, pack, to_json
from .cache import EgoCache
from .metrics import Metrics
from .scheduler import Job, Scheduler

log = logging.getLogger("bb_align.service")
_EGO_FEATURES = "@ego-features"  # the scheduler key of the eager ego-feature job (never a vehicle id)
_VEHICLE_ID = re.compile(VEHICLE_ID_PATTERN)


class Unavailable(RuntimeError):
    """The service is shutting down or overloaded; the request was not run."""


class PeerStatus(BaseModel):
    last_result: Result | None = None
    frames_dropped: int = 0
    bandwidth: PeerBandwidth | None = None


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


class AlignService:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.aligner = Aligner(settings.align)
        self.cache = EgoCache(settings.ego_cache_size)
        # Ego frames are only decoded and cached by their own job (cheap), so they may go first.
        self.scheduler = Scheduler(settings.peer_queue_depth, settings.max_pending_requests,
                                   priority=frozenset({settings.ego_id}))
        self.meter = BandwidthMeter(settings.bandwidth_window_s)
        self.metrics = Metrics(self.meter.report, lambda: len(self.cache), self.scheduler.pending)
        self.publishers: list[Callable[[Result], None]] = []
        self._lock = threading.Lock()
        self._peers: dict[str, PeerStatus] = {}
        self._threads: list[threading.Thread] = []

    # ---- lifecycle ---------------------------------------------------------------------------------------------
    def start(self) -> None:
        for i in range(self.settings.workers):
            t = threading.Thread(target=self._work, name=f"bbalign-worker-{i}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self, timeout: float = 30.0) -> None:
        """Refuse new work, answer waiting requests with Unavailable, and join the workers."""
        for job in self.scheduler.close():
            if job.reply is not None:
                job.reply(Unavailable("the service is shutting down"))
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        self._threads = [t for t in self._threads if t.is_alive()]
        if self._threads:
            log.warning("%d worker(s) still busy after %.0f s", len(self._threads), timeout)

    @property
    def running(self) -> bool:
        return bool(self._threads) and all(t.is_alive() for t in self._threads)

    # ---- doors -------------------------------------------------------------------------------------------------
    def admit(self, sender: str) -> WireError | None:
        """A sender id must be well formed, and at most limits.max_peers distinct senders are tracked."""
        if not _VEHICLE_ID.match(sender):
            return WireError(422, "invalid", f"vehicle id must match {VEHICLE_ID_PATTERN}", "vehicle_id")
        with self._lock:
            if sender in self._peers:
                return None
            if len(self._peers) >= self.settings.limits.max_peers:
                return WireError(503, "overloaded", "too many distinct peers", "vehicle_id",
                                 self.settings.limits.max_peers)
            self._peers[sender] = PeerStatus()
        return None

    def submit_message(self, sender: str, data: bytes, door: str = "zenoh") -> bool:
        """A raw stream message (msgpack Frame) from ``sender``; cheap enough for a Zenoh callback."""
        refused = self.admit(sender)
        if refused is not None:
            self.metrics.rejected.labels(door, refused.error).inc()
            return False
        self.meter.record_message(sender, len(data))
        self._queue_frame(Job(sender, time.perf_counter(), door, data=data, nbytes=len(data)))
        return True

    def submit_frame(self, frame: Frame, nbytes: int, encoding: str = MSGPACK, door: str = "rest",
                     received: float | None = None) -> bool:
        """A decoded stream frame (REST /v1/frames). Raises WireError when the sender is refused."""
        refused = self.admit(frame.vehicle_id)
        if refused is not None:
            self.metrics.rejected.labels(door, refused.error).inc()
            raise refused
        self.meter.record_message(frame.vehicle_id, nbytes)
        job = Job(frame.vehicle_id, received or time.perf_counter(), door, frame=frame, encoding=encoding,
                  nbytes=nbytes)
        return self._queue_frame(job)

    def submit_request(self, reply: Callable[[object], None], *, data: bytes | None = None,
                       frame: Frame | None = None, ego: Frame | None = None, nbytes: int = 0,
                       encoding: str = MSGPACK, door: str = "rest", received: float | None = None,
                       refused: WireError | None = None) -> bool:
        """A frame to align and answer through ``reply`` (called once, from a worker, with a Result or an
        exception; ``refused``: the door already knows the answer is this error). False when the request queue
        is full: the caller answers 'overloaded' itself."""
        job = Job(frame.vehicle_id if frame is not None else "", received or time.perf_counter(), door,
                  data=data, frame=frame, ego=ego, nbytes=nbytes or len(data or b""), encoding=encoding,
                  reply=reply, meta={"refused": refused} if refused is not None else {})
        if not self.scheduler.put_request(job):
            self.metrics.rejected.labels(door, "overloaded").inc()
            return False
        return True

    def _queue_frame(self, job: Job) -> bool:
        dropped = self.scheduler.put_frame(job)
        if dropped is job:  # closed
            return False
        if dropped is not None:
            self.metrics.dropped.labels(job.sender).inc()
            with self._lock:
                self._peers[job.sender].frames_dropped += 1
        return True

    # ---- queries -----------------------------------------------------------------------------------------------
    def peers(self) -> dict[str, PeerStatus]:
        with self._lock:
            status = {p: s.model_copy() for p, s in self._peers.items() if p != self.settings.ego_id}
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
                outcome = self._run(job)
            except WireError as e:
                self.metrics.rejected.labels(job.door, e.error).inc()
                log.info("refused a frame from %s: %s", job.sender or "?", e)
                outcome = e
            except Exception as e:  # a bug must not kill the worker; the request still gets an answer
                log.exception("job from %s failed", job.sender or "?")
                outcome = e
            finally:
                self.scheduler.done(job)
            if job.reply is not None:
                job.reply(outcome)
            elif isinstance(outcome, Result):
                for publish in self.publishers:
                    try:
                        publish(outcome)
                    except Exception:
                        log.exception("publishing a result failed")

    def _run(self, job: Job) -> Result | None:
        if job.task == "ego_features":
            job.meta["entry"].features(self._prepare_entry)
            return None
        if "refused" in job.meta:
            raise job.meta["refused"]
        frame = job.frame
        if frame is None:
            frame = load_frame(job.data, self.settings.limits, job.encoding)
            if job.reply is None and frame.vehicle_id != job.sender:
                raise WireError(422, "invalid", f"vehicle_id {frame.vehicle_id!r} differs from the key's "
                                                f"{job.sender!r}", "vehicle_id")
        if job.reply is not None:  # requests are accounted here (stream frames were at arrival)
            refused = self.admit(frame.vehicle_id)
            if refused is not None:
                raise refused
            job.nbytes = len(_encode(frame, job.encoding))  # the peer frame alone, as it would go on the air
            self.meter.record_message(frame.vehicle_id, job.nbytes)
        kind = "ego" if job.reply is None and frame.vehicle_id == self.settings.ego_id else "peer"
        self.metrics.frames.labels(job.door, kind).inc()
        if kind == "ego":
            self.meter.record_frame(frame.vehicle_id, FrameBytes.of(frame, job.nbytes, job.encoding))
            entry = self.cache.add(frame, frame.bev_image())  # a corrupt image never enters the cache
            # Features of the newest ego frame, computed when a worker is free (or by the first peer needing them).
            self.scheduler.put_frame(Job(_EGO_FEATURES, time.perf_counter(), job.door, task="ego_features",
                                         meta={"entry": entry}), depth=1)
            return None
        return self._align(frame, job)

    def _prepare_entry(self, entry) -> PreparedFrame:
        return self._prepare(entry.frame, "prepare_ego", entry.bev)

    def _prepare(self, frame: Frame, step: str, bev=None) -> PreparedFrame:
        t0 = time.perf_counter()
        bev = bev if bev is not None else frame.bev_image()
        t_png = (time.perf_counter() - t0) * 1e3
        prepared = self.aligner.prepare(bev, frame.boxes_array())
        prepared = dataclasses.replace(prepared, num_points=frame.num_points,
                                       timings_ms={"decode_png": t_png, **prepared.timings_ms})
        self.metrics.engine.labels(step).observe(time.perf_counter() - t0)
        return prepared

    def _align(self, peer: Frame, job: Job) -> Result:
        """Align one peer frame against the given ego frame, or the cached one nearest in time."""
        s = self.settings
        fb = FrameBytes.of(peer, job.nbytes, job.encoding)
        self.meter.record_frame(peer.vehicle_id, fb)
        timings = {"queue_wait": (time.perf_counter() - job.received) * 1e3}
        base = dict(ego_id=s.ego_id, peer_id=peer.vehicle_id, peer_seq=peer.seq, peer_stamp=peer.stamp,
                    bytes_received=fb.total, raw_points_bytes=fb.raw_points,
                    ratio_vs_points=fb.total / fb.raw_points if fb.raw_points else None)

        if job.ego is None:  # answer at once when no usable ego frame exists, before any engine work
            picked = self._pick_ego(peer, job, base, timings, wait=False)
            if isinstance(picked, Result):
                return picked
        peer_prep = self._prepare(peer, "prepare_peer")
        if job.ego is not None:
            ego_frame, ego_prep = job.ego, self._prepare(job.ego, "prepare_ego")
        else:  # look again: a nearer ego frame may have come in while the peer was prepared
            picked = self._pick_ego(peer, job, base, timings, wait=True)
            if isinstance(picked, Result):
                return picked
            ego_frame, ego_prep = picked
        base.update(ego_seq=ego_frame.seq, ego_stamp=ego_frame.stamp, ego_skew_s=peer.stamp - ego_frame.stamp)

        prior = relative_prior(ego_frame, peer)
        tz, roll, pitch = prior if prior is not None else (0.0, 0.0, 0.0)
        t0 = time.perf_counter()
        T_prior = reported_relative_pose(ego_frame, peer) if self.settings.use_pose_prior else None
        res = self.aligner.align(ego_prep, peer_prep, tz=tz, roll=roll, pitch=pitch, T_prior=T_prior)
        self.metrics.engine.labels("align").observe(time.perf_counter() - t0)
        timings.update({f"peer_{k}": v for k, v in peer_prep.timings_ms.items()}, **res.timings_ms)
        return self._finish(job, _from_engine(res, base, prior is not None, timings))

    def _pick_ego(self, peer: Frame, job: Job, base: dict, timings: dict, wait: bool):
        """(ego frame, its features) nearest in time to the peer frame, or a failed Result saying why."""
        s = self.settings
        entry = self.cache.nearest(peer.stamp)
        if entry is None:
            return self._finish(job, Result(**base, success=False, reason=FailureReason.no_ego_frame.value,
                                            timings_ms=timings))
        skew = peer.stamp - entry.stamp
        if abs(skew) > s.max_ego_skew_s:
            return self._finish(job, Result(
                **base, ego_seq=entry.frame.seq, ego_stamp=entry.stamp, ego_skew_s=skew, success=False,
                reason=FailureReason.stale_ego_frame.value, timings_ms=timings,
                notes=[f"nearest ego frame is {abs(skew):.3f} s away, the limit is {s.max_ego_skew_s} s"]))
        if not wait:
            return entry.frame, None
        t0 = time.perf_counter()
        prepared = entry.features(self._prepare_entry)
        timings["ego_features"] = (time.perf_counter() - t0) * 1e3  # waited for, or computed here
        return entry.frame, prepared

    def _finish(self, job: Job, result: Result) -> Result:
        latency_s = time.perf_counter() - job.received
        result = result.model_copy(update={"latency_ms": latency_s * 1e3})
        self.metrics.latency.labels(job.door).observe(latency_s)
        self.metrics.alignments.labels(result.peer_id, "success" if result.success else result.reason).inc()
        with self._lock:
            self._peers.setdefault(result.peer_id, PeerStatus()).last_result = result
        return result


def _encode(frame: Frame, encoding: str) -> bytes:
    return to_json(frame) if encoding == JSON else pack(frame)


def _from_engine(res: AlignResult, base: dict, prior_used: bool, timings: dict[str, float]) -> Result:
    T = np.asarray(res.T_ego_peer, dtype=float)
    return Result(**base, success=res.success, reason=res.reason, yaw_deg=res.yaw_deg, tx=res.tx, ty=res.ty,
                  T_ego_peer=T.tolist(), inliers_bv=res.inliers_bv, inliers_box=res.inliers_box,
                  matches_bv=res.matches_bv, box_pairs=res.box_pairs, confidence=res.confidence,
                  stage2_applied=res.stage2_applied, prior_used=prior_used, notes=list(res.notes),
                  timings_ms={k: float(v) for k, v in timings.items()})
