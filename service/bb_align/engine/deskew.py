"""Undo a sweep's self-motion distortion before it is encoded (sender side).

A rotating LiDAR fires its columns over a whole revolution (0.1 s at 10 Hz) while the car moves; a driver that does
not de-skew reports each point in the sensor frame of its own firing time. At 15 m/s the car travels 1.5 m in one
sweep: the wall behind it is torn by that much and, seen from another car, the image is sheared about the seam.
The two cars' shears differ (different speeds, headings and seams), and the pose between them is biased: on the
simulated turn family (`bb-align sim --family turn`, seed 7) one pair came out 1.0 deg off with a yaw 1-sigma of
0.32 deg, 0.035 deg off with the same scene rendered without distortion, and 0.039 deg off once the two sweeps are
de-skewed with this module (docs/engine.md, "Self-motion distortion").

Only the car that drove knows its motion, so the sender undoes it: every point is moved into the sensor frame at the
frame's stamp (mid-sweep) under a constant twist (``velocity`` in the sensor frame, ``yaw_rate``), the same model
as LiDAR odometry's deskewing. Each point's firing time comes from ``times_s`` (what most drivers report) or, without
it, from its azimuth: the sweep faces forward at mid-sweep and spins ``clockwise`` seen from above (Velodyne; the
simulator does the same), so a point at azimuth a fired ``-a / (2 pi)`` of a period from mid-sweep (``+a`` when
counter-clockwise), the seam behind the car.
"""

from __future__ import annotations

import numpy as np


def firing_times(points: np.ndarray, period_s: float = 0.1, clockwise: bool = True) -> np.ndarray:
    """(N,) seconds from mid-sweep at which each point of a sweep was fired, from its azimuth (module doc)."""
    pts = np.asarray(points, dtype=np.float64)
    az = np.arctan2(pts[:, 1], pts[:, 0])  # (-pi, pi]: 0 ahead (mid-sweep), +-pi behind (the seam)
    frac = az / (2.0 * np.pi)
    return (-frac if clockwise else frac) * float(period_s)


def deskew_sweep(
    points,
    velocity,
    yaw_rate: float = 0.0,
    *,
    times_s=None,
    period_s: float = 0.1,
    clockwise: bool = True,
) -> np.ndarray:
    """The sweep (N, 3+) moved into the sensor frame at mid-sweep. ``velocity``: (vx, vy) of the sensor in its own
    frame at mid-sweep, m/s (a car driving forward: (speed, 0)); ``yaw_rate``: rad/s, counter-clockwise positive;
    ``times_s``: each point's firing time relative to mid-sweep (None: from its azimuth, module doc). Columns beyond
    x, y (z, intensity, ...) are kept; z is unchanged (a ground-plane twist)."""
    pts = np.array(points, dtype=np.float64, copy=True)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, 3+), got shape {pts.shape}")
    v = np.asarray(velocity, dtype=np.float64).reshape(-1)
    if v.shape != (2,) or not np.all(np.isfinite(v)):
        raise ValueError(f"velocity must be two finite numbers (vx, vy) in m/s, got {velocity!r}")
    if not np.isfinite(yaw_rate):
        raise ValueError(f"yaw_rate must be finite (rad/s), got {yaw_rate!r}")
    if not (np.isfinite(period_s) and period_s > 0):
        raise ValueError(f"period_s must be a positive number of seconds, got {period_s!r}")
    if times_s is None:
        dt = firing_times(pts, period_s, clockwise)
    else:
        dt = np.asarray(times_s, dtype=np.float64).reshape(-1)
        if dt.shape != (len(pts),) or not np.all(np.isfinite(dt)):
            raise ValueError(f"times_s must hold one finite time per point ({len(pts)}), got shape {dt.shape}")
    # The sensor's pose at dt in the mid-sweep frame: the SE(2) exponential of the constant twist.
    theta = float(yaw_rate) * dt
    small = np.abs(theta) < 1e-9
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(theta) / safe)  # sin(theta) / theta
    b = np.where(small, theta / 2.0, (1.0 - np.cos(theta)) / safe)  # (1 - cos(theta)) / theta
    tx = (a * v[0] - b * v[1]) * dt
    ty = (b * v[0] + a * v[1]) * dt
    c, s = np.cos(theta), np.sin(theta)
    x, y = pts[:, 0].copy(), pts[:, 1].copy()
    pts[:, 0] = c * x - s * y + tx
    pts[:, 1] = s * x + c * y + ty
    return pts
