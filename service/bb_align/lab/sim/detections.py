"""A 3-D object detector's errors, as a model: what a car reports as boxes given the true vehicles it sees.

Per agent: every true vehicle with at least ``min_points`` LiDAR points is detected unless missed; its box gets
centre, size and yaw noise growing with range, and sometimes a heading flipped by 180 degrees; a few false
positives appear on structure (points well above the ground). Scores rank true boxes above most false ones,
as a trained detector's do, so AP is meaningful.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bb_align.engine.geometry import wrap_angle


class DetectionModel(BaseModel):
    """Named parameters of the detector model (defaults: a decent LiDAR detector, e.g. PointPillars-class)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    min_points: int = Field(10, ge=1, description="K: a vehicle needs at least this many points to be detectable")
    max_range_m: float = Field(100.0, gt=0, description="no detections farther than this")
    miss_prob: float = Field(0.05, ge=0, le=1, description="probability of missing a detectable vehicle near by")
    miss_prob_far: float = Field(0.25, ge=0, le=1, description="miss probability at max_range_m (linear in range)")
    centre_sigma_m: float = Field(0.10, ge=0, description="centre noise (x, y), 1 sigma, near by")
    centre_sigma_far_m: float = Field(0.35, ge=0, description="centre noise at max_range_m")
    z_sigma_m: float = Field(0.1, ge=0, description="centre height noise")
    size_sigma_m: float = Field(0.12, ge=0, description="length/width/height noise, 1 sigma")
    yaw_sigma_deg: float = Field(2.0, ge=0, description="heading noise, 1 sigma")
    flip_prob: float = Field(0.05, ge=0, le=1, description="probability that the heading is off by 180 degrees")
    false_positives: float = Field(1.0, ge=0, description="mean number of false boxes per frame (Poisson)")


@dataclass
class Detections:
    boxes: np.ndarray  # (M, 7) [x, y, z, l, w, h, yaw] sensor frame
    scores: np.ndarray  # (M,) in (0, 1)
    truth: np.ndarray  # (M,) index of the true vehicle box it came from, -1 for a false positive


def detect(
    true_boxes: np.ndarray,
    n_points: np.ndarray,
    points: np.ndarray | None,
    rng: np.random.Generator,
    model: DetectionModel | None = None,
) -> Detections:
    """Simulated detections from (K, 7) true boxes in the sensor frame with their LiDAR point counts.

    ``points`` (N, 3+) in the sensor frame is used to put false positives on real structure (None: at random
    places within range).
    """
    m = model or DetectionModel()
    true_boxes = np.asarray(true_boxes, dtype=float).reshape(-1, 7)
    n_points = np.asarray(n_points).reshape(-1)
    if len(n_points) != len(true_boxes):
        raise ValueError(f"n_points has {len(n_points)} entries for {len(true_boxes)} true_boxes")
    dist = np.hypot(true_boxes[:, 0], true_boxes[:, 1])
    frac = np.clip(dist / m.max_range_m, 0, 1)
    p_miss = m.miss_prob + (m.miss_prob_far - m.miss_prob) * frac
    det = (n_points >= m.min_points) & (dist <= m.max_range_m) & (rng.random(len(true_boxes)) >= p_miss)
    idx = np.flatnonzero(det)
    out = true_boxes[idx].copy()
    sig = (m.centre_sigma_m + (m.centre_sigma_far_m - m.centre_sigma_m) * frac[idx])[:, None]
    out[:, :2] += rng.normal(0, 1, (len(idx), 2)) * sig
    out[:, 2] += rng.normal(0, m.z_sigma_m, len(idx))
    out[:, 3:6] = np.maximum(out[:, 3:6] + rng.normal(0, m.size_sigma_m, (len(idx), 3)), 0.3)
    flip = rng.random(len(idx)) < m.flip_prob
    out[:, 6] = wrap_angle(out[:, 6] + np.radians(rng.normal(0, m.yaw_sigma_deg, len(idx))) + np.pi * flip)
    scores = 0.55 + 0.4 * (1 - np.exp(-n_points[idx] / 60.0)) + rng.normal(0, 0.05, len(idx))

    n_fp = int(rng.poisson(m.false_positives))
    fp = np.zeros((n_fp, 7))
    if n_fp:
        anchors = None
        if points is not None and len(points):
            p = np.asarray(points)[:, :3]
            ground = np.percentile(p[:, 2], 5)
            tall = p[(p[:, 2] > ground + 0.5) & (np.hypot(p[:, 0], p[:, 1]) < m.max_range_m)]
            if len(tall):
                anchors = tall[rng.integers(0, len(tall), n_fp), :2]
                fp[:, 2] = ground + 0.8
        if anchors is None:
            r = rng.uniform(5, m.max_range_m, n_fp)
            a = rng.uniform(-np.pi, np.pi, n_fp)
            anchors = np.stack([r * np.cos(a), r * np.sin(a)], 1)
        fp[:, :2] = anchors + rng.normal(0, 0.5, (n_fp, 2))
        fp[:, 3:6] = np.stack(
            [rng.uniform(3.8, 5.0, n_fp), rng.uniform(1.6, 2.0, n_fp), rng.uniform(1.3, 1.8, n_fp)], 1
        )
        fp[:, 6] = rng.uniform(-np.pi, np.pi, n_fp)
    fp_scores = rng.uniform(0.2, 0.75, n_fp)
    boxes = np.concatenate([out, fp])
    return Detections(
        boxes,
        np.clip(np.concatenate([scores, fp_scores]), 0.01, 0.99),
        np.concatenate([idx, np.full(n_fp, -1)]).astype(np.int64),
    )


def count_points_in_boxes(points: np.ndarray, boxes: np.ndarray, margin_m: float = 0.2) -> np.ndarray:
    """LiDAR points inside each (K, 7) box (same frame), boxes grown by margin_m: (K,) int."""
    pts = np.asarray(points)[:, :3]
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
    out = np.zeros(len(boxes), dtype=np.int64)
    for i, (x, y, z, l, w, h, yaw) in enumerate(boxes):
        near = np.abs(pts[:, 0] - x) < (l + w) / 2 + margin_m
        near &= np.abs(pts[:, 1] - y) < (l + w) / 2 + margin_m
        if not near.any():
            continue
        q = pts[near] - (x, y, z)
        c, s = np.cos(yaw), np.sin(yaw)
        u, v = c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1]
        inside = (np.abs(u) <= l / 2 + margin_m) & (np.abs(v) <= w / 2 + margin_m)
        inside &= np.abs(q[:, 2]) <= h / 2 + margin_m
        out[i] = int(inside.sum())
    return out


# ---- detections simulated from a dataset's labels (explicit opt-in: `--simulate-detections`) ------------------


def vehicles_in_sensor(agent) -> tuple[dict[str, int], np.ndarray]:
    """An AgentFrame's labelled vehicles in its sensor frame: (id -> row, (K, 7) boxes)."""
    ids = list(agent.vehicles)
    if not ids:
        return {}, np.zeros((0, 7))
    world = np.stack([agent.vehicles[i] for i in ids])
    T_sw = np.linalg.inv(agent.T_world_sensor)
    out = world.copy()
    out[:, :3] = world[:, :3] @ T_sw[:3, :3].T + T_sw[:3, 3]
    out[:, 6] = world[:, 6] + np.arctan2(T_sw[1, 0], T_sw[0, 0])
    return dict(zip(ids, range(len(ids)))), out


def points_per_vehicle(agent, points: np.ndarray, gt_sensor: np.ndarray, ids: dict) -> dict[str, int]:
    """LiDAR points on each labelled vehicle (the simulator's count when the yaml has one)."""
    known = agent.extra.get("vehicle_points")
    if isinstance(known, dict):
        known = {str(k): int(v) for k, v in known.items()}
        return {i: known.get(i, 0) for i in ids}
    counts = count_points_in_boxes(points, gt_sensor)
    return {i: int(counts[j]) for i, j in ids.items()}


def frame_rng(seed: int, *keys: str) -> np.random.Generator:
    import zlib

    return np.random.default_rng([int(seed), *(zlib.crc32(k.encode()) for k in keys)])


class GroundTruthDetections:
    """Boxes simulated from an agent's ground-truth labels through the detector model (a stand-in for a real
    detector when a dataset has none; deterministic for the seed). A detection source for
    ``bb_align.io.recover`` and the evaluation."""

    def __init__(self, model: DetectionModel | None = None, seed: int = 0):
        self.model = model or DetectionModel()
        self.seed = int(seed)
        self.name = f"simulated from ground truth (detector model, seed {self.seed})"

    def detections(self, agent, points: np.ndarray) -> Detections:
        ids, gt = vehicles_in_sensor(agent)
        seen = points_per_vehicle(agent, points, gt, ids)
        counts = np.array([seen[i] for i in ids], dtype=np.int64)
        rng = frame_rng(self.seed, agent.scenario, agent.agent, agent.timestamp)
        return detect(gt, counts, points, rng, self.model)

    def __call__(self, agent, points: np.ndarray) -> np.ndarray:
        return self.detections(agent, points).boxes
