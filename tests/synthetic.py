"""A small synthetic street for engine tests that must not depend on ../shared: walls, poles, parked cars and a
ground plane sampled as surface points (no ray casting; the simulator proper is bb_align.lab.sim)."""

from __future__ import annotations

import numpy as np

from bb_align.engine.geometry import transform_points_3d


def synthetic_world(seed: int = 0, extent: float = 70.0):
    """(points_world (N, 3), boxes_world (K, 7)) of a random street scene around the origin."""
    rng = np.random.default_rng(seed)
    parts = []
    # Buildings: axis-free rectangles, walls sampled every ~0.15 m, heights 4-15 m.
    for _ in range(28):
        cx, cy = rng.uniform(-extent, extent, 2)
        if abs(cy) < 8:  # keep a street free along x
            cy += np.sign(cy + 1e-9) * 10
        L, W, H, yaw = rng.uniform(6, 20), rng.uniform(5, 14), rng.uniform(4, 15), rng.uniform(-np.pi, np.pi)
        for (x0, y0), (x1, y1) in _rect_edges(cx, cy, L, W, yaw):
            n = int(np.hypot(x1 - x0, y1 - y0) / 0.15)
            t = rng.random(n * 6)
            parts.append(np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0), rng.uniform(0, H, len(t))], 1))
    # Poles and trees.
    for _ in range(60):
        x, y = rng.uniform(-extent, extent, 2)
        h = rng.uniform(3, 9)
        r = rng.uniform(0.1, 2.0)
        n = 300
        a = rng.uniform(0, 2 * np.pi, n)
        rr = r * np.sqrt(rng.random(n))
        parts.append(np.stack([x + rr * np.cos(a), y + rr * np.sin(a), rng.uniform(0.5, h, n)], 1))
    # Parked cars (boxes are the ground truth detections).
    boxes = []
    for _ in range(14):
        x = rng.uniform(-extent * 0.6, extent * 0.6)
        y = rng.choice([-1, 1]) * rng.uniform(3, 6)
        yaw = rng.normal(0, 0.1) + rng.choice([0, np.pi])
        L, W, H = rng.uniform(3.8, 5.0), rng.uniform(1.7, 2.0), rng.uniform(1.4, 1.8)
        boxes.append([x, y, H / 2, L, W, H, yaw])
        for (x0, y0), (x1, y1) in _rect_edges(x, y, L, W, yaw):
            t = rng.random(150)
            parts.append(np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0), rng.uniform(0.3, H, 150)], 1))
    # Ground.
    g = rng.uniform(-extent, extent, (60000, 2))
    parts.append(np.column_stack([g, rng.normal(0, 0.03, len(g))]))
    return np.concatenate(parts), np.array(boxes)


def _rect_edges(cx, cy, L, W, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[L / 2, -W / 2], [L / 2, W / 2], [-L / 2, W / 2], [-L / 2, -W / 2]])
    pts = local @ np.array([[c, s], [-s, c]]) + (cx, cy)
    return [(pts[i], pts[(i + 1) % 4]) for i in range(4)]


def view_from(
    points_world: np.ndarray,
    T_world_sensor: np.ndarray,
    *,
    max_range: float = 80.0,
    drop: float = 0.3,
    sensor_height: float = 1.8,
    seed: int = 0,
) -> np.ndarray:
    """The world seen from a sensor pose: points in the sensor frame (z up from the sensor), a random fraction
    dropped, cropped to max_range."""
    rng = np.random.default_rng(seed)
    pts = transform_points_3d(np.linalg.inv(T_world_sensor), points_world)
    pts[:, 2] -= sensor_height
    keep = (rng.random(len(pts)) >= drop) & (np.hypot(pts[:, 0], pts[:, 1]) < max_range)
    return pts[keep].astype(np.float32)
