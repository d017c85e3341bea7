"""The verdict: why an alignment fails, the success rule (the paper's Inliers_bv > 25 and Inliers_box > 6, plus
the checks this project adds against confident aliases) and the confidence, in one place.

Each check returns a :class:`FailureReason` or None, so the pipeline chains its stages with ``or`` and finishes
once (:meth:`Verdict.finish`).
"""

from __future__ import annotations

from enum import Enum
from typing import TYPE_CHECKING

import numpy as np

from .config import AcquireConfig, AlignConfig, AnswerRule, FreeSpaceConfig, SuccessRule
from .covariance import probability_within
from .geometry import se2_params, se3_from_se2, worst_sigma_m
from .result import AlignResult

if TYPE_CHECKING:
    from .acquisition.decision import Decision


class FailureReason(str, Enum):
    """Why an alignment did not succeed (``AlignResult.reason``)."""

    too_few_points = "too_few_points"  # a cloud had fewer than config.min_points points
    empty_image = "empty_image"  # a BV image has no lit pixels
    no_keypoints = "no_keypoints"  # FAST found (almost) nothing to describe
    too_few_matches = "too_few_matches"  # fewer descriptor matches than a rigid fit needs
    too_few_inliers_bv = "too_few_inliers_bv"  # stage 1 below the success rule
    ambiguous_bv = "ambiguous_bv"  # a distinct pose explains almost as many matches
    inconsistent_overlap = "inconsistent_overlap"  # after refinement too few BV pixels coincide (alias)
    free_space_conflict = "free_space_conflict"  # one car's structure lands where the other saw through (alias)
    degenerate_pose = "degenerate_pose"  # the pose's 1-sigma along its worst direction is too large (corridor)
    no_boxes = "no_boxes"  # boxes were required but one side sent none
    no_box_overlap = "no_box_overlap"  # no peer box lands on an ego box after stage 1
    too_few_inliers_box = "too_few_inliers_box"  # stage 2 below the success rule
    box_correction_too_large = "box_correction_too_large"  # stage 2 disagrees with stage 1 by too much
    # Tracking (bb_align.engine.follow), not in the paper:
    refinement_diverged = "refinement_diverged"  # the refinement from the prediction moved beyond its bounds
    outside_track_gate = "outside_track_gate"  # the measurement disagrees with the track's prediction
    track_uncertain = "track_uncertain"  # no usable measurement, and the prediction is too old or too uncertain
    out_of_order = "out_of_order"  # a frame older than the track's last one
    disagrees_with_prior = "disagrees_with_prior"  # the acquired pose is far from the reported one (alias or lie)


# Evidence -> confidence (Verdict.confidence): each stage's share saturates exponentially in its inliers above the
# success rule's minimum (the paper's Fig. 9 puts > 90 % of pairs under 1 m / 1 deg beyond 100 BV or 20 box inliers).
BV_INLIER_SCALE = 40.0  # BV inliers above the minimum giving 63 % of stage 1's share
BOX_INLIER_SCALE = 8.0  # likewise for box inliers
FITNESS_SPAN = 0.2  # stage 1's share grows linearly over this much refinement fitness above min_refine_fitness
CAP_STAGE1_FAILED = 0.1  # the most confidence a failure before stage 2 gets
CAP_STAGE2_FAILED = 0.5  # the most confidence when only stage 2 failed

# Stage 1 stands but stage 2 could not confirm it (confidence capped at CAP_STAGE2_FAILED, not CAP_STAGE1_FAILED).
UNCONFIRMED_BY_BOXES = frozenset(
    {FailureReason.no_boxes, FailureReason.no_box_overlap, FailureReason.too_few_inliers_box}
)
STAGE2_FAILURES = UNCONFIRMED_BY_BOXES | {FailureReason.box_correction_too_large}


class Verdict:
    """Built once from the config; judges each stage's evidence and finishes the result."""

    def __init__(
        self,
        rule: SuccessRule,
        answer: AnswerRule,
        acquire: AcquireConfig,
        *,
        min_points: int,
        min_keypoints: int,
        box_max_correction_m: float,
        box_max_correction_deg: float,
        refine_enabled: bool,
        free_space: FreeSpaceConfig | None = None,
    ):
        self.rule, self.answer, self.acquire = rule, answer, acquire
        self.min_points, self.min_keypoints = min_points, min_keypoints
        self.box_max_m, self.box_max_deg = box_max_correction_m, box_max_correction_deg
        self.refine_enabled = refine_enabled
        self.free_space = free_space or FreeSpaceConfig()

    @classmethod
    def of(cls, cfg: AlignConfig) -> Verdict:
        """The verdict of an alignment configuration."""
        return cls(
            cfg.success,
            cfg.answer,
            cfg.acquire,
            min_points=cfg.min_points,
            min_keypoints=cfg.min_keypoints,
            box_max_correction_m=cfg.box.max_correction_m,
            box_max_correction_deg=cfg.box.max_correction_deg,
            refine_enabled=cfg.refine.enabled,
            free_space=cfg.free_space,
        )

    def inputs(self, *frames) -> FailureReason | None:
        """Nothing to match: too few points, an empty image, (almost) no keypoints."""
        reason = self.images(*frames)
        if reason is None and any(len(f.keypoints_rc) < self.min_keypoints for f in frames):
            return FailureReason.no_keypoints
        return reason

    def images(self, *frames) -> FailureReason | None:
        """What a tracking measurement needs: enough points (when known) and a lit image on each side."""
        for f in frames:
            if f.num_points is not None and f.num_points < self.min_points:
                return FailureReason.too_few_points
            if f.lit_pixels == 0:
                return FailureReason.empty_image
        return None

    def measured(self, accepted: bool, fitness: float, min_fitness: float) -> FailureReason | None:
        """A tracking measurement: the refinement within its bounds, on at least min_fitness overlap."""
        if not accepted:
            return FailureReason.refinement_diverged
        return FailureReason.inconsistent_overlap if fitness < min_fitness else None

    def stage1(self, r: AlignResult) -> FailureReason | None:
        """Inliers_bv above the rule's minimum, and no distinct runner-up pose nearly as good."""
        if r.inliers_bv <= self.rule.min_inliers_bv:
            return FailureReason.too_few_inliers_bv
        if r.ambiguity_bv >= self.rule.max_ambiguity:
            return FailureReason.ambiguous_bv
        return None

    def candidates(self, peer_keypoints: int) -> FailureReason | None:
        """A rigid pose needs at least two peer keypoints with descriptor candidates (paper mode: 0 when RANSAC had
        fewer than two matches to fit)."""
        return FailureReason.too_few_matches if peer_keypoints < 2 else None

    def hypotheses(self, hyps: list) -> FailureReason | None:
        """Multi mode: no hypothesis with enough keypoint inliers survived verification."""
        return FailureReason.too_few_inliers_bv if not hyps else None

    def acquisition(self, d: Decision, notes: list[str]) -> FailureReason | None:
        """Multi mode: the best hypothesis (``d``: acquisition.decision.Decision) stands when the images single it
        out (margin and evidence; inside a prior's window the landscape weighs the rivals instead) or, failing that,
        the boxes do (never for a pose chosen after better-scoring ones gave way to the free space); when no rival
        beyond stage 2's reach has the boxes' vote instead; when it overlaps enough; and when the free space does not
        rule it out. Remarks go to ``notes``."""
        a, fs, best = self.acquire, self.free_space, d.best
        if not d.dense_ok and d.weighed:
            # Inside a prior's window the rivals are weighed in the answer's covariance instead (pipeline._judge): a
            # street's repeated structure then widens the uncertainty along it rather than refusing the pose.
            notes.append(f"margin {d.margin:.2f} inside the prior's window: the rivals are weighed instead")
        elif not d.dense_ok and d.gave_way:
            # Chosen because better-scoring poses gave way: the images misled once already, and the boxes pair at
            # many poses along rows of parked cars, so the images' own evidence must carry it.
            notes.append("chosen after better-scoring poses gave way: box evidence alone does not carry it")
            return FailureReason.ambiguous_bv
        elif not d.dense_ok and not d.box_confirmed:
            return FailureReason.ambiguous_bv
        if d.contradicting is not None:
            notes.append(
                f"the boxes vouch for another pose: {d.contradicting.box_pairs} cars on cars, {best.box_pairs} here"
            )
            return FailureReason.ambiguous_bv
        if not d.dense_ok and not d.weighed:
            notes.append(f"acquired on box evidence: {best.box_pairs} cars on cars, distinct poses fewer")
        if best.fitness < a.min_fitness or best.relative_fitness < a.min_relative_fitness:
            return FailureReason.inconsistent_overlap
        separation_m = float(np.hypot(best.T[0, 2], best.T[1, 2]))
        if separation_m < a.near_m and best.fitness < a.near_min_fitness:
            # Two LiDARs this near see nearly one scene; so little of it shared is two places' near fields overlaid
            notes.append(f"the peer placed {separation_m:.1f} m away shares only {best.fitness:.2f} of its image")
            return FailureReason.inconsistent_overlap
        if fs.enabled and best.conflict > (fs.gave_way_max_conflict if d.gave_way else fs.max_conflict):
            notes.append(f"free-space conflict {best.conflict:.2f}: structure where the other car saw through")
            return FailureReason.free_space_conflict
        return None

    def refined(self, r: AlignResult) -> FailureReason | None:
        """After the dense refinement, enough of the peer's lit pixels must land on ego pixels."""
        return FailureReason.inconsistent_overlap if r.refine_fitness < self.rule.min_refine_fitness else None

    def uncertain(self, r: AlignResult, max_sigma_m: float | None = None) -> FailureReason | None:
        """A pose whose covariance does not put the truth within the answer rule's bound (answer.max_error_m /
        max_error_deg) with at least answer.confidence is not a pose to act on: a long straight street pins it
        across, not along. ``max_sigma_m``: also a bound on the worst-direction 1-sigma (a pose found inside a
        prior's window without the landscape)."""
        cov = np.asarray(r.covariance)
        a = self.answer
        p = probability_within(cov, a.max_error_m, a.max_error_deg)
        if p < a.confidence:
            r.notes.append(
                f"its covariance puts it within {a.max_error_m:g} m / {a.max_error_deg:g} deg with probability "
                f"{p:.2f} (answer.confidence {a.confidence:g})"
            )
            return FailureReason.degenerate_pose
        if max_sigma_m is not None and worst_sigma_m(cov) > max_sigma_m:
            return FailureReason.degenerate_pose
        return None

    def without_boxes(self, r: AlignResult, missing: list[str]) -> FailureReason | None:
        if self.rule.require_boxes:
            return FailureReason.no_boxes
        r.notes.append("stage 2 skipped: no boxes from " + " and ".join(missing))
        return None

    def stage2(
        self, r: AlignResult, T_box: np.ndarray, densely_verified: bool = False, evidence: float | None = None
    ) -> FailureReason | None:
        """Inliers_box above the rule's minimum (or a densely verified multi-hypothesis pose when
        acquire.stage2_required is off, or when some boxes pair under it but too few corners agree and its
        ``evidence`` reaches acquire.stage2_waiver_evidence), and a correction within bounds."""
        failure = (
            FailureReason.no_box_overlap
            if r.box_pairs == 0
            else FailureReason.too_few_inliers_box
            if r.inliers_box <= self.rule.min_inliers_box
            else None
        )
        waiver = self.acquire.stage2_waiver_evidence
        # Only the count is waived: a pose under which no box of one car pairs with any of the other's has no
        # support beside the images (a street alias 42 m off passed a waiver of no_box_overlap, docs/acquisition.md)
        partly_supported = failure is FailureReason.too_few_inliers_box
        if partly_supported and densely_verified and evidence is not None and waiver is not None:
            if evidence >= waiver:
                r.notes.append(
                    f"stage 2 could not verify ({failure.value}); accepted on strong dense evidence "
                    f"({evidence:.2f} >= {waiver:g})"
                )
                return None
        if failure is not None and densely_verified and not self.acquire.stage2_required:
            r.notes.append(
                f"stage 2 could not verify ({failure.value}); accepted on the dense multi-hypothesis verification"
            )
            return None
        if failure is not None:
            return failure
        yaw, tx, ty = se2_params(T_box)
        if np.hypot(tx, ty) > self.box_max_m or abs(np.degrees(yaw)) > self.box_max_deg:
            return FailureReason.box_correction_too_large
        return None

    def within_prior(self, r: AlignResult, holds: bool) -> FailureReason | None:
        """Multi mode with a prior: the pose the search everywhere found must lie inside the prior's window (else
        the images and the report disagree: an alias, or a wrong or lying report)."""
        if holds:
            r.notes.append("the pose lies inside the prior's window")
            return None
        r.notes.append("the pose found everywhere lies outside the prior's window: refused")
        return FailureReason.disagrees_with_prior

    def boxes_disagree(self, r: AlignResult, refuse: bool) -> FailureReason | None:
        """The boxes' measurement and the refined pose disagree: two independent measurements contradict each
        other; refused when ``refuse`` (box.fuse_disagreement_fails), else the boxes are left out."""
        if refuse:
            r.notes.append("box measurement disagrees with the refined pose: refused")
            return FailureReason.box_correction_too_large
        r.notes.append("box measurement left out: disagrees")
        return None

    def boxes_verified(self, r: AlignResult) -> bool:
        """Stage 2 itself passed (its correction may be applied)."""
        return r.box_pairs > 0 and r.inliers_box > self.rule.min_inliers_box

    def finish(
        self, r: AlignResult, reason: FailureReason | None, *, tz: float, roll: float, pitch: float
    ) -> AlignResult:
        """Algorithm 1 lines 15-17: T_2D = T_box @ T_bv, T_3D by Eq. 1; success, reason and confidence."""
        r.T_ego_peer = se3_from_se2(r.T_box @ r.T_bv, tz=tz, roll=roll, pitch=pitch)
        r.success = reason is None
        r.reason = None if reason is None else reason.value
        r.confidence = self.confidence(r, reason)
        r.timings_ms["align_total"] = sum(v for k, v in r.timings_ms.items() if k != "align_total")
        return r

    def confidence(self, r: AlignResult, reason: FailureReason | None) -> float:
        """Evidence -> [0, 1]. Grows with Inliers_bv and Inliers_box (the paper's Fig. 9), shrinks with the RANSAC
        ambiguity and a low refinement fitness; capped when failed."""
        s = self.rule
        c_bv = 1.0 - np.exp(-max(0, r.inliers_bv - s.min_inliers_bv) / BV_INLIER_SCALE)
        c_bv *= 1.0 - min(1.0, r.ambiguity_bv)
        if self.refine_enabled and r.refine_fitness > 0:
            c_bv *= float(np.clip((r.refine_fitness - s.min_refine_fitness) / FITNESS_SPAN, 0.0, 1.0))
        c_box = 1.0 - np.exp(-max(0, r.inliers_box - s.min_inliers_box) / BOX_INLIER_SCALE)
        out = 1.0 - (1.0 - c_bv) * (1.0 - c_box)
        if reason is not None:
            out = min(out, CAP_STAGE2_FAILED if reason in UNCONFIRMED_BY_BOXES else CAP_STAGE1_FAILED)
        return float(np.clip(out, 0.0, 1.0))
