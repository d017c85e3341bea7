"""Rigid 2-D RANSAC (rotation + translation, no scale): seeded, adaptive, vectorised; Kabsch refit.

Besides the best transform it reports the *ambiguity*: the largest number of matches that some distinct
hypothesis explains and the winner does not, over the winner's inlier count. A repetitive scene (a straight
corridor of identical facades) or a half-turn look-alike scores high; a clean unique fit scores near 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import RansacConfig
from .geometry import kabsch_2d, se2

REFITS = 3  # Kabsch refits on the inliers after the best hypothesis (stops when the inliers no longer grow)
AMBIGUITY_HYPOTHESES = 1024  # best-scoring hypotheses searched for a distinct runner-up (RansacResult.ambiguity)


@dataclass
class RansacResult:
    T_dst_src: np.ndarray  # 3x3
    inliers: np.ndarray  # (M,) bool
    iterations: int
    ambiguity: float  # exclusive inliers of the best distinct runner-up / inliers of the winner

    @property
    def num_inliers(self) -> int:
        return int(self.inliers.sum())


def _hypotheses(src, dst, i, j):
    """Rigid transforms (theta, tx, ty) from sample pairs (i, j): rotation of the pair's vector, centroid fit."""
    s = src[j] - src[i]
    d = dst[j] - dst[i]
    theta = np.arctan2(s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0], s[:, 0] * d[:, 0] + s[:, 1] * d[:, 1])
    c, sn = np.cos(theta), np.sin(theta)
    ms = (src[i] + src[j]) / 2
    md = (dst[i] + dst[j]) / 2
    tx = md[:, 0] - (c * ms[:, 0] - sn * ms[:, 1])
    ty = md[:, 1] - (sn * ms[:, 0] + c * ms[:, 1])
    return theta, tx, ty


def _inlier_masks(src, dst, theta, tx, ty, thr2):
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    px = c * src[None, :, 0] - s * src[None, :, 1] + tx[:, None]
    py = s * src[None, :, 0] + c * src[None, :, 1] + ty[:, None]
    return (px - dst[None, :, 0]) ** 2 + (py - dst[None, :, 1]) ** 2 < thr2


def _inliers_of(T, src, dst, thr2):
    p = src @ T[:2, :2].T + T[:2, 2]
    return ((p - dst) ** 2).sum(1) < thr2


class RigidRansac:
    """Algorithm 1 line 11 (and 14): the step object, built once from its config; ``fit(src, dst)``."""

    def __init__(self, cfg: RansacConfig, seed: int = 0):
        self.cfg, self.seed = cfg, seed

    def fit(self, src: np.ndarray, dst: np.ndarray) -> RansacResult | None:
        return rigid_ransac(src, dst, self.cfg, self.seed)


def rigid_ransac(src: np.ndarray, dst: np.ndarray, cfg: RansacConfig, seed: int = 0) -> RansacResult | None:
    """Fit dst ~ T @ src on (M, 2) correspondences. Returns None when M < 2 or no valid sample exists."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    m = len(src)
    if m < 2:
        return None
    rng = np.random.default_rng(seed)
    threshold, batch = cfg.inlier_threshold_m, cfg.batch
    max_iterations, min_iterations, confidence = cfg.max_iterations, cfg.min_iterations, cfg.confidence
    thr2 = threshold * threshold
    min_d2 = cfg.min_sample_dist_m * cfg.min_sample_dist_m
    best_count, best_params = -1, None
    kept = []  # (count, theta, tx, ty) of each scored batch, for the ambiguity check
    it, needed = 0, max_iterations
    while it < min(max(min_iterations, needed), max_iterations):
        i = rng.integers(0, m, batch)
        j = rng.integers(0, m, batch)
        ds = ((src[j] - src[i]) ** 2).sum(1)
        dd = ((dst[j] - dst[i]) ** 2).sum(1)
        # A rigid motion keeps lengths: drop degenerate and length-inconsistent samples before scoring.
        ok = (i != j) & (ds >= min_d2) & (np.abs(np.sqrt(ds) - np.sqrt(dd)) < 2 * threshold)
        it += batch
        if not ok.any():
            continue
        theta, tx, ty = _hypotheses(src, dst, i[ok], j[ok])
        counts = _inlier_masks(src, dst, theta, tx, ty, thr2).sum(1)
        kept.append(np.stack([counts, theta, tx, ty], axis=1))
        b = int(counts.argmax())
        if counts[b] > best_count:
            best_count, best_params = int(counts[b]), (theta[b], tx[b], ty[b])
            w = best_count / m
            p_good = w * w
            needed = (
                max_iterations
                if p_good <= 0
                else (0 if p_good >= 1 else int(np.ceil(np.log(1 - confidence) / np.log(1 - p_good))))
            )
    if best_params is None:
        return None

    T = se2(*best_params)
    inliers = _inliers_of(T, src, dst, thr2)
    for _ in range(REFITS):
        if inliers.sum() < 2:
            break
        T_new = kabsch_2d(src[inliers], dst[inliers])
        new_inliers = _inliers_of(T_new, src, dst, thr2)
        if new_inliers.sum() < inliers.sum():
            break
        T, inliers = T_new, new_inliers

    ambiguity = _ambiguity(np.concatenate(kept), src, dst, inliers, thr2, AMBIGUITY_HYPOTHESES)
    return RansacResult(T_dst_src=T, inliers=inliers, iterations=it, ambiguity=ambiguity)


def _ambiguity(hyps: np.ndarray, src, dst, inliers: np.ndarray, thr2: float, top: int) -> float:
    n_best = int(inliers.sum())
    if n_best == 0 or len(hyps) == 0:
        return 0.0
    order = np.argsort(-hyps[:, 0], kind="stable")[:top]
    h = hyps[order]
    masks = _inlier_masks(src, dst, h[:, 1], h[:, 2], h[:, 3], thr2)
    exclusive = (masks & ~inliers[None, :]).sum(1)
    return float(exclusive.max() / n_best)
