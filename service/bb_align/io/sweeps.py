"""A dataset's sweeps as their car sends them: de-skewed with the sweep's own motion when the frame's yaml
carries it (``sweep_twist``: the simulator's distorted sweeps, or a recorder that kept the twist). Whether to is
``DESKEW_DEFAULT`` (bb_align.io.defaults) unless a command is told otherwise."""

from __future__ import annotations

import numpy as np

from bb_align.engine.deskew import deskew_sweep, firing_times

from .dataset import AgentFrame
from .defaults import DESKEW_DEFAULT, DESKEW_HELP

__all__ = ["DESKEW_DEFAULT", "DESKEW_HELP", "deskew_boxes", "deskewed", "sweep_twist"]


def sweep_twist(agent: AgentFrame) -> tuple[tuple[float, float], float, float] | None:
    """((vx, vy) m/s, yaw rate rad/s, period s) from the yaml's ``sweep_twist``, or None (a de-skewed cloud)."""
    tw = agent.extra.get("sweep_twist")
    if tw is None:
        return None
    try:
        return (float(tw["vx_mps"]), float(tw["vy_mps"])), float(tw["yaw_rate_rps"]), float(tw["period_s"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(
            f"{agent.scenario}/{agent.agent}/{agent.timestamp}: sweep_twist must map vx_mps, vy_mps, yaw_rate_rps and "
            f"period_s to numbers, got {tw!r}"
        ) from exc


def deskew_boxes(boxes: np.ndarray, velocity, yaw_rate: float, period_s: float) -> np.ndarray:
    """(K, 7) boxes drawn on a sweep that was not de-skewed, moved as ``deskew_sweep`` moves the points at their
    centres: the centre and a point 1 m ahead of it along the heading are de-skewed, the heading follows them."""
    boxes = np.array(boxes, dtype=np.float64, copy=True).reshape(-1, 7)
    if not len(boxes):
        return boxes
    ahead = boxes[:, :3].copy()
    ahead[:, 0] += np.cos(boxes[:, 6])
    ahead[:, 1] += np.sin(boxes[:, 6])
    # the nose takes the centre's firing time: both points are moved by one rigid motion
    times = firing_times(boxes[:, :3], period_s)
    centre = deskew_sweep(boxes[:, :3], velocity, yaw_rate, times_s=times, period_s=period_s)
    nose = deskew_sweep(ahead, velocity, yaw_rate, times_s=times, period_s=period_s)
    boxes[:, :2] = centre[:, :2]
    boxes[:, 6] = np.arctan2(nose[:, 1] - centre[:, 1], nose[:, 0] - centre[:, 0])
    return boxes


def deskewed(agent: AgentFrame, pts: np.ndarray, boxes: np.ndarray | None):
    """A sweep and the boxes detected on it, de-skewed with the sweep's motion (the yaml's ``sweep_twist``) as a
    sender with odometry does; unchanged when the yaml has none (a de-skewed cloud)."""
    twist = sweep_twist(agent)
    if twist is None:
        return pts, boxes
    pts = deskew_sweep(pts, *twist[:2], period_s=twist[2]).astype(pts.dtype)
    if boxes is not None and len(boxes):
        boxes = deskew_boxes(np.asarray(boxes, dtype=float), *twist[:2], twist[2])
    return pts, boxes
