"""A first answer from a second of stream (not in the paper): several frames of each car, their odometry known.

One frame pair 70-100 m apart often cannot tell the true pose from an alias (a pose along the street, the two cars'
near fields laid over each other), nor pin the true one to a metre along the street. With each car's odometry
between its frames, every frame pair measures the same offset ``X = O_e T_ego_peer O_p^-1`` (engine.evidence), so
a pose must explain every frame, and an alias that does not persist loses its weight:

1. **hypotheses**: the full search (``Aligner.align``) on a few of the frames (``search_frames``), every pose it
   verified and the free space did not rule out (the best and its rivals) taken to X with that frame's odometry;
2. **each hypothesis explained by every frame**: the frame's refinement from ``inv(O_e) X O_p`` judged on its pose
   landscape (what a tracked frame's own evidence is: ``Aligner.measure`` and ``Aligner.judge``) and on the two
   LiDARs' free space; the frames that bound it and agree on it (as the stream's evidence keeps frames) must be at
   least ``min_bounded_share`` of them, its score is the sum of their landscape peaks, and a hypothesis the free
   space rules out on their average is dropped;
3. **the winner and its rivals**: the best-scoring hypothesis wins; each other one (distinct after refinement, within
   the free space's rival bound) weighs ``exp(effective_points x (its score - the winner's) / (1 + rho (n - 1)))``:
   frames that share their errors are not independent evidence (the fusion's own design effect, ``rho`` =
   ``track.evidence_correlation``);
4. **the answer**: the winner's frames fused as the stream fuses them (``StreamEvidence``: information-weighted,
   the odometry's drift since each frame, the design effect, frames that disagree left out), at the last frame,
   widened by the rivals as modes; ``success`` by the answer rule, as every answer.

With a reported pose (a GNSS-grade ``T_prior`` at the last frame), as ``align --prior`` is for one pair: each
searched frame is searched with the prior carried to it by the odometry, a hypothesis farther from it than the
prior's window (``prior.max_translation_m`` / ``max_yaw_deg``) is dropped, and the winner and its rivals' weights
count the prior's density (``prior.sigma_m`` / ``sigma_deg``) beside the frames' scores. When the frames alone (no
prior) answer successfully outside the window, the images and the report disagree: refused
(``disagrees_with_prior``), never an alias inside the window instead.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .acquisition.free_space import conflicts
from .acquisition.model import Hypothesis
from .covariance import left_covariance, params_covariance, probability_within
from .evidence import StreamEvidence
from .frame import PreparedFrame
from .geometry import distinct_pose, ground_se2, log_left, pose_error, se2_params
from .landscape import GaussianPrior
from .result import AlignResult
from .tracker import adjoint, odometry_drift, offset_sample, shared_error
from .verdict import FailureReason


@dataclass
class StreamFrame:
    """One instant of the stream: both cars' prepared frames and odometry poses (3x3 or 4x4, ``O_ego`` =
    T_egoodom_ego, ``O_peer`` = T_peerodom_peer), ``stamp`` in seconds."""

    ego: PreparedFrame
    peer: PreparedFrame
    O_ego: np.ndarray
    O_peer: np.ndarray
    stamp: float


@dataclass
class _Explained:
    """A hypothesis X explained by every frame: the landscape scores of the frames that agree on it, the free
    space's conflict there and the frames' fusion."""

    X: np.ndarray
    scores: list[float] = field(default_factory=list)
    conflict: float = 0.0
    fused: tuple[np.ndarray, np.ndarray, int] | None = None  # (X, covariance of its left increments, frames)

    @property
    def score(self) -> float:
        return float(sum(self.scores))


class StreamAcquirer:
    """Acquisition over a second of stream (the module doc). Built once per aligner; ``__call__`` per stream."""

    def __init__(self, aligner):
        self.aligner = aligner
        self.cfg = aligner.config

    def __call__(self, frames: list[StreamFrame], T_prior: np.ndarray | None = None) -> AlignResult:
        if not frames:
            raise ValueError("frames: at least one frame of each car is needed")
        frames = [_ground(f) for f in sorted(frames, key=lambda f: f.stamp)]
        sc = self.cfg.stream
        r = AlignResult(success=False, T_ego_peer=np.eye(4), T_bv=np.eye(3), T_box=np.eye(3))
        X_prior = None
        if T_prior is not None:  # the reported pose at the last frame, as an odometry offset
            X_prior = frames[-1].O_ego @ ground_se2(np.asarray(T_prior, dtype=float)) @ np.linalg.inv(frames[-1].O_peer)
        seeds = self.hypotheses(frames, r, X_prior)
        explained = [self.explain(frames, X) for X in seeds[: sc.max_hypotheses]]
        explained = [e for e in explained if e.fused is not None]
        r.notes.append(
            f"stream acquisition: {len(frames)} frames over {frames[-1].stamp - frames[0].stamp:.2f} s, "
            f"{len(seeds)} hypotheses from {min(sc.search_frames, len(frames))} searched frames, "
            f"{len(explained)} bounded by the frames"
        )
        ruled_out = [e for e in explained if e.conflict > self.cfg.free_space.max_conflict]
        explained = [e for e in explained if e.conflict <= self.cfg.free_space.max_conflict]
        if ruled_out:
            r.notes.append(f"the free space rules out {len(ruled_out)} of them")
        if X_prior is not None and explained:
            if self._images_disagree(r, frames, explained, X_prior):
                return self._finish(r, FailureReason.disagrees_with_prior, frames)
            inside = [e for e in explained if self._inside_prior(e.fused[0], X_prior, frames[-1])]
            if len(inside) < len(explained):
                r.notes.append(f"{len(explained) - len(inside)} outside the reported pose's window")
            explained = inside
        if not explained:
            why = FailureReason.free_space_conflict if ruled_out else FailureReason.too_few_inliers_bv
            return self._finish(r, why, frames)
        weigh = self._weigh(frames, X_prior)
        explained.sort(key=lambda e: -weigh(e))
        best = explained[0]
        self._answer(r, frames, best, self._rivals(best, explained[1:], weigh))
        return self._finish(r, None, frames)

    def _images_disagree(self, r: AlignResult, frames, explained: list[_Explained], X_prior: np.ndarray) -> bool:
        """As for one pair with a prior: what the frames alone answer (no prior) stands against the report when it
        is a success outside the prior's window (an alias inside the window must not win because the report
        lies); a failure alone leaves the search inside the window."""
        weigh = self._weigh(frames, None)
        ranked = sorted(explained, key=lambda e: -weigh(e))
        if self._inside_prior(ranked[0].fused[0], X_prior, frames[-1]):
            return False
        alone = AlignResult(success=False, T_ego_peer=np.eye(4), T_bv=np.eye(3), T_box=np.eye(3))
        self._answer(alone, frames, ranked[0], self._rivals(ranked[0], ranked[1:], weigh))
        a = self.cfg.answer
        if probability_within(alone.covariance, a.max_error_m, a.max_error_deg) < a.confidence:
            return False
        t_err, r_err = pose_error(alone.T_bv, _at(frames[-1], X_prior))
        r.T_bv, r.covariance = alone.T_bv, alone.covariance
        r.notes.append(
            f"the frames alone answer {t_err:.1f} m / {r_err:.1f} deg from the reported pose (prior tolerance "
            f"{self.cfg.prior.max_translation_m:g} m / {self.cfg.prior.max_yaw_deg:g} deg)"
        )
        return True

    def _inside_prior(self, X: np.ndarray, X_prior: np.ndarray, last: StreamFrame) -> bool:
        """Whether the pose of offset X lies within the prior's window of the reported one, at the last frame."""
        t_err, r_err = pose_error(_at(last, X), _at(last, X_prior))
        p = self.cfg.prior
        return t_err <= p.max_translation_m and r_err <= p.max_yaw_deg

    def _weigh(self, frames: list[StreamFrame], X_prior: np.ndarray | None):
        """A hypothesis's log weight: its frames' summed landscape scores times ``effective_points`` over the design
        effect (frames that share their errors are not independent evidence), plus the prior's log density of its
        pose at the last frame."""
        design = 1.0 + self.cfg.track.evidence_correlation * (len(frames) - 1)
        points, last = self.cfg.landscape.effective_points, frames[-1]
        prior = None
        if X_prior is not None:
            pc = self.cfg.prior
            prior = GaussianPrior(_at(last, X_prior), pc.sigma_m, pc.sigma_deg)

        def log_weight(e: _Explained) -> float:
            w = points * e.score / design
            if prior is not None:
                w += float(prior.log_density(np.array(se2_params(_at(last, e.fused[0]))))[0])
            return w

        return log_weight

    # ---- 1. hypotheses -----------------------------------------------------------------------------------------
    def hypotheses(
        self, frames: list[StreamFrame], r: AlignResult, X_prior: np.ndarray | None = None
    ) -> list[np.ndarray]:
        """The poses the full search verified on ``search_frames`` of the frames (the last, then spread over the
        stream), as offsets X: every searched frame's best first, then their second best, and so on (no frame's
        aliases crowd out another frame's answer); near ones merged, those the free space rules out left out.
        ``X_prior``: each frame searched with the reported pose carried to it (``Aligner.align``'s ``T_prior``)."""
        n, k = len(frames), min(self.cfg.stream.search_frames, len(frames))
        picks = sorted({int(round(i)) for i in np.linspace(n - 1, 0, k)}, reverse=True)
        ac, fs = self.cfg.acquire, self.cfg.free_space
        ranked: list[list[np.ndarray]] = []
        for i in picks:
            f = frames[i]
            T_prior = None if X_prior is None else np.linalg.inv(f.O_ego) @ X_prior @ f.O_peer
            res = self.aligner.align(f.ego, f.peer, T_prior=T_prior)
            for name, ms in res.timings_ms.items():
                r.timings_ms[f"search_{name}"] = r.timings_ms.get(f"search_{name}", 0.0) + ms
            hyps: list[Hypothesis] = [] if res.acquisition is None else res.acquisition.hypotheses
            ok = [h for h in hyps if not (fs.enabled and h.conflict > fs.rival_conflict)]
            ranked.append([f.O_ego @ h.T @ np.linalg.inv(f.O_peer) for h in ok])
        seeds: list[np.ndarray] = []
        for rank in range(max((len(x) for x in ranked), default=0)):
            for X in (x[rank] for x in ranked if rank < len(x)):
                if distinct_pose(X, seeds, ac.distinct_m, ac.distinct_deg):
                    seeds.append(X)
        return seeds

    # ---- 2. each hypothesis explained by every frame ------------------------------------------------------------
    def explain(self, frames: list[StreamFrame], X: np.ndarray) -> _Explained:
        a, sc = self.aligner, self.cfg.stream
        e, q = _Explained(X), odometry_drift(self.cfg.track)
        stream = self._stream(frames)
        hyps = []
        for f in frames:
            T_pred = np.linalg.inv(f.O_ego) @ X @ f.O_peer
            m = a.measure(f.ego, f.peer, T_pred)
            if not m.success:
                e.scores.append(0.0)
                continue
            land = a.judge(f.ego, f.peer, m.T_bv)
            e.scores.append(land.score)
            if land.at_edge:
                continue
            hyps.append((f, Hypothesis(T=land.T, inliers=0)))
            cov = left_covariance(land.covariance, land.T)
            stream.add(offset_sample(f.stamp, land.T, cov, f.O_ego, f.O_peer, q))
        fused = stream.fused(frames[-1].stamp)
        if fused is None or fused.frames < max(1, int(np.ceil(sc.min_bounded_share * len(frames)))):
            return e  # too few frames bound it and agree on it: no answer from this hypothesis
        e.fused = (fused.X, fused.covariance, fused.frames)
        # Its score is what the frames that agree on it found: the newest ``fused.frames`` of those bounding it.
        agreeing = {id(f) for f, _ in hyps[-fused.frames :]}
        e.scores = [sc_k for f, sc_k in zip(frames, e.scores) if id(f) in agreeing]
        hyps = hyps[-fused.frames :]
        if self.cfg.free_space.enabled:
            for f, h in hyps:
                conflicts(f.ego, f.peer, [h], self.cfg)
            e.conflict = float(np.mean([h.conflict for _, h in hyps]))
        return e

    def _stream(self, frames: list[StreamFrame]) -> StreamEvidence:
        tc = self.cfg.track
        span = frames[-1].stamp - frames[0].stamp
        return StreamEvidence(span + 1e-6, len(frames), shared_error(tc), tc.gate_chi2, tc.evidence_agreement)

    # ---- 3. rivals -----------------------------------------------------------------------------------------------
    def _rivals(self, best: _Explained, others: list[_Explained], weigh) -> list[tuple[float, _Explained]]:
        """(weight, hypothesis) of every other hypothesis distinct from the winner after refinement: exp of its log
        weight (``_weigh``) less the winner's."""
        ac = self.cfg.acquire
        out, kept, top = [], [best.fused[0]], weigh(best)
        for e in others:
            if not distinct_pose(e.fused[0], kept, ac.distinct_m, ac.distinct_deg):
                continue
            kept.append(e.fused[0])
            out.append((float(np.exp(min(50.0, weigh(e) - top))), e))
        return out

    # ---- 4. the answer --------------------------------------------------------------------------------------------
    def _answer(self, r: AlignResult, frames, best: _Explained, rivals) -> None:
        last = frames[-1]
        H = adjoint(np.linalg.inv(last.O_ego))
        X, P_X, kept = best.fused
        T = np.linalg.inv(last.O_ego) @ X @ last.O_peer
        P = H @ P_X @ H.T
        total, second = 1.0, P.copy()
        for w, e in rivals:
            T_r = np.linalg.inv(last.O_ego) @ e.fused[0] @ last.O_peer
            d = log_left(T_r, T)
            second += w * (H @ e.fused[1] @ H.T + np.outer(d, d))
            total += w
        P = second / total
        r.T_bv, r.covariance = T, params_covariance(0.5 * (P + P.T), T)
        weights = [w for w, _ in rivals]
        r.notes.append(
            f"the winner is bounded by {kept} of {len(frames)} frames (free-space conflict {best.conflict:.2f})"
            + (f"; its rivals weigh up to {max(weights):.3f} of it" if weights else "; no rival")
        )

    def _finish(self, r: AlignResult, reason: FailureReason | None, frames) -> AlignResult:
        """The verdict's finish; ``confidence`` is the answer rule's probability (0 without an answer)."""
        p = 0.0
        if reason is None:
            a = self.cfg.answer
            p = probability_within(r.covariance, a.max_error_m, a.max_error_deg)
            if p < a.confidence:
                reason = FailureReason.degenerate_pose
                r.notes.append(
                    f"the frames put the answer within {a.max_error_m:g} m / {a.max_error_deg:g} deg with "
                    f"probability {p:.2f} only (answer.confidence {a.confidence:g})"
                )
        r = self.aligner.verdict.finish(r, reason, tz=0.0, roll=0.0, pitch=0.0)
        r.confidence = float(p)
        return r


def _at(f: StreamFrame, X: np.ndarray) -> np.ndarray:
    """T_ego_peer (3x3) at frame f of the odometry offset X."""
    return np.linalg.inv(f.O_ego) @ X @ f.O_peer


def _ground(f: StreamFrame) -> StreamFrame:
    O_ego, O_peer = ground_se2(np.asarray(f.O_ego, float)), ground_se2(np.asarray(f.O_peer, float))
    return StreamFrame(f.ego, f.peer, O_ego, O_peer, f.stamp)
