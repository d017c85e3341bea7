"""The acquisition's records: a pose hypothesis, a prior's window, what two searches of one pair share, and the
typed outcome (``Acquisition``) the pipeline reads and the result serialises."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import distinct_pose, pose_is_distinct, se2, se2_params


@dataclass
class Hypothesis:
    T: np.ndarray  # 3x3 ego <- peer
    inliers: int  # distinct peer keypoints with a candidate within the inlier threshold
    votes: float = 0.0
    fitness: float = 0.0  # dense overlap (fraction of peer pixels within the finest gate)
    covisible: float = 0.0  # fraction of peer pixels within COVISIBLE_M of ego structure
    rmse_m: float = float("inf")
    refined: bool = False
    inlier_mask: np.ndarray | None = field(default=None, repr=False)
    source: str = "keypoints"  # what proposed it: "keypoints" (descriptor votes), "boxes" or "prior"
    box_pairs: int = 0  # peer boxes paired with an agreeing ego box under T (box_poses.box_agreement)
    box_score: float = 0.0  # the boxes' soft score under T (box_poses.box_agreement)
    conflict: float = 0.0  # free-space conflict under T, the larger of the two directions (engine.freespace)
    _params: tuple = field(default=(None, None), init=False, repr=False, compare=False)

    @property
    def params(self) -> tuple[float, float, float]:
        """se2_params(T), kept until T is replaced (T is assigned anew, never changed in place)."""
        of, params = self._params
        if of is not self.T:
            params = se2_params(self.T)
            self._params = (self.T, params)
        return params

    @property
    def relative_fitness(self) -> float:
        return self.fitness / self.covisible if self.covisible > 0 else 0.0

    @property
    def pose_deg(self) -> tuple[float, float, float]:
        """(yaw degrees, tx m, ty m): the pose as the diagnostics report it."""
        yaw, tx, ty = se2_params(self.T)
        return float(np.degrees(yaw)), float(tx), float(ty)

    def reported_T(self) -> np.ndarray:
        """The 3x3 pose rebuilt from ``pose_deg``: what a saved record of this hypothesis reproduces."""
        yaw_deg, tx, ty = self.pose_deg
        return se2(np.radians(yaw_deg), tx, ty)

    def to_dict(self) -> dict:
        yaw_deg, tx, ty = self.pose_deg
        return {
            "yaw_deg": yaw_deg,
            "tx": tx,
            "ty": ty,
            "inliers": self.inliers,
            "fitness": self.fitness,
            "covisible": self.covisible,
            "relative_fitness": self.relative_fitness,
            "refined": self.refined,
            "source": self.source,
            "box_pairs": self.box_pairs,
            "box_score": self.box_score,
            "conflict": self.conflict,
        }


def distinct(T: np.ndarray, chosen: list[Hypothesis], dist_m: float, deg: float) -> bool:
    """T is at least ``dist_m`` or ``deg`` from every hypothesis of ``chosen`` (True when there is none)."""
    return not chosen or pose_is_distinct(np.array([h.params for h in chosen]), se2_params(T), dist_m, deg)


@dataclass(frozen=True)
class PriorWindow:
    """Where a prior pose (e.g. from both cars' reported GNSS poses) says the true pose lies: within ``max_m`` of
    its translation and ``max_deg`` of its yaw (config.prior). Hypotheses outside it are not formed, not verified
    and are no rivals."""

    T: np.ndarray  # 3x3 ego <- peer
    max_m: float
    max_deg: float

    @property
    def params(self) -> tuple[float, float, float]:
        return se2_params(self.T)

    def holds(self, T: np.ndarray) -> bool:
        return not distinct_pose(T, [self.T], self.max_m, self.max_deg)

    def mask_accumulator(self, acc: np.ndarray, yaw_bin: float, t_bin: float, t_half: float) -> None:
        """Zero (in place) every (yaw, tx, ty) cell whose centre lies more than one cell beyond the window."""
        yaw0, tx0, ty0 = self.params
        yaw_c = (np.arange(acc.shape[0]) + 0.5) * yaw_bin - np.pi
        t_c = (np.arange(acc.shape[1]) + 0.5) * t_bin - t_half
        off_yaw = np.abs((yaw_c - yaw0 + np.pi) % (2 * np.pi) - np.pi) > np.radians(self.max_deg) + yaw_bin
        acc[off_yaw] = 0.0
        acc[:, np.abs(t_c - tx0) > self.max_m + t_bin] = 0.0
        acc[:, :, np.abs(t_c - ty0) > self.max_m + t_bin] = 0.0


@dataclass
class SearchMemo:
    """What one alignment's searches of the same two frames share: the first search fills it, a second (inside a
    prior's window, pipeline.Aligner._within_prior) reads it. Lives for one alignment: nothing here outlives it."""

    candidates: tuple[np.ndarray, np.ndarray] | None = None  # topk_candidates' (rows, cand)
    proposed: list[Hypothesis] | None = None  # the boxes' poses, before any window
    votes: dict[int, np.ndarray] = field(default_factory=dict)  # candidates per keypoint -> unmasked accumulator


@dataclass
class Acquisition:
    """What the multi-hypothesis acquisition found (``AlignResult.acquisition``): the verified hypotheses, best
    first, and the images' margin of the best over the runner-up."""

    best: Hypothesis | None
    runner_up: Hypothesis | None
    hypotheses: list[Hypothesis]
    candidates: int  # descriptor candidates (peer keypoints x top-k)
    margin: float  # best dense score / runner-up's (floored: acquire.runner_up_floor)
    gave_way: bool = False  # better-scoring hypotheses were ruled out by the free space before this best

    @property
    def evidence(self) -> float:
        """The images' evidence for the best: margin x its relative fitness (0 without a best)."""
        return self.margin * self.best.relative_fitness if self.best is not None else 0.0

    def rivals(self) -> list[np.ndarray]:
        """The other verified hypotheses' poses (3x3), as reported."""
        return [h.reported_T() for h in self.hypotheses[1:]]

    def to_dict(self, full: bool = True) -> dict:
        """Plain JSON-able dict; ``full=False``: the summary an alignment's result carries (no rivals)."""
        out = {
            "candidates": self.candidates,
            "hypotheses": len(self.hypotheses),
            "margin": self.margin,
            "best": None if self.best is None else self.best.to_dict(),
        }
        if full:
            out["runner_up"] = None if self.runner_up is None else self.runner_up.to_dict()
            out["all"] = [h.to_dict() for h in self.hypotheses]
            out["gave_way"] = self.gave_way
        return out
