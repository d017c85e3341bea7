"""The acquisition as a pipeline step (Algorithm 1 lines 9-11 in multi mode): candidates -> hypotheses ->
verification -> decision, each a named call below; the verdict judges the decision."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..box_poses import BoxSet
from ..config import AlignConfig
from ..frame import PreparedFrame
from ..refine import BevCloud, bev_samples, peer_normals
from ..result import AlignResult
from ..verdict import FailureReason, Verdict
from . import free_space
from .candidates import topk_candidates
from .decision import Decision, decide, margin, runner_up_of
from .hypotheses import box_hypotheses, pose_hypotheses, with_keypoint_inliers
from .kernels import ego_pairs
from .model import Acquisition, Hypothesis, PriorWindow, SearchMemo
from .verification import COARSE_POINTS, Sample, coarse_config, covisible, verify


@dataclass
class _Search:
    """One search of a frame pair: the frames, the peer keypoints with candidates, what verification reads (the
    ego's cloud and co-visibility mask, the peer's seeded samples, both cars' boxes) and what is shared."""

    ego: PreparedFrame
    peer: PreparedFrame
    timed: object  # name -> context manager adding its time to the result's timings
    window: PriorWindow | None
    memo: SearchMemo
    keep_votes: bool  # a lone search does not hold its first pass's votes (5 MB) through the second
    kp: np.ndarray  # (Q, 2) the peer keypoints with a usable descriptor
    t_half: float  # the pose accumulator's reach in tx and ty, metres
    ego_cloud: BevCloud
    covis: np.ndarray
    coarse_sample: Sample
    full_sample: Sample
    boxes: tuple[BoxSet, BoxSet]
    proposed: list[Hypothesis]  # poses not from the keypoint vote (the boxes', the prior)


class Acquirer:
    """Stage 1 in multi mode as a pipeline step, built once from the config: candidates, hypotheses by voting,
    dense verification, decision by margin and relative fitness. ``__call__`` fills the result (T_bv, inliers,
    fitness, the typed ``Acquisition``) and returns (FailureReason or None, the refinement's peer points and their
    normals)."""

    def __init__(self, config: AlignConfig, verdict: Verdict | None = None):
        if not config.refine.enabled:
            raise ValueError(
                "acquire.mode='multi' verifies hypotheses with the dense refinement: refine.enabled must be True"
            )
        self.config = config
        self.verdict = verdict or Verdict.of(config)
        self.coarse = coarse_config(config.refine)

    def __call__(
        self,
        ego: PreparedFrame,
        peer: PreparedFrame,
        result: AlignResult,
        timed,
        window: PriorWindow | None = None,
        memo: SearchMemo | None = None,
    ) -> tuple[FailureReason | None, Sample | None]:
        """``window``: only hypotheses inside it are formed, verified and counted as rivals, and its prior pose is
        verified as one more hypothesis (config.prior.verify_prior_pose). ``memo``: what an earlier search of the
        same two frames found (read) or an empty one (filled)."""
        keep_votes, memo = memo is not None, memo or SearchMemo()
        with timed("matching"):
            rows, cand = self.candidates(ego, peer, memo)
        result.matches_bv = int(cand.size)
        if (reason := self.verdict.candidates(len(rows))) is not None:
            return reason, None
        s = self._search(ego, peer, rows, timed, window, memo, keep_votes)
        hyps, used = self.hypotheses_verified(s, cand, result.notes)
        if (reason := self.verdict.hypotheses(hyps)) is not None:
            return reason, None
        decision, hyps, bound = self.decision(s, hyps, result.notes)
        self._report(result, s, decision, hyps, bound, rows, used, int(cand.size))
        return self.verdict.acquisition(decision, result.notes), s.full_sample

    # ---- 1. candidates ---------------------------------------------------------------------------------------
    def candidates(self, ego: PreparedFrame, peer: PreparedFrame, memo: SearchMemo) -> tuple[np.ndarray, np.ndarray]:
        """(peer rows with a usable descriptor, their acquire.top_k nearest ego keypoints), once per frame pair."""
        cfg = self.config
        if memo.candidates is None:
            desc_ref = ego.reference_descriptors(cfg.features, cfg.mim.n_orient)
            memo.candidates = topk_candidates(
                peer.descriptors, desc_ref, len(ego.descriptors), cfg.acquire.top_k, threads=cfg.match.threads
            )
        return memo.candidates

    def _search(self, ego, peer, rows, timed, window, memo, keep_votes) -> _Search:
        """What every search pass of this frame pair reads: the peer's pixels sampled once (seeded) for every
        verification, the ego's cloud and mask, and the poses the boxes (and the prior) propose."""
        cfg, a, rf = self.config, self.config.acquire, self.config.refine
        coarse_pts, full_pts = bev_samples(peer.bev, rf.min_pixel_value, [COARSE_POINTS, rf.max_peer_points], cfg.seed)
        coarse_sample, full_sample = ((p, peer_normals(peer.bev, p, rf)) for p in (coarse_pts, full_pts))
        with timed("hypotheses"):
            if memo.proposed is None:
                memo.proposed = box_hypotheses(ego.boxes, peer.boxes, a)  # poses not from the keypoint vote
            proposed = memo.proposed
            if window is not None:
                proposed = [h for h in proposed if window.holds(h.T)]
                if cfg.prior.verify_prior_pose:
                    proposed.append(Hypothesis(T=window.T.copy(), inliers=0, source="prior"))
        return _Search(
            ego=ego,
            peer=peer,
            timed=timed,
            window=window,
            memo=memo,
            keep_votes=keep_votes,
            kp=peer.keypoints_xy[rows],
            t_half=1.5 * max(ego.bev.range_m, peer.bev.range_m),
            ego_cloud=ego.cloud(rf),
            covis=covisible(ego, cfg),
            coarse_sample=coarse_sample,
            full_sample=full_sample,
            boxes=(BoxSet.of(ego.boxes), BoxSet.of(peer.boxes)),
            proposed=proposed,
        )

    # ---- 2. + 3. hypotheses, verified ------------------------------------------------------------------------
    def hypotheses_verified(
        self, s: _Search, cand: np.ndarray, notes: list[str]
    ) -> tuple[list[Hypothesis], np.ndarray]:
        """The verified hypotheses, best first, and the candidates they were formed from. Cheap first: the
        acquire.first_k nearest candidates only (a close pair needs no more), kept only when its evidence is far
        above the success threshold; else the full top-k search."""
        a = self.config.acquire
        if 0 < a.first_k < cand.shape[1]:
            used = np.ascontiguousarray(cand[:, : a.first_k])
            hyps = self.verification(s, self.hypotheses(s, used))
            if hyps and margin(hyps, a) * hyps[0].relative_fitness >= a.first_pass_evidence:
                notes.append(f"acquired on the first {a.first_k} candidates per keypoint")
                return hyps, used
        return self.verification(s, self.hypotheses(s, cand)), cand

    def hypotheses(self, s: _Search, cand: np.ndarray) -> list[Hypothesis]:
        """The keypoint vote's distinct poses, then the proposed ones distinct from them."""
        cfg, ego = self.config, s.ego
        thr = cfg.ransac.inlier_threshold_m
        with s.timed("hypotheses"):
            pairs = ego.cached("ego_pairs", lambda: ego_pairs(np.ascontiguousarray(ego.keypoints_xy, np.float64)))
            votes = s.memo.votes if s.keep_votes else None
            hs = pose_hypotheses(s.kp, ego.keypoints_xy, cand, cfg.acquire, thr, s.t_half, pairs, s.window, votes)
            hs += with_keypoint_inliers(s.proposed, hs, s.kp, ego.keypoints_xy, cand, cfg.acquire, thr)
        return hs

    def verification(self, s: _Search, hyps: list[Hypothesis]) -> list[Hypothesis]:
        """The hypotheses refined densely and scored, best first (``verify``; in place)."""
        if hyps:
            with s.timed("verify"):
                verify(
                    hyps, s.ego_cloud, s.covis, s.coarse_sample, s.full_sample, self.config, self.coarse, s.boxes,
                    s.window,
                )  # fmt: skip
        return hyps

    # ---- 4. decision -----------------------------------------------------------------------------------------
    def decision(
        self, s: _Search, hyps: list[Hypothesis], notes: list[str]
    ) -> tuple[Decision, list[Hypothesis], float]:
        """The facts the verdict judges, the hypotheses they are about (without those the free space ruled out
        when the best gave way) and the conflict bound above which a hypothesis is no rival."""
        cfg = self.config
        fs = cfg.free_space
        bound, gave_way = (fs.rival_conflict if fs.enabled else 1.0), False
        if fs.enabled:
            with s.timed("free_space"):
                hyps, bound, gave_way = self._free_space(s, hyps, notes)
        reach = (cfg.box.max_correction_m, cfg.box.max_correction_deg)
        weighed = s.window is not None and cfg.landscape.enabled
        return decide(hyps, cfg.acquire, bound, reach, weighed, gave_way), hyps, bound

    def _free_space(self, s: _Search, hyps: list[Hypothesis], notes: list[str]):
        """(hypotheses, rival conflict bound, whether the best gave way): every hypothesis's conflict measured; a
        best the free space rules out gives way to the best of the others (free_space.ruled_out_first)."""
        cfg = self.config
        free_space.conflicts(s.ego, s.peer, hyps, cfg)
        bound = free_space.rival_bound(hyps, cfg)
        if not (cfg.free_space.ruled_out_first and hyps[0].conflict > bound):
            return hyps, bound, False
        kept = free_space.without_ruled_out(
            s.ego, s.peer, hyps, s.ego_cloud, s.covis, s.full_sample, s.boxes, bound, cfg
        )
        if not kept:  # the ruled-out best stands, and is refused by the verdict
            return hyps, bound, False
        notes.append(
            f"the free space rules out {len(hyps) - len(kept)} hypotheses (best conflict "
            f"{hyps[0].conflict:.2f}); the best of the others is judged"
        )
        return kept, bound, True

    def _report(self, result, s: _Search, d: Decision, hyps, bound, rows, used, n_cand) -> None:
        """The best hypothesis as stage 1's answer, with the typed Acquisition and its keypoint inliers."""
        best = d.best
        runner_up = runner_up_of(hyps, self.config.acquire, bound)
        result.acquisition = Acquisition(best, runner_up, hyps, n_cand, d.margin, d.gave_way)
        result.T_bv, result.inliers_bv, result.refine_fitness = best.T, best.inliers, best.fitness
        result.ambiguity_bv = 1.0 / max(1.0, d.margin)
        mask = best.inlier_mask
        result.inlier_xy_peer = np.repeat(s.peer.keypoints_xy[rows], used.shape[1], axis=0)[mask]
        result.inlier_xy_ego = s.ego.keypoints_xy[used.ravel()][mask]
