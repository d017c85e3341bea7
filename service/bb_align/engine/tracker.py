"""Following one peer through time: acquire once, then refine each frame from a prediction, fuse, gate.

The state is what stays nearly constant between the two cars:

* with odometry (each car's own locally accurate, slowly drifting pose ``O_e``, ``O_p`` in its odometry frame),
  the offset between the two odometry frames ``X = T_egoodom_peerodom``, so that
  ``T_ego_peer(t) = inv(O_e(t)) @ X @ O_p(t)``; process noise is the odometries' drift;
* without odometry, the relative pose ``T_ego_peer`` itself and its velocity (constant-velocity model).

Each frame: predict ``T_ego_peer`` and its covariance, measure it by refining densely from the prediction (the
caller's ``measure``), gate the measurement by its Mahalanobis distance, fuse (a Kalman update on left increments
``T = se2(delta) @ T_hat``). A full acquisition runs when there is no track, when the track's uncertainty grows
past a bound, and periodically as a cross-check. Every answer says where it came from, its covariance and the track
state; every state change carries its reason.

With odometry the periodic cross-check can also run beside the track (``step(..., crosscheck=False)``, then
``begin_crosscheck`` and ``finish_crosscheck`` on the acquisition of that earlier frame): the offset X is the same at
every time, so an acquisition finished a few frames later still measures it, and the frames meanwhile are tracked
in milliseconds instead of waiting for it.

Covariances are of left increments (yaw rad, tx m, ty m), the convention of the refinement's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np

from .config import AnswerRule, TrackConfig
from .covariance import fuse_poses, mahalanobis2, params_covariance, probability_within
from .evidence import OffsetSample, SharedError, StreamEvidence
from .geometry import log_left, se2, worst_sigma_m
from .odometry import OdometryWatch

OUT_OF_ORDER = "frame older than the track: ignored"  # the event of a frame that came after a newer one


class TrackState(str, Enum):
    acquiring = "acquiring"  # no pose yet: every frame runs a full acquisition
    tracking = "tracking"  # a pose and a covariance, refined each frame
    lost = "lost"  # the last track was given up (the next frame acquires afresh)


@dataclass
class Evidence:
    """What one frame's own engine run says, before any fusion: the refined (or acquired) T_ego_peer (3x3) and the
    run's own covariance (left increments, not inflated). A tracked answer is valid only on this."""

    T_ego_peer: np.ndarray
    covariance: np.ndarray
    fitness: float = 0.0  # the share of the peer's points the run found on the ego's (its support)


@dataclass
class Measurement:
    """One frame's measurement as the filter fuses it: a refined or acquired T_ego_peer (3x3) and its covariance
    (possibly inflated, possibly combined with the boxes'), or a failure; ``evidence``: the frame's own engine run
    (None when the refinement failed and only the boxes measured)."""

    ok: bool
    T_ego_peer: np.ndarray | None = None
    covariance: np.ndarray | None = None  # 3x3, left increments (yaw, tx, ty)
    reason: str | None = None
    evidence: Evidence | None = None


@dataclass
class TrackAnswer:
    """What the tracker says for one frame."""

    stamp: float
    state: TrackState
    source: str  # "acquisition", "tracking", "stream" (no evidence of its own), "prediction" or "none"
    valid: bool  # a pose to act on: within the track's bounds and supported by this or recent frames
    T_ego_peer: np.ndarray | None  # 3x3
    covariance: np.ndarray | None  # 3x3, left increments (yaw, tx, ty)
    event: str | None = None  # why the state changed this frame, if it did
    mahalanobis2: float | None = None  # the measurement's squared Mahalanobis distance to the prediction
    why_not: str | None = None  # why a tracked pose was not valid, when it was not


def adjoint(T: np.ndarray) -> np.ndarray:
    """Maps a left increment d of A to the left increment of T @ A @ inv(T): se2(d') = T se2(d) T^-1 (first order)."""
    c, s, tx, ty = T[0, 0], T[1, 0], T[0, 2], T[1, 2]
    return np.array([[1.0, 0.0, 0.0], [ty, c, -s], [-tx, s, c]])


def combine(m: Measurement, other: Measurement, agreement_chi2: float) -> tuple[Measurement, bool]:
    """Two independent measurements of the same frame's T_ego_peer as one (information-weighted, on left increments
    about ``m``'s pose), and whether ``other`` was used: it is left out when ``m`` is a measurement and the two lie
    farther apart than ``agreement_chi2`` (squared Mahalanobis). A failed ``m`` gives way to ``other``."""
    if not other.ok:
        return m, False
    if not m.ok:
        return other, True
    fused = fuse_poses(m.T_ego_peer, m.covariance, other.T_ego_peer, other.covariance, agreement_chi2)
    return (m, False) if fused is None else (Measurement(True, *fused, evidence=m.evidence), True)


def odometry_drift(cfg: TrackConfig) -> np.ndarray:
    """Each car's odometry drift per second, (yaw, tx, ty) variances in its own body frame."""
    sigma = [np.radians(cfg.odometry_drift_deg_per_s), cfg.odometry_drift_m_per_s, cfg.odometry_drift_m_per_s]
    return np.diag(np.square(sigma))


def offset_sample(
    stamp: float, T: np.ndarray, cov: np.ndarray, O_e: np.ndarray, O_p: np.ndarray, q: np.ndarray
) -> OffsetSample:
    """One frame's own measurement of T_ego_peer (covariance of its left increments) as a measurement of the
    odometry offset X = O_e T O_p^-1, its covariance growing with age by both cars' drift ``q`` (per second), taken
    where the two cars' odometries put them (what decides what its error shares with other frames')."""
    A, Ad_T = adjoint(O_e), adjoint(T)  # left increments of T_ego_peer -> of X
    drift = A @ (q + Ad_T @ q @ Ad_T.T) @ A.T
    places = np.array([O_e[:2, 2], O_p[:2, 2]], dtype=float)
    return OffsetSample(stamp, O_e @ T @ np.linalg.inv(O_p), A @ cov @ A.T, drift, places)


def shared_error(cfg: TrackConfig) -> SharedError:
    """What the stream's frames share, from the track's settings (engine.evidence.SharedError): never more once the
    cars have moved on than in one place."""
    far = cfg.evidence_correlation_far
    far = None if far is None else min(far, cfg.evidence_correlation)
    return SharedError(cfg.evidence_correlation, far, cfg.evidence_same_place_m, cfg.evidence_decorrelation_m)


def kalman_step(P: np.ndarray, H: np.ndarray, R: np.ndarray, nu: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """One Kalman update for innovation ``nu`` (covariance R) of a state with covariance P seen through H: the
    innovation's squared Mahalanobis distance, the state increment and the updated covariance (symmetrised)."""
    S = H @ P @ H.T + R
    d2 = float(nu @ np.linalg.solve(S, nu))
    K = P @ H.T @ np.linalg.inv(S)
    P = (np.eye(len(P)) - K @ H) @ P
    return d2, K @ nu, 0.5 * (P + P.T)


class PeerTrack:
    """The track of one ego-peer pair. ``step`` once per peer frame, in time order."""

    def __init__(self, cfg: TrackConfig | None = None, answer: AnswerRule | None = None):
        self.cfg = cfg or TrackConfig()
        self.answer = answer or AnswerRule()
        c = self.cfg
        # With odometry, the answer is the stream's evidence: the recent frames' own measurements fused.
        self.stream = StreamEvidence(
            c.evidence_window_s, c.evidence_max_frames, shared_error(c), c.gate_chi2, c.evidence_agreement
        )
        self.state = TrackState.acquiring
        self.X: np.ndarray | None = None  # 3x3: T_egoodom_peerodom, or T_ego_peer without odometry
        self.P: np.ndarray | None = None  # state covariance: 3x3 (odometry) or 6x6 (pose and velocity)
        self.w = np.zeros(3)  # constant-velocity model: left increment per second
        self.with_odometry = False
        self.stamp: float | None = None
        self.last_acquired: float | None = None
        self.rejects = 0
        self.misses = 0  # tracked frames in a row without valid evidence of their own: an acquisition when too many
        self.support: float | None = None  # the track's reference fitness (its recent valid evidence)
        self.last_event: str | None = None
        self.last_fused: float | None = None
        self.epoch = 0  # counts tracks: a cross-check run beside the track applies only to the track it checked
        self.pending_event: str | None = None  # a state change made between frames, said with the next answer
        self.odometry = OdometryWatch(self.cfg)  # each car's recent odometry poses: is its next step motion?

    # ---- the frame step ----------------------------------------------------------------------------------------
    def step(
        self,
        stamp: float,
        measure: Callable[[np.ndarray], Measurement],
        acquire: Callable[[np.ndarray | None], Measurement],
        O_ego: np.ndarray | None = None,
        O_peer: np.ndarray | None = None,
        crosscheck: bool = True,
        ego_stamp: float | None = None,
    ) -> TrackAnswer:
        """One peer frame at ``stamp`` (s). ``measure(T_pred)`` refines from a predicted T_ego_peer (3x3);
        ``acquire(T_prior or None)`` runs the full method. ``O_ego`` / ``O_peer``: 3x3 odometry poses of the two
        frames (both or neither), the ego's at ``ego_stamp`` if given. ``crosscheck=False``: no periodic cross-check
        here (``begin_crosscheck``); one forced by the track's uncertainty still runs."""
        odometry = O_ego is not None and O_peer is not None
        O_e = np.asarray(O_ego, float) if odometry else np.eye(3)
        O_p = np.asarray(O_peer, float) if odometry else np.eye(3)
        event, self.pending_event = self.pending_event, None
        poses = {"ego": (stamp if ego_stamp is None else ego_stamp, O_e), "peer": (stamp, O_p)}
        jump, unchecked_m = self.odometry.check(poses) if odometry else (None, 0.0)
        if self.X is not None and odometry != self.with_odometry:
            event = self._drop("odometry appeared or disappeared")
        elif self.X is not None and self.stamp - stamp > self.cfg.max_gap_s:  # a recording replayed from its start
            event = self._drop(f"the stream restarted {self.stamp - stamp:.1f} s earlier")
        elif self.X is not None and stamp < self.stamp:
            return self._answer(stamp, "none", False, None, None, OUT_OF_ORDER)
        elif self.X is not None and jump:
            event = self._drop(jump[1])
        elif self.X is not None and stamp - self.stamp > self.cfg.max_gap_s:
            event = self._drop(f"no frame for {stamp - self.stamp:.1f} s (max_gap_s {self.cfg.max_gap_s:g})")
        self.odometry.record(poses if odometry else None, jump[0] if jump else None)
        if self.X is None:
            return self._acquire(stamp, acquire(None), O_e, O_p, odometry, event)

        X, P, T_pred, H = self._predict(stamp - self.stamp, O_e, O_p)
        P_T, blind = H @ P @ H.T, unchecked_m > self.cfg.max_unchecked_jump_m
        if self._full_method_due(stamp, P_T, unchecked_m) or (crosscheck and self.crosscheck_due(stamp)):
            # fused when it agrees, a fresh track when not; when it fails the refinement below tries (unless blind)
            self.last_acquired = stamp
            m = acquire(T_pred)
            if m.ok or blind:
                return self._full_method(stamp, m, X, P, T_pred, H, O_e, O_p, unchecked_m)
        m = measure(T_pred)
        ev = m.evidence if m.ok else None
        if ev is not None and (d2 := self._disagreement(ev, T_pred, P_T)) > self.cfg.gate_chi2:
            # This frame's own run contradicts the prediction beyond both uncertainties: an event (an odometry
            # jump or relocalisation, a car lying about its motion, a wrong track), not a correction to fuse.
            event = self._drop(
                f"this frame's refinement disagrees with the prediction (Mahalanobis^2 {d2:.1f}, gate "
                f"{self.cfg.gate_chi2:g}): an odometry jump, a relocalisation or a wrong track"
            )
            return self._acquire(stamp, acquire(None), O_e, O_p, odometry, event)
        if not m.ok:
            self.misses += 1
            return self._coast(stamp, X, P, T_pred, P_T, m.reason, rejected=False, odometry=(O_e, O_p))
        return self._update(stamp, m, X, P, T_pred, H, O_e, O_p, "tracking")

    def _full_method_due(self, stamp: float, P_T: np.ndarray, unchecked_m: float) -> bool:
        """Whether this frame needs the full method whatever else: a track too uncertain, unconfirmed for
        max_rejects frames (at most every reacquire_s: ~0.3 s each), or a gap so long the odometry check could miss
        a relocalisation the refinement cannot find its way back from."""
        unsupported = self.misses >= self.cfg.max_rejects and stamp - self.last_acquired >= self.cfg.reacquire_s
        blind = unchecked_m > self.cfg.max_unchecked_jump_m
        return worst_sigma_m(P_T) > self.cfg.max_sigma_m or unsupported or blind

    def _full_method(self, stamp, m: Measurement, X, P, T_pred, H, O_e, O_p, unchecked_m: float) -> TrackAnswer:
        """The full method's answer within a track: fused or a fresh track; failed after unchecked odometry, the
        track is dropped."""
        if m.ok:
            return self._update(stamp, m, X, P, T_pred, H, O_e, O_p, "acquisition", crosscheck=True)
        event = self._drop(
            f"an odometry step the check could not tell from a relocalisation of {unchecked_m:.1f} m, and the full "
            f"method did not confirm the track ({m.reason})"
        )
        return self._answer(stamp, "none", False, None, None, event, None, m.reason)

    def _disagreement(self, ev: Evidence, T_pred: np.ndarray, P_T: np.ndarray) -> float:
        """Squared Mahalanobis distance of this frame's own evidence to the prediction, under the evidence's own
        covariance plus the prediction's (never the inflated one the filter fuses)."""
        return mahalanobis2(P_T + ev.covariance, log_left(ev.T_ego_peer, T_pred))

    def _supported(self, ev: Evidence | None) -> str | None:
        """Why this frame's evidence cannot validate an answer, or None: a refinement that found too little of the
        peer on the ego (below support_ratio of the track's recent evidence: a local minimum near a wrong
        prediction finds a fraction of what the right pose found)."""
        if ev is None:
            return "no refinement of this frame"
        if self.support is not None and ev.fitness < self.cfg.support_ratio * self.support:
            return (
                f"the refinement found {ev.fitness:.2f} of the peer, under {self.cfg.support_ratio:g} of the "
                f"track's {self.support:.2f}"
            )
        return None

    def _evidence_answer(self, stamp: float, ev: Evidence, O_e: np.ndarray, O_p: np.ndarray):
        """The answer this frame's own evidence gives, with the recent frames' (the stream's, with odometry): (T,
        covariance of left increments, why it is not valid or None). Without odometry the relative motion between
        frames is unknown, so the answer is this frame's own measurement."""
        if not self.with_odometry:
            return ev.T_ego_peer, ev.covariance, self._within(ev.T_ego_peer, ev.covariance)
        self.stream.add(offset_sample(stamp, ev.T_ego_peer, ev.covariance, O_e, O_p, odometry_drift(self.cfg)))
        return self._stream_answer(stamp, O_e, O_p)

    def _stream_answer(self, stamp: float, O_e: np.ndarray, O_p: np.ndarray, trim: bool = True):
        """The stream's fused evidence at ``stamp`` as T_ego_peer through the cars' odometry poses then: (T,
        covariance of left increments, why it is not valid or None); None when the stream holds no frame."""
        fused = self.stream.fused(stamp, trim)
        if fused is None:
            return None
        H = adjoint(np.linalg.inv(O_e))
        T, P_T = np.linalg.inv(O_e) @ fused.X @ O_p, H @ fused.covariance @ H.T
        return T, P_T, self._within(T, P_T, fused.frames)

    def _within(self, T: np.ndarray, P_T: np.ndarray, frames: int = 1) -> str | None:
        """Why the answer T (covariance P_T of left increments) does not keep the answer rule's promise, or None."""
        a = self.answer
        p = probability_within(params_covariance(P_T, T), a.max_error_m, a.max_error_deg)
        if p >= a.confidence:
            return None
        held = "this frame's evidence" if frames == 1 else f"the evidence of {frames} frames"
        return (
            f"{held} puts the answer within {a.max_error_m:g} m / {a.max_error_deg:g} deg with probability "
            f"{p:.2f} only (answer.confidence {a.confidence:g})"
        )

    # ---- a frame not measured ---------------------------------------------------------------------------------
    def unmeasured(self, stamp: float, O_ego: np.ndarray, O_peer: np.ndarray, ego_stamp: float | None = None):
        """A frame the caller will not measure (a service behind its frames): the stream's recent evidence carried
        to it by both cars' odometry (``_carried``), when that is a valid answer and nothing about this frame calls
        for the engine (a new or lost track, an odometry jump or unchecked gap, an event to report, a frame out of
        order or after a long gap, a track due for the full method); else None (``step`` the frame then). The stream
        is left as it was, misses and support too: the frame neither confirms nor fails; the filter and the
        odometry watch move on to it, as for a frame the refinement could not measure."""
        if (
            self.X is None
            or not self.with_odometry
            or self.pending_event
            or not 0 < stamp - self.stamp <= self.cfg.max_gap_s
        ):
            return None
        O_e, O_p = np.asarray(O_ego, float), np.asarray(O_peer, float)
        poses = {"ego": (stamp if ego_stamp is None else ego_stamp, O_e), "peer": (stamp, O_p)}
        jump, unchecked_m = self.odometry.check(poses)
        if jump:
            return None
        X, P, _, H = self._predict(stamp - self.stamp, O_e, O_p)
        if self._full_method_due(stamp, H @ P @ H.T, unchecked_m):
            return None
        carried = self._carried(stamp, O_e, O_p, trim=False)  # the next measured frame's fusion trims the stream
        if carried is None or carried[2] is not None:
            return None
        self.odometry.record(poses)
        self._keep(stamp, X, P)
        return self._answer(stamp, "stream", True, carried[0], carried[1])

    # ---- the cross-check beside the track ----------------------------------------------------------------------
    def crosscheck_due(self, stamp: float) -> bool:
        """A track whose last full acquisition is crosscheck_s old at ``stamp``."""
        return self.X is not None and self.cfg.crosscheck_s > 0 and stamp - self.last_acquired >= self.cfg.crosscheck_s

    def begin_crosscheck(self, stamp: float) -> int | None:
        """When a cross-check beside the track is due at ``stamp`` (a tracked frame with odometry): mark it begun
        and return the track's epoch, to hand back to ``finish_crosscheck``; else None."""
        if not (self.with_odometry and self.crosscheck_due(stamp)):
            return None
        self.last_acquired = stamp
        return self.epoch

    def finish_crosscheck(self, epoch: int, m: Measurement, O_ego: np.ndarray, O_peer: np.ndarray) -> str | None:
        """Apply the full acquisition of an earlier frame (with that frame's odometry) of track ``epoch``: fused
        into the offset when it agrees, the track dropped when it does not (the next frame acquires afresh and its
        answer says why). Ignored when that track is gone or the acquisition failed. Returns the event, if any."""
        if epoch != self.epoch or self.X is None or not m.ok:
            return None
        O_e, O_p = np.asarray(O_ego, float), np.asarray(O_peer, float)
        A = adjoint(O_e)  # left increments of that frame's T_ego_peer -> of X
        nu = log_left(O_e @ m.T_ego_peer @ np.linalg.inv(O_p), self.X)
        # The drift since that frame is left out: a little tighter gate, never a looser one.
        d2, dx, P = kalman_step(self.P, np.eye(3), A @ np.asarray(m.covariance, float) @ A.T, nu)
        if d2 > self.cfg.gate_chi2:
            self.pending_event = self._drop(
                f"the cross-check acquisition disagrees with the track (Mahalanobis^2 {d2:.1f})"
            )
            return self.pending_event
        self.X, self.P = se2(*dx) @ self.X, P
        self.rejects = 0
        return None

    # ---- steps -------------------------------------------------------------------------------------------------
    def _predict(self, dt: float, O_e: np.ndarray, O_p: np.ndarray):
        """The state dt seconds on, its covariance, the predicted T_ego_peer and H (state increment -> left
        increment of T_ego_peer)."""
        c = self.cfg
        if self.with_odometry:
            # Each car's odometry drifts in its own body frame: the ego's error is a left increment of T_ego_peer,
            # the peer's a right one (at the peer, up to 100 m away: its yaw drift moves the peer sideways in the
            # ego frame). Both carried to left increments of X = O_e T O_p^-1.
            q = odometry_drift(c) * dt
            T_prev = np.linalg.inv(O_e) @ self.X @ O_p
            Ad_T, A = adjoint(T_prev), adjoint(O_e)
            X, P = self.X, self.P + A @ (q + Ad_T @ q @ Ad_T.T) @ A.T  # the offset stays; its uncertainty grows
            H = adjoint(np.linalg.inv(O_e))
        else:
            X = se2(*(self.w * dt)) @ self.X
            F = np.eye(6)
            F[:3, 3:] = np.eye(3) * dt
            qa = np.diag(
                np.array(
                    [np.radians(c.relative_accel_deg_per_s2), c.relative_accel_m_per_s2, c.relative_accel_m_per_s2]
                )
                ** 2
            )
            Q = np.block([[qa * dt**3 / 3, qa * dt**2 / 2], [qa * dt**2 / 2, qa * dt]])  # white acceleration
            P = F @ self.P @ F.T + Q
            H = np.hstack([np.eye(3), np.zeros((3, 3))])
        return X, P, np.linalg.inv(O_e) @ X @ O_p, H

    def _update(
        self, stamp, m: Measurement, X, P, T_pred, H, O_e, O_p, source: str, crosscheck: bool = False
    ) -> TrackAnswer:
        """Kalman update on left increments; a measurement outside the Mahalanobis gate is rejected. The answer is
        valid only on the evidence of this frame and the stream's (``_evidence_answer``)."""
        nu = log_left(m.T_ego_peer, T_pred)
        d2, dx, P_new = kalman_step(P, H, np.asarray(m.covariance, float), nu)
        ev = m.evidence
        if d2 > self.cfg.gate_chi2:
            if crosscheck:  # a full acquisition that disagrees with the track: the track was wrong
                event = self._drop(f"the cross-check acquisition disagrees with the track (Mahalanobis^2 {d2:.1f})")
                return self._acquire(stamp, m, O_e, O_p, self.with_odometry, event)
            self.rejects += 1
            self.misses += 1
            if self.rejects >= self.cfg.max_rejects:
                event = self._drop(f"{self.rejects} measurements in a row outside the gate (Mahalanobis^2 {d2:.1f})")
                return self._answer(stamp, "none", False, None, None, event, d2)
            return self._coast(stamp, X, P, T_pred, H @ P @ H.T, f"measurement outside the gate ({d2:.1f})", True, d2)
        self.rejects = 0
        if self.with_odometry:
            X = se2(*dx) @ X
        else:
            X = se2(*dx[:3]) @ X
            self.w = self.w + dx[3:]
        self._keep(stamp, X, P_new)
        self.last_fused = stamp
        # The filter only predicts (where to refine from, what to gate); its pose is the answer only when no frame
        # of the stream supports one, and then never a valid one.
        T, P_T = np.linalg.inv(O_e) @ X @ O_p, H @ self.P @ H.T
        if source == "acquisition" and ev is not None:
            self.support = ev.fitness  # a full acquisition that agrees: the reference the next frames are held to
        why = self._supported(ev)
        confirmed = why is None
        if confirmed:
            T, P_T, why = self._evidence_answer(stamp, ev, O_e, O_p)
            confirmed = why is None
        elif ev is None and (carried := self._carried(stamp, O_e, O_p)) is not None:
            (T, P_T, why), source = carried, "stream"  # the boxes alone measured this frame: no evidence of its own
        if confirmed:  # this frame's own evidence confirms the track
            self.misses = 0
            self.support = ev.fitness if self.support is None else 0.5 * (self.support + ev.fitness)
        else:
            self.misses += 1
        return self._answer(stamp, source, why is None, T, P_T, None, d2, why)

    def _coast(self, stamp, X, P, T_pred, P_T, why: str, rejected: bool, d2=None, odometry=None) -> TrackAnswer:
        """No usable measurement this frame: the prediction stands, never as a valid answer (nothing of this frame
        supports it); with ``odometry`` (O_e, O_p) the stream's recent evidence may answer (``_carried``)."""
        self._keep(stamp, X, P)
        carried = None if odometry is None else self._carried(stamp, *odometry)
        if carried is not None:
            T, cov, why_not = carried
            return self._answer(stamp, "stream", why_not is None, T, cov, why, d2, why_not)
        return self._answer(stamp, "prediction", False, T_pred, P_T, why, d2, why)

    def _carried(self, stamp: float, O_e: np.ndarray, O_p: np.ndarray, trim: bool = True):
        """A frame with no evidence of its own: the stream's frames, the newest at most ``stream_coast_s`` old, fused
        and carried to it by both cars' odometry, the covariance grown by their drift since: (T, covariance, why it
        is not valid or None); None when there are none that recent (or tracking without odometry)."""
        samples = self.stream.samples
        if not (self.with_odometry and samples and stamp - samples[-1].stamp <= self.cfg.stream_coast_s):
            return None
        return self._stream_answer(stamp, O_e, O_p, trim)

    def _acquire(self, stamp, m: Measurement, O_e, O_p, odometry: bool, event: str | None) -> TrackAnswer:
        """A full acquisition's outcome: a new track, or (failed) the old track given up."""
        self.last_acquired = stamp
        if not m.ok:
            return self._answer(stamp, "acquisition", False, None, None, event or m.reason)
        self.with_odometry = odometry
        A = adjoint(O_e)  # left increments of T_ego_peer -> of X = O_e T O_p^-1
        P = A @ np.asarray(m.covariance, float) @ A.T
        if not odometry:
            v0 = np.array(
                [
                    np.radians(self.cfg.initial_relative_yaw_rate_deg_per_s),
                    self.cfg.initial_relative_speed_m_per_s,
                    self.cfg.initial_relative_speed_m_per_s,
                ]
            )
            P = np.block([[P, np.zeros((3, 3))], [np.zeros((3, 3)), np.diag(v0**2)]])
        self.w = np.zeros(3)
        self.rejects = self.misses = 0
        self.support = m.evidence.fitness if m.evidence is not None else None
        self.last_fused = stamp
        changed = self.state != TrackState.tracking
        self.state = TrackState.tracking
        self.epoch += 1
        self._keep(stamp, O_e @ m.T_ego_peer @ np.linalg.inv(O_p), P)
        if changed:
            event = (event + "; acquired") if event else "acquired"
        self.last_event = event or self.last_event
        # The engine's verdict starts the track and the stream's evidence; the answer keeps the answer rule's promise
        # like a tracked one.
        self.stream.clear()
        T, cov, why = m.T_ego_peer, np.asarray(m.covariance, float), None
        if m.evidence is not None:
            T, cov, why = self._evidence_answer(stamp, m.evidence, O_e, O_p)
        return self._answer(stamp, "acquisition", why is None, T, cov, event, None, why)

    # ---- bookkeeping -------------------------------------------------------------------------------------------
    def _keep(self, stamp: float, X: np.ndarray, P: np.ndarray) -> None:
        self.stamp, self.X, self.P = stamp, X, P

    def _drop(self, why: str) -> str:
        self.epoch += 1
        self.X = self.P = None
        self.w = np.zeros(3)
        self.state = TrackState.lost
        self.rejects = self.misses = 0
        self.support = None
        self.stream.clear()
        self.last_event = f"lost: {why}"
        return self.last_event

    def _answer(self, stamp, source, valid, T, cov, event=None, d2=None, why_not=None) -> TrackAnswer:
        return TrackAnswer(stamp, self.state, source, valid, T, cov, event, d2, why_not)
