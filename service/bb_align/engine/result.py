"""The typed outcome of one alignment."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from .geometry import se2_params


class FailureReason(str, Enum):
    """Why an alignment did not succeed (``AlignResult.reason``)."""

    too_few_points = "too_few_points"  # a cloud had fewer than config.min_points points
    empty_image = "empty_image"  # a BV image has no lit pixels
    no_keypoints = "no_keypoints"  # FAST found (almost) nothing to describe
    too_few_matches = "too_few_matches"  # fewer descriptor matches than a rigid fit needs
    too_few_inliers_bv = "too_few_inliers_bv"  # stage 1 below the success rule
    ambiguous_bv = "ambiguous_bv"  # a distinct pose explains almost as many matches
    inconsistent_overlap = "inconsistent_overlap"  # after refinement too few BV pixels coincide (alias)
    no_boxes = "no_boxes"  # boxes were required but one side sent none
    no_box_overlap = "no_box_overlap"  # no peer box lands on an ego box after stage 1
    too_few_inliers_box = "too_few_inliers_box"  # stage 2 below the success rule
    box_correction_too_large = "box_correction_too_large"  # stage 2 disagrees with stage 1 by too much
    # Service-level reasons (set by the service, never by the engine):
    no_ego_frame = "no_ego_frame"
    stale_ego_frame = "stale_ego_frame"


@dataclass
class AlignResult:
    """T_ego_peer and its evidence. ``success`` is the paper's rule (configurable); when False, ``reason`` says
    why, and the best transform found so far is still reported (stage 1's when only stage 2 failed)."""

    success: bool
    T_ego_peer: np.ndarray  # 4x4, Eq. 1 (roll, pitch, tz constants)
    T_bv: np.ndarray  # 3x3, stage 1 (peer -> ego on the ground plane)
    T_box: np.ndarray  # 3x3, stage 2 correction (identity when skipped)
    inliers_bv: int = 0
    inliers_box: int = 0
    matches_bv: int = 0
    box_pairs: int = 0
    confidence: float = 0.0
    reason: str | None = None  # a FailureReason value when success is False
    notes: list[str] = field(default_factory=list)  # non-fatal remarks, e.g. "stage 2 skipped: no boxes"
    stage2_applied: bool = False
    refine_fitness: float = 0.0  # fraction of peer BV pixels landing within the finest ICP gate of an ego pixel
    timings_ms: dict[str, float] = field(default_factory=dict)
    # Stage-1 inlier correspondences (metres, each car's sensor frame), for plots and diagnostics.
    inlier_xy_peer: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)
    inlier_xy_ego: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)

    @property
    def yaw_deg(self) -> float:
        return float(np.degrees(se2_params(self.T_ego_peer)[0]))

    @property
    def tx(self) -> float:
        return float(self.T_ego_peer[0, 3])

    @property
    def ty(self) -> float:
        return float(self.T_ego_peer[1, 3])

    def to_dict(self) -> dict:
        """Plain JSON-able dict (the CLI's --json output and the service's result body)."""
        return {
            "success": bool(self.success),
            "reason": self.reason,
            "yaw_deg": self.yaw_deg,
            "tx": self.tx,
            "ty": self.ty,
            "T_ego_peer": np.asarray(self.T_ego_peer, dtype=float).tolist(),
            "T_bv": np.asarray(self.T_bv, dtype=float).tolist(),
            "T_box": np.asarray(self.T_box, dtype=float).tolist(),
            "inliers_bv": int(self.inliers_bv),
            "inliers_box": int(self.inliers_box),
            "matches_bv": int(self.matches_bv),
            "box_pairs": int(self.box_pairs),
            "confidence": float(self.confidence),
            "stage2_applied": bool(self.stage2_applied),
            "refine_fitness": float(self.refine_fitness),
            "notes": list(self.notes),
            "timings_ms": {k: float(v) for k, v in self.timings_ms.items()},
        }
