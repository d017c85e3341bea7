"""Following one peer through time with the engine: the tracker's two steps on prepared frames.

    follower = Follower(aligner)                                     # one per ego-peer pair
    result = follower.step(ego, peer, stamp, O_ego=..., O_peer=...)  # once per peer frame, in time order

``acquire`` is the full method (``Aligner.align``, with the caller's reported-pose prior if any; without one the
multi-hypothesis acquisition searches every pose, and the track judges whether it agrees); ``measure`` is the
dense refinement from the track's prediction (``Aligner.measure``: no MIM or descriptors). The tracker
(bb_align.engine.tracker) predicts, gates and fuses; its answer comes back as an AlignResult whose ``source`` says
where it came from and whose covariance is the track's.

A service that cannot let a peer's frames wait for a periodic cross-check (~0.3 s) runs it beside the track:

    result = follower.step(ego, peer, stamp, O_ego=..., O_peer=..., crosscheck=False)
    if (epoch := follower.begin_crosscheck(stamp)) is not None:           # due, and the track has odometry
        r = follower.crosscheck(ego, peer, T_prior=...)                    # elsewhere: another thread, later
        follower.finish_crosscheck(epoch, r, O_ego, O_peer)                # with the track's lock held
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterable

import numpy as np

from .boxes import box_measurement
from .config import TrackConfig
from .covariance import left_covariance, params_covariance, probability_within
from .frame import PreparedFrame
from .geometry import ground_se2, pose_error, se3_from_se2, worst_sigma_m
from .pipeline import Aligner
from .result import AlignResult
from .stream_acquire import StreamFrame
from .tracker import OUT_OF_ORDER, Evidence, Measurement, PeerTrack, TrackAnswer, combine
from .verdict import CAP_STAGE1_FAILED, FailureReason


def ground_pose(T: np.ndarray | None) -> np.ndarray | None:
    """A 4x4 (or 3x3) pose's ground-plane part as 3x3, None for None (an optional odometry pose)."""
    return None if T is None else ground_se2(np.asarray(T, dtype=float))


def as_measurement(r: AlignResult, inflation: float = 1.0) -> Measurement:
    """An engine result as the tracker's measurement: the ground-plane pose and its covariance of left increments
    (times ``inflation``); its evidence is the same pose with the run's own covariance."""
    if not r.success or r.covariance is None:
        return Measurement(False, reason=r.reason or "no covariance")
    T = r.T_box @ r.T_bv
    cov = left_covariance(r.covariance, T)
    return Measurement(True, T, inflation * cov, evidence=Evidence(T, cov, float(r.refine_fitness or 0.0)))


class Follower:
    """The track of one peer and the engine steps it runs. Not thread-safe: one peer's frames in order."""

    def __init__(self, aligner: Aligner, cfg: TrackConfig | None = None):
        self.aligner = aligner
        self.cfg = cfg or aligner.config.track
        self.track = PeerTrack(self.cfg, aligner.config.answer)
        # The last engine run's own pose (3x3) and covariance (of its parameters) before the track fused it:
        # for diagnostics and calibration (bb_align.lab.tracking).
        self.last_measured: tuple[np.ndarray, np.ndarray | None] | None = None
        self.last_boxes = Measurement(False)  # the last tracked frame's box measurement (left increments)
        # The last second of frames with odometry: a first acquisition that one frame cannot give is tried on them
        # together (Aligner.align_stream), at most every stream.every_s.
        self.recent: deque[StreamFrame] = deque(maxlen=aligner.config.stream.frames)
        self.last_stream_try: float | None = None

    def step(
        self,
        ego: PreparedFrame,
        peer: PreparedFrame,
        stamp: float,
        *,
        O_ego: np.ndarray | None = None,
        O_peer: np.ndarray | None = None,
        T_prior: np.ndarray | None = None,
        tz: float = 0.0,
        roll: float = 0.0,
        pitch: float = 0.0,
        crosscheck: bool = True,
        ego_stamp: float | None = None,
    ) -> AlignResult:
        """One peer frame at ``stamp`` (s) against the ego frame of (about) that time. ``O_ego`` / ``O_peer``: the
        two cars' odometry poses (4x4 or 3x3; both or neither). ``T_prior``: a reported T_ego_peer (e.g. from GNSS)
        that gates an acquisition's matches, as ``Aligner.align`` does. tz, roll, pitch: Eq. 1's constants.
        ``crosscheck=False``: cross-check left to the caller; ``ego_stamp``: the ego frame's, if not ``stamp``."""
        runs: list[AlignResult] = []
        self.last_boxes, c = Measurement(False), self.cfg
        with_odometry = O_ego is not None and O_peer is not None
        inflation = c.measurement_inflation if with_odometry else c.measurement_inflation_without_odometry
        acquired_ms: list[float] = []

        def measure(T_pred: np.ndarray) -> Measurement:
            runs.append(self.aligner.measure(ego, peer, T_pred))
            runs[-1].source = "tracking"
            m = as_measurement(runs[-1], inflation)
            if m.ok and c.landscape:
                m.evidence = self._judged(ego, peer, m.evidence, runs[-1])
            self.last_boxes = self._boxes(ego, peer, T_pred)
            if self.last_boxes.ok:
                ev = m.evidence
                m, used = combine(m, self.last_boxes, c.box_agreement_chi2)
                runs[-1].notes.append(f"box measurement {'fused' if used else 'left out: disagrees'}")
                if ev is not None:  # this frame's own evidence: the refinement and the boxes, neither inflated
                    own, _ = combine(
                        Measurement(True, ev.T_ego_peer, ev.covariance), self.last_boxes, c.box_agreement_chi2
                    )
                    m.evidence = Evidence(own.T_ego_peer, own.covariance, ev.fitness)
            return m

        def acquire(T_pred: np.ndarray | None) -> Measurement:  # the prediction is not a prior: judged after
            t = time.perf_counter()
            runs.append(self.crosscheck(ego, peer, T_prior=T_prior, tz=tz, roll=roll, pitch=pitch))
            if not runs[-1].success and T_pred is None and self._stream_due(stamp):  # no track, none from one frame
                runs.append(self._from_stream(runs[-1], T_prior, stamp))
            acquired_ms.append((time.perf_counter() - t) * 1e3)  # with the frames' features, when computed now
            return as_measurement(runs[-1])

        ego_stamp, t0 = stamp if ego_stamp is None else ego_stamp, time.perf_counter()
        self._remember(StreamFrame(ego, peer, O_ego, O_peer, stamp) if with_odometry else None, ego_stamp)
        answer = self.track.step(
            stamp, measure, acquire, ground_pose(O_ego), ground_pose(O_peer), crosscheck=crosscheck, ego_stamp=ego_stamp
        )
        r = self._result(answer, runs, (time.perf_counter() - t0) * 1e3, tz, roll, pitch)
        if acquired_ms:
            r.timings_ms["acquire"] = sum(acquired_ms)
        return r

    def _remember(self, frame: StreamFrame | None, ego_stamp: float) -> None:
        """Keep the frame for a stream acquisition; a frame without odometry, older than the stream's window or after
        an odometry step no car makes (a relocalisation) starts the memory afresh."""
        if frame is None:
            self.recent.clear()
            return
        frame = StreamFrame(frame.ego, frame.peer, ground_pose(frame.O_ego), ground_pose(frame.O_peer), frame.stamp)
        # the track's own view of the cars' motion (it records this frame in its step, next)
        jump, _ = self.track.odometry.check({"ego": (ego_stamp, frame.O_ego), "peer": (frame.stamp, frame.O_peer)})
        if self.recent and (frame.stamp <= self.recent[-1].stamp or jump):
            self.recent.clear()
        self.recent.append(frame)
        window = self.aligner.config.stream.window_s
        while self.recent and frame.stamp - self.recent[0].stamp > window:
            self.recent.popleft()

    def _stream_due(self, stamp: float) -> bool:
        sc = self.aligner.config.stream
        if not sc.first_answer or len(self.recent) < sc.min_frames:
            return False
        return self.last_stream_try is None or stamp - self.last_stream_try >= sc.every_s

    def _from_stream(self, alone: AlignResult, T_prior: np.ndarray | None, stamp: float) -> AlignResult:
        """The acquisition from the last second of frames (``Aligner.align_stream``), with the reported pose as
        its prior (``track.prior`` gate, as a single frame's acquisition) and checked against it as an acquisition
        that searched every pose is (``_check_prior``)."""
        self.last_stream_try = stamp
        gate = T_prior is not None and self.cfg.prior == "gate"
        r = self.aligner.align_stream(list(self.recent), T_prior if gate else None)
        r.notes.insert(0, f"this frame alone: {alone.reason}; then the last {len(self.recent)} frames together")
        if T_prior is not None:
            self._check_prior(r, T_prior)
        return r if r.success else alone

    def _judged(self, ego: PreparedFrame, peer: PreparedFrame, ev: Evidence, r: AlignResult) -> Evidence:
        """This frame's own evidence judged on the pose landscape around its refinement (``Aligner.judge``), as an
        acquisition's answer is: the refinement's curvature is over-confident at range (docs/tracking.md). A
        landscape with no bounded peak (a corridor) leaves an unbounded covariance: no evidence of its own."""
        t = time.perf_counter()
        land = self.aligner.judge(ego, peer, ev.T_ego_peer, half_width_m=self._window(r))
        r.timings_ms["landscape"] = (time.perf_counter() - t) * 1e3
        if land.at_edge:
            r.notes.append("the pose landscape has no bounded peak within its window (a corridor)")
        return Evidence(land.T, left_covariance(land.covariance, land.T), ev.fitness)

    def _window(self, r: AlignResult) -> float:
        """The landscape's reach for a tracked frame: ``landscape_sigmas`` of the refinement's own worst-direction
        1-sigma (which is wider than the landscape's at range), between ``landscape_min_half_width_m`` and the
        acquisition's window. Near frames are pinned to decimetres: a narrow window costs half as much."""
        full = self.aligner.config.landscape.half_width_m
        if r.covariance is None:
            return full
        reach = self.cfg.landscape_sigmas * worst_sigma_m(np.asarray(r.covariance))
        return float(np.clip(reach, min(self.cfg.landscape_min_half_width_m, full), full))

    def _boxes(self, ego: PreparedFrame, peer: PreparedFrame, T_pred: np.ndarray) -> Measurement:
        """The boxes both cars detected, paired under the prediction, as a measurement (track.boxes)."""
        c = self.cfg
        if not c.boxes or len(ego.boxes) == 0 or len(peer.boxes) == 0:
            return Measurement(False, reason="no boxes")
        b = box_measurement(
            ego.boxes,
            peer.boxes,
            T_pred,
            c.box_sigma_m,
            pair_gate_m=c.box_pair_gate_m,
            min_pairs=c.box_min_pairs,
            min_inliers=c.box_min_inliers,
            cfg=self.aligner.config.box,
        )
        return Measurement(False, reason="too few box pairs") if b is None else Measurement(True, *b)

    def crosscheck(
        self,
        ego: PreparedFrame,
        peer: PreparedFrame,
        *,
        T_prior: np.ndarray | None = None,
        tz: float = 0.0,
        roll: float = 0.0,
        pitch: float = 0.0,
    ) -> AlignResult:
        """The full acquisition of one frame pair, judged against the reported pose (``track.prior``). It touches
        no track state: a cross-check beside the track may run it on another thread."""
        gate = T_prior is not None and self.cfg.prior == "gate"
        r = self.aligner.align(ego, peer, tz=tz, roll=roll, pitch=pitch, T_prior=T_prior if gate else None)
        if T_prior is not None and not gate:
            self._check_prior(r, T_prior)
        return r

    def unmeasured(
        self,
        stamp: float,
        *,
        O_ego: np.ndarray,
        O_peer: np.ndarray,
        ego_stamp: float | None = None,
        tz: float = 0.0,
        roll: float = 0.0,
        pitch: float = 0.0,
    ) -> AlignResult | None:
        """A peer frame answered without measuring it (no images needed): the stream's recent evidence carried by
        both cars' odometry, when the track says that is a valid answer (``PeerTrack.unmeasured``); None when the
        frame must be ``step``ped instead (nothing of the track changed then)."""
        t0 = time.perf_counter()
        a = self.track.unmeasured(stamp, ground_pose(O_ego), ground_pose(O_peer), ego_stamp=ego_stamp)
        return None if a is None else self._result(a, [], (time.perf_counter() - t0) * 1e3, tz, roll, pitch)

    def observe_odometry(
        self, ego: Iterable[tuple[float, np.ndarray]] = (), peer: Iterable[tuple[float, np.ndarray]] = ()
    ) -> None:
        """The odometry poses (stamp s, 4x4 or 3x3) of frames of either car that will not be stepped, oldest first:
        a service too busy to step every frame still checks each car's every odometry step (a relocalisation among
        the skipped frames is caught at the next step; a step after them is judged as one 0.1 s step, not a gap)."""
        watch = self.track.odometry
        for car, poses in (("ego", ego), ("peer", peer)):
            last = watch.last_stamp(car)
            watch.observe(car, [(t, ground_pose(O)) for t, O in poses if last is None or t > last])

    def begin_crosscheck(self, stamp: float) -> int | None:
        """The track's epoch when a cross-check beside it is due at ``stamp`` (marked begun), else None."""
        return self.track.begin_crosscheck(stamp)

    def finish_crosscheck(self, epoch: int, r: AlignResult, O_ego: np.ndarray, O_peer: np.ndarray) -> str | None:
        """Apply a cross-check's acquisition (``crosscheck``) of the frame pair with odometry ``O_ego``, ``O_peer``
        to the track of ``epoch``; the event when it dropped the track."""
        return self.track.finish_crosscheck(epoch, as_measurement(r), ground_pose(O_ego), ground_pose(O_peer))

    def _check_prior(self, r: AlignResult, T_prior: np.ndarray) -> None:
        """An acquisition farther from the reported pose than the prior's tolerance is refused: the images found
        an alias (a street repeats along itself) or the report lies; either way not a pose to start a track on."""
        if not r.success:
            return
        t_err, r_err = pose_error(r.T_box @ r.T_bv, ground_pose(T_prior))
        tol = self.aligner.config.prior
        if t_err > tol.max_translation_m or r_err > tol.max_yaw_deg:
            r.success, r.reason = False, FailureReason.disagrees_with_prior.value
            r.confidence = min(r.confidence, CAP_STAGE1_FAILED)
            r.notes.append(
                f"the acquired pose is {t_err:.1f} m / {r_err:.1f} deg from the reported pose (prior tolerance "
                f"{tol.max_translation_m:g} m / {tol.max_yaw_deg:g} deg)"
            )
        else:
            r.notes.append("checked against the reported pose")

    def _result(self, a: TrackAnswer, runs: list[AlignResult], ms: float, tz, roll, pitch) -> AlignResult:
        """The track's answer as an AlignResult: the evidence of the engine run it rests on, the track's pose and
        covariance, and success only when the track says the pose is valid."""
        r = runs[-1] if runs else AlignResult(success=False, T_ego_peer=np.eye(4), T_bv=np.eye(3), T_box=np.eye(3))
        self.last_measured = (r.T_box @ r.T_bv, r.covariance) if runs and r.success else None
        r.timings_ms = {k: v for run in runs for k, v in run.timings_ms.items()} | {"track_total": ms}
        r.source, r.track_state, r.track_event = a.source, a.state.value, a.event
        own = a.source == "acquisition" and a.valid  # the acquisition's own verdict stands
        if a.T_ego_peer is not None:
            r.T_ego_peer = se3_from_se2(a.T_ego_peer, tz=tz, roll=roll, pitch=pitch)
            r.covariance = params_covariance(a.covariance, a.T_ego_peer)
        r.success = bool(a.valid)
        r.reason = None if a.valid else self._reason(a, r)
        if a.source == "stream":
            r.notes.append("no evidence of its own this frame: the stream's recent frames answer, carried by odometry")
        if a.why_not:
            r.notes.append(f"not valid on this frame's evidence: {a.why_not}")
        if not own:
            rule = self.aligner.config.answer
            p = 0.0 if r.covariance is None else probability_within(r.covariance, rule.max_error_m, rule.max_error_deg)
            cap = CAP_STAGE1_FAILED
            r.confidence = float(p if a.valid else min(p, cap))
        return r

    def _reason(self, a: TrackAnswer, r: AlignResult) -> str:
        if a.event == OUT_OF_ORDER:
            return FailureReason.out_of_order.value
        if a.mahalanobis2 is not None and a.mahalanobis2 > self.cfg.gate_chi2:
            return FailureReason.outside_track_gate.value
        if a.source == "prediction":
            return FailureReason.track_uncertain.value
        return r.reason or FailureReason.track_uncertain.value
