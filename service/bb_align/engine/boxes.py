"""Stage 2: refine the stage-1 pose on the corners of boxes both cars detected (paper Section IV-B).

Boxes are rows ``[x, y, z, l, w, h, yaw]`` in the detecting car's sensor frame (centre, length along the
heading, width, height, yaw counter-clockwise about +z in radians). BV corners follow OpenCOOD's order:
front-right, front-left, rear-left, rear-right.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from .config import BoxConfig
from .geometry import se2_params, transform_points_2d, wrap_angle
from .ransac import RigidRansac

BOX_FIELDS = ("x", "y", "z", "l", "w", "h", "yaw")


def as_boxes(boxes) -> np.ndarray:
    """Anything array-like of shape (K, 7) in BOX_FIELDS order -> float64 (K, 7); None -> (0, 7)."""
    if boxes is None:
        return np.zeros((0, 7))
    arr = np.asarray(boxes, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 7))
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise ValueError(f"boxes must be (K, 7) rows of {list(BOX_FIELDS)}, got shape {arr.shape}")
    bad = np.argwhere(~np.isfinite(arr))
    if len(bad):
        i, j = (int(v) for v in bad[0])
        raise ValueError(f"boxes[{i}] {BOX_FIELDS[j]} is {arr[i, j]}: boxes must hold finite numbers only")
    return arr


def box_corners_bev(boxes: np.ndarray) -> np.ndarray:
    """(K, 7) boxes -> (K, 4, 2) BV corners: front-right, front-left, rear-left, rear-right."""
    boxes = as_boxes(boxes)
    hl, hw = boxes[:, 3] / 2, boxes[:, 4] / 2
    local = np.stack(
        [np.stack([hl, -hw], 1), np.stack([hl, hw], 1), np.stack([-hl, hw], 1), np.stack([-hl, -hw], 1)], axis=1
    )
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    x = c[:, None] * local[..., 0] - s[:, None] * local[..., 1] + boxes[:, 0:1]
    y = s[:, None] * local[..., 0] + c[:, None] * local[..., 1] + boxes[:, 1:2]
    return np.stack([x, y], axis=-1)


def transform_boxes(T_a_b: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Move (K, 7) boxes from frame b to frame a with a 3x3 ground-plane transform (z, sizes unchanged)."""
    boxes_b = as_boxes(boxes_b)
    out = boxes_b.copy()
    out[:, :2] = transform_points_2d(T_a_b, boxes_b[:, :2])
    out[:, 6] = wrap_angle(boxes_b[:, 6] + se2_params(T_a_b)[0])
    return out


def pair_boxes(centres_a: np.ndarray, centres_b: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one pairing of box centres (Hungarian on distance), pairs farther apart than ``gate`` dropped."""
    if len(centres_a) == 0 or len(centres_b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d = np.linalg.norm(centres_a[:, None, :] - centres_b[None, :, :], axis=2)
    cost = np.where(d < gate, d, 1e6)
    ia, ib = linear_sum_assignment(cost)
    keep = d[ia, ib] < gate
    return ia[keep], ib[keep]


def match_corners(corners_ego: np.ndarray, corners_peer: np.ndarray) -> np.ndarray:
    """For paired (P, 4, 2) corner sets, reorder each peer box's corners by the cyclic shift that brings them
    closest to the ego box's: robust to 180 deg (and 90 deg) heading flips of either detector."""
    shifts = np.stack([np.roll(corners_peer, -k, axis=1) for k in range(4)], axis=1)  # (P, 4, 4, 2)
    cost = np.linalg.norm(shifts - corners_ego[:, None], axis=3).sum(2)  # (P, 4)
    best = cost.argmin(axis=1)
    return shifts[np.arange(len(best)), best]


@dataclass
class BoxAlignment:
    T_box: np.ndarray  # 3x3 correction in the ego frame
    inliers: int  # corner inliers
    pairs: int  # box pairs found


class BoxStage:
    """Stage 2 (Algorithm 1 lines 12-14) as a pipeline step, built once from its config."""

    def __init__(self, cfg: BoxConfig, seed: int = 0):
        self.cfg, self.seed = cfg, seed

    def align(self, boxes_ego: np.ndarray, boxes_peer: np.ndarray, T_bv: np.ndarray) -> BoxAlignment:
        return align_boxes(boxes_ego, boxes_peer, T_bv, self.cfg, self.seed)


def _fit_pairs(boxes_ego, boxes_peer, T: np.ndarray, gate: float, cfg: BoxConfig, seed: int, min_pairs: int = 1):
    """Boxes paired under T (centres within ``gate``) and the rigid fit of their corners: (peer rows paired, the
    fit or None). The fit is not tried with fewer than ``min_pairs`` pairs."""
    peer_in_ego = transform_boxes(T, boxes_peer)
    ia, ib = pair_boxes(boxes_ego[:, :2], peer_in_ego[:, :2], gate)
    if len(ia) < max(min_pairs, 1):
        return ib, None
    c_ego = box_corners_bev(boxes_ego[ia])
    c_peer = match_corners(c_ego, box_corners_bev(peer_in_ego[ib]))
    return ib, RigidRansac(cfg.ransac, seed).fit(c_peer.reshape(-1, 2), c_ego.reshape(-1, 2))


def align_boxes(
    boxes_ego: np.ndarray, boxes_peer: np.ndarray, T_bv: np.ndarray, cfg: BoxConfig | None = None, seed: int = 0
) -> BoxAlignment:
    """Stage 2: T_box with ego corners ~ T_box @ (T_bv @ peer corners); pairs == 0 when nothing overlaps."""
    cfg = cfg or BoxConfig()
    ib, fit = _fit_pairs(as_boxes(boxes_ego), as_boxes(boxes_peer), T_bv, cfg.pair_gate_m, cfg, seed)
    if fit is None:
        return BoxAlignment(np.eye(3), 0, len(ib))
    return BoxAlignment(fit.T_dst_src, fit.num_inliers, len(ib))


def box_measurement(
    boxes_ego: np.ndarray,
    boxes_peer: np.ndarray,
    T_pred: np.ndarray,
    sigma_m: float,
    *,
    pair_gate_m: float = 2.0,
    min_pairs: int = 2,
    min_inliers: int = 6,
    cfg: BoxConfig | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray] | None:
    """T_ego_peer (3x3) from the boxes both cars detected, paired under a predicted T_pred, and its covariance of
    left increments (yaw, tx, ty); None with fewer than ``min_pairs`` pairs or ``min_inliers`` corner inliers.

    The pose is stage 2's corner fit. Its covariance treats each paired box centre as one 2-D measurement of
    ``sigma_m`` (the four corners of a box share its detection error, so they are not four measurements): with
    J_i = d(T p_i)/d(left increment) = [[-y_i, 1, 0], [x_i, 0, 1]] at the centre p_i in the ego frame,
    Cov = sigma_m^2 (sum J_i^T J_i)^-1. Two boxes far apart fix the yaw; one box fixes only the translation."""
    boxes_peer = as_boxes(boxes_peer)
    ib, fit = _fit_pairs(as_boxes(boxes_ego), boxes_peer, T_pred, pair_gate_m, cfg or BoxConfig(), seed, min_pairs)
    if fit is None or fit.num_inliers < min_inliers:
        return None
    T = fit.T_dst_src @ T_pred
    p = transform_points_2d(T, boxes_peer[ib, :2])
    J = np.zeros((2 * len(p), 3))
    J[0::2, 0], J[0::2, 1] = -p[:, 1], 1.0
    J[1::2, 0], J[1::2, 2] = p[:, 0], 1.0
    H = J.T @ J
    if np.linalg.cond(H) > 1e12:
        return None
    return T, sigma_m**2 * np.linalg.inv(H)
