"""Polylines with arc length: road centrelines, lanes and the trajectories cars drive along."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Path:
    """A densely sampled 2-D polyline (world frame) with cumulative arc length and unwrapped heading."""

    xy: np.ndarray  # (n, 2)
    s: np.ndarray  # (n,) arc length, metres, s[0] = 0
    heading: np.ndarray  # (n,) radians, unwrapped (CCW from +x)

    @classmethod
    def from_points(cls, xy: np.ndarray) -> Path:
        xy = np.asarray(xy, dtype=float)
        seg = np.diff(xy, axis=0)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
        h = np.arctan2(seg[:, 1], seg[:, 0])
        heading = np.unwrap(np.concatenate([h, h[-1:]]))
        return cls(xy, s, heading)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def pose_at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, yaw) at arc lengths s (clamped to the ends)."""
        s = np.asarray(s, dtype=float)
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        yaw = np.interp(s, self.s, self.heading)
        return x, y, yaw

    def offset(self, d: float) -> Path:
        """The parallel curve d metres to the left (negative: right)."""
        n = np.stack([-np.sin(self.heading), np.cos(self.heading)], axis=1)
        return Path.from_points(self.xy + d * n)

    def reversed(self) -> Path:
        return Path.from_points(self.xy[::-1].copy())

    def nearest_s(self, xy: np.ndarray) -> tuple[float, float]:
        """(arc length, distance) of the sample closest to the point xy."""
        d = np.hypot(self.xy[:, 0] - xy[0], self.xy[:, 1] - xy[1])
        i = int(np.argmin(d))
        return float(self.s[i]), float(d[i])


def build_centreline(
    rng: np.random.Generator, length_m: float, step_m: float = 0.5, start_xy=(0.0, 0.0), start_heading: float = 0.0
) -> Path:
    """A street of straight pieces and circular curves, integrated from a piecewise-constant curvature."""
    kappa_pieces: list[tuple[float, float]] = []  # (length, curvature)
    total = 0.0
    while total < length_m:
        if rng.random() < 0.55:
            piece = (float(rng.uniform(40, 160)), 0.0)
        else:
            radius = float(rng.uniform(35, 160))
            turn = np.radians(rng.uniform(20, 80)) * rng.choice([-1.0, 1.0])
            piece = (abs(turn) * radius, float(np.sign(turn) / radius))
        kappa_pieces.append(piece)
        total += piece[0]
    n = int(np.ceil(length_m / step_m)) + 1
    s = np.arange(n) * step_m
    bounds = np.cumsum([p[0] for p in kappa_pieces])
    kappa = np.array([p[1] for p in kappa_pieces])[np.searchsorted(bounds, s, side="right").clip(0, len(bounds) - 1)]
    heading = start_heading + np.concatenate([[0.0], np.cumsum(kappa[:-1] * step_m)])
    x = start_xy[0] + np.concatenate([[0.0], np.cumsum(np.cos(heading[:-1]) * step_m)])
    y = start_xy[1] + np.concatenate([[0.0], np.cumsum(np.sin(heading[:-1]) * step_m)])
    return Path.from_points(np.stack([x, y], axis=1))


def straight(start_xy, heading: float, length_m: float, step_m: float = 0.5) -> Path:
    s = np.arange(0.0, length_m + step_m / 2, step_m)
    xy = np.stack([start_xy[0] + s * np.cos(heading), start_xy[1] + s * np.sin(heading)], axis=1)
    return Path.from_points(xy)
