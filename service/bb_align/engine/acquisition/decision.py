"""Step 4 of the acquisition: what the verified hypotheses say about the best one. Its margin over the runner-up
(the images' evidence), whether the boxes single it out or vouch for a rival, and which rivals count at all. The
verdict (``engine.verdict.Verdict.acquisition``) turns these facts into success or a failure reason."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import AcquireConfig
from .model import Hypothesis, distinct


def dense_score(h: Hypothesis, cfg: AcquireConfig) -> float:
    """The images' evidence for a hypothesis: its dense overlap (the relative fitness is judged apart, as the
    evidence margin x relative fitness)."""
    return h.fitness


def score(h: Hypothesis, cfg: AcquireConfig) -> float:
    """What ranks verified hypotheses: the dense score plus ``box_weight`` per peer box landing on an ego box."""
    return dense_score(h, cfg) + cfg.box_weight * h.box_pairs


def rivals(hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float = 1.0) -> list[Hypothesis]:
    """The hypotheses distinct from the first, in order (after refinement two may have met); those whose free-space
    conflict exceeds ``max_conflict`` are no rivals (a pose the two LiDARs' free space rules out)."""
    return [
        h for h in hyps[1:] if h.conflict <= max_conflict and distinct(h.T, [hyps[0]], cfg.distinct_m, cfg.distinct_deg)
    ]


def runner_up_of(hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float = 1.0) -> Hypothesis | None:
    """The best-scoring hypothesis distinct from the first (and within ``max_conflict``, see ``rivals``)."""
    return next(iter(rivals(hyps, cfg, max_conflict)), None)


def margin(hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float = 1.0) -> float:
    """The images' margin: the first hypothesis's dense score over the best dense score of any distinct one
    (floored at cfg.runner_up_floor; the floor alone without one). The boxes, which helped rank, are left out: they
    are judged on their own (``box_confirmed``), not counted twice. ``max_conflict``: see ``rivals``."""
    best_rival = max((dense_score(h, cfg) for h in rivals(hyps, cfg, max_conflict)), default=0.0)
    return float(dense_score(hyps[0], cfg) / max(best_rival, cfg.runner_up_floor))


def boxes_single_out(pairs: int, others: int, cfg: AcquireConfig) -> bool:
    """``pairs`` peer boxes on ego boxes under one pose single it out over ``others`` under any other: at least
    ``box_confirm_pairs``, and at least ``box_confirm_margin`` more and ``box_confirm_ratio`` times as many (a row of
    parked cars seen from its two ends pairs many boxes at a wrong pose too)."""
    if cfg.box_confirm_pairs == 0 or pairs < cfg.box_confirm_pairs:
        return False
    return pairs - others >= cfg.box_confirm_margin and pairs >= cfg.box_confirm_ratio * others


def box_confirmed(hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float = 1.0) -> bool:
    """The boxes single out the best pose (``hyps[0]``) among its rivals (``rivals``, ``max_conflict``)."""
    others = max((h.box_pairs for h in rivals(hyps, cfg, max_conflict)), default=0)
    return boxes_single_out(hyps[0].box_pairs, others, cfg)


def box_contradicted(
    hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float, reach: tuple[float, float]
) -> Hypothesis | None:
    """The rival (``rivals``) the boxes single out over the best pose, if any: the images and the boxes then vouch
    for two different poses, and neither is trusted. Only a rival beyond stage 2's ``reach`` (m, deg: a nearer one is
    stage 2's to judge, box against image) whose dense overlap reaches ``runner_up_floor`` counts: where the two
    images share nothing, boxes that pair say nothing about the scene."""
    seen = [
        h
        for h in rivals(hyps, cfg, max_conflict)
        if h.fitness >= cfg.runner_up_floor and distinct(h.T, [hyps[0]], *reach)
    ]
    rival = max(seen, key=lambda h: h.box_pairs, default=None)
    return rival if rival is not None and boxes_single_out(rival.box_pairs, hyps[0].box_pairs, cfg) else None


@dataclass
class Decision:
    """The facts the verdict judges the best hypothesis on (``Verdict.acquisition``)."""

    best: Hypothesis
    margin: float  # the images' margin over the runner-up (``margin``)
    dense_ok: bool  # the margin and margin x relative fitness reach acquire.min_margin and min_evidence
    weighed: bool  # searched inside a prior's window with the landscape on: the rivals are weighed, not the margin
    gave_way: bool  # better-scoring hypotheses were ruled out by the free space before this best
    box_confirmed: bool  # the boxes single the best out among its rivals
    contradicting: Hypothesis | None  # a rival beyond stage 2's reach the boxes single out instead


def decide(
    hyps: list[Hypothesis], cfg: AcquireConfig, bound: float, reach: tuple[float, float], weighed: bool, gave_way: bool
) -> Decision:
    """The facts about ``hyps[0]`` among the hypotheses whose conflict is within ``bound`` (``rivals``); ``reach``:
    stage 2's largest correction (m, deg)."""
    best = hyps[0]
    m = margin(hyps, cfg, bound)
    return Decision(
        best=best,
        margin=m,
        dense_ok=m >= cfg.min_margin and m * best.relative_fitness >= cfg.min_evidence,
        weighed=weighed,
        gave_way=gave_way,
        box_confirmed=box_confirmed(hyps, cfg, bound),
        contradicting=box_contradicted(hyps, cfg, bound, reach),
    )
