"""The typed outcome of one alignment."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .geometry import se2_params

if TYPE_CHECKING:
    from .acquisition import Acquisition


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
    ambiguity_bv: float = 1.0  # stage-1 RANSAC: a distinct runner-up's exclusive inliers / the winner's (1: no fit)
    confidence: float = 0.0
    reason: str | None = None  # a verdict.FailureReason value when success is False
    notes: list[str] = field(default_factory=list)  # non-fatal remarks, e.g. "stage 2 skipped: no boxes"
    stage2_applied: bool = False
    refine_fitness: float = 0.0  # fraction of peer BV pixels landing within the finest ICP gate of an ego pixel
    timings_ms: dict[str, float] = field(default_factory=dict)
    # 3x3 covariance of (yaw rad, tx m, ty m) of T_ego_peer's ground-plane part (None when not computed).
    covariance: np.ndarray | None = None
    # Tracking (bb_align.engine.follow): where the answer came from ("acquisition", "tracking", "stream" or
    # "prediction"), the peer's track state and, when it changed this frame, why.
    source: str = "acquisition"
    track_state: str | None = None
    track_event: str | None = None
    # Multi-hypothesis acquisition: margin over the runner-up, relative fitness, hypotheses (engine.acquisition).
    acquisition: Acquisition | None = field(default=None, repr=False)
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
            "ambiguity_bv": float(self.ambiguity_bv),
            "confidence": float(self.confidence),
            "stage2_applied": bool(self.stage2_applied),
            "refine_fitness": float(self.refine_fitness),
            "notes": list(self.notes),
            "timings_ms": {k: float(v) for k, v in self.timings_ms.items()},
            "source": self.source,
            "track_state": self.track_state,
            "track_event": self.track_event,
            "covariance": None if self.covariance is None else np.asarray(self.covariance, dtype=float).tolist(),
            "acquisition": None if self.acquisition is None else self.acquisition.to_dict(full=False),
        }
