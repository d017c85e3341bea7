"""Rigid transforms in 2-D and 3-D: T_a_b maps points of frame b into frame a (p_a = T_a_b @ p_b)."""

from __future__ import annotations

import numpy as np
from numba import njit


def se2(yaw_rad: float, tx: float, ty: float) -> np.ndarray:
    """3x3 homogeneous 2-D rigid transform."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, tx], [s, c, ty], [0.0, 0.0, 1.0]])


def se2_params(T: np.ndarray) -> tuple[float, float, float]:
    """(yaw_rad, tx, ty) of a 3x3 (or the x-y part of a 4x4) rigid transform."""
    T = np.asarray(T, dtype=float)
    t_col = T.shape[1] - 1
    return float(np.arctan2(T[1, 0], T[0, 0])), float(T[0, t_col]), float(T[1, t_col])


def _arc(w: float) -> tuple[float, float]:
    """(sin w / w, (1 - cos w) / w): how a twist turning by ``w`` maps its velocity to the translation it makes."""
    if abs(w) < 1e-9:
        return 1.0 - w * w / 6.0, w / 2.0
    return np.sin(w) / w, (1.0 - np.cos(w)) / w


def se2_exp(xi) -> np.ndarray:
    """The rigid motion of a constant twist ``xi`` = (yaw, x, y) applied for unit time (an arc): 3x3."""
    w, vx, vy = (float(v) for v in xi)
    a, b = _arc(w)
    return se2(w, a * vx - b * vy, b * vx + a * vy)


def se2_log(T: np.ndarray) -> np.ndarray:
    """The twist (yaw, x, y) whose ``se2_exp`` is the 3x3 (or 4x4's ground) rigid motion T (|yaw| < pi)."""
    w, tx, ty = se2_params(T)
    a, b = _arc(w)
    det = a * a + b * b
    return np.array([w, (a * tx + b * ty) / det, (a * ty - b * tx) / det])


def ground_se2(T: np.ndarray) -> np.ndarray:
    """A 3x3 or 4x4 pose's ground-plane part as a 3x3 (yaw about z, x, y)."""
    return se2(*se2_params(T))


def distinct_pose(T: np.ndarray, others: list[np.ndarray], dist_m: float, deg: float) -> bool:
    """True when the 3x3 pose T is at least ``dist_m`` or ``deg`` away from every pose in ``others``."""
    if not others:
        return True
    return pose_is_distinct(np.array([se2_params(T2) for T2 in others]), se2_params(T), dist_m, deg)


def pose_is_distinct(params: np.ndarray, pose: tuple[float, float, float], dist_m: float, deg: float) -> bool:
    """True when ``pose`` (yaw_rad, tx, ty) is at least ``dist_m`` or ``deg`` away from every row of (N, 3) ``params``.
    Compiled: the acquisition asks this thousands of times per alignment (tested against numpy arithmetic)."""
    p = np.ascontiguousarray(params, dtype=np.float64).reshape(-1, 3)
    return not _any_near(p, float(pose[0]), float(pose[1]), float(pose[2]), float(dist_m), float(deg))


@njit(cache=True, nogil=True)
def _any_near(params, yaw, tx, ty, dist_m, deg):
    for n in range(len(params)):
        dyaw = abs((params[n, 0] - yaw + np.pi) % (2 * np.pi) - np.pi)
        if np.hypot(params[n, 1] - tx, params[n, 2] - ty) < dist_m and np.degrees(dyaw) < deg:
            return True
    return False


def transform_points_2d(T_a_b: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """Apply a 3x3 transform to (N, 2) points."""
    pts_b = np.asarray(pts_b, dtype=float)
    return pts_b @ T_a_b[:2, :2].T + T_a_b[:2, 2]


def transform_points_3d(T_a_b: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3+) points; extra columns are kept."""
    pts_b = np.asarray(pts_b)
    out = pts_b.copy()
    out[:, :3] = pts_b[:, :3] @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    return out


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) @ Ry(pitch) @ Rx(roll), radians (the paper's Eq. 2 with alpha=yaw, beta=pitch, gamma=roll)."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def se3_from_se2(T2: np.ndarray, *, tz: float = 0.0, roll: float = 0.0, pitch: float = 0.0) -> np.ndarray:
    """Eq. 1: the 4x4 transform from the estimated (yaw, tx, ty) and constant roll, pitch, tz."""
    yaw, tx, ty = se2_params(T2)
    T = np.eye(4)
    T[:3, :3] = rotation_rpy(roll, pitch, yaw)
    T[:3, 3] = (tx, ty, tz)
    return T


def wrap_angle(a):
    """Wrap radians to (-pi, pi]."""
    return -((-np.asarray(a) + np.pi) % (2 * np.pi) - np.pi)


def log_left(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """The left increment d = (yaw, tx, ty) with T_a = se2(d) @ T_b (yaw wrapped)."""
    yaw, tx, ty = se2_params(T_a @ np.linalg.inv(T_b))
    return np.array([float(wrap_angle(yaw)), tx, ty])


def kabsch_2d(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Closed-form least-squares rigid transform T (3x3) with dst ~ T @ src; (N, 2) each, N >= 2.

    theta = atan2(sum(x*y' - y*x'), sum(x*x' + y*y')) on centred points, t = mu' - R mu.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    a = src - mu_s
    b = dst - mu_d
    s_cross = np.sum(w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    s_dot = np.sum(w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    theta = np.arctan2(s_cross, s_dot)
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[c, -s], [s, c]])
    t = mu_d - R @ mu_s
    return se2(theta, t[0], t[1])


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error m, |yaw error| deg) between two 2-D/3-D transforms, on the ground plane."""
    y1, x1, y1t = se2_params(T_est)
    y2, x2, y2t = se2_params(T_true)
    return float(np.hypot(x1 - x2, y1t - y2t)), float(abs(np.degrees(wrap_angle(y1 - y2))))


def worst_sigma_m(cov: np.ndarray) -> float:
    """1-sigma of the translation along its worst direction: sqrt of the largest eigenvalue of the (tx, ty) block
    of a (yaw, tx, ty) covariance."""
    return float(np.sqrt(max(0.0, float(np.linalg.eigvalsh(np.asarray(cov)[1:, 1:]).max()))))
