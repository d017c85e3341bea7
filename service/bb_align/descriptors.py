"""Rotation-invariant BVFT descriptors on the Maximum Index Map, vectorised over keypoints.

Per keypoint: the dominant MIM orientation m of a (1.44 J)-px neighbourhood (histogram of MIM values weighted
by a radial falloff times the max amplitude); MIM values shifted so m becomes 1 (rotating the scene shifts the
values); the J x J window sampled on a grid rotated by 15 deg * (m - 1) (nearest neighbour); an l x l grid of
value histograms, L2-normalised. Orientations live in [0, pi), so a scene rotated by 180 deg gives the same m
and a descriptor whose cells are in reverse order: :func:`flip_180` makes that copy for the matching side.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .config import FeatureConfig


@lru_cache(maxsize=4)
def _orientation_window(radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets (dr, dc) of a (2 radius)^2 window and its weights (1 - min(1, d/radius))^2."""
    off = np.arange(-radius, radius)
    dr, dc = np.meshgrid(off, off, indexing="ij")
    d = np.hypot(dr, dc)
    w = (1.0 - np.minimum(1.0, d / radius)) ** 2
    return dr.ravel(), dc.ravel(), w.ravel().astype(np.float32)


@lru_cache(maxsize=4)
def _descriptor_grid(patch: int, grid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets of a patch x patch window symmetric about the keypoint, and each sample's cell index."""
    q = np.arange(patch) - (patch - 1) / 2.0
    dr, dc = np.meshgrid(q, q, indexing="ij")
    cell_px = patch // grid
    ci = np.minimum(np.arange(patch) // cell_px, grid - 1)
    cell = (ci[:, None] * grid + ci[None, :]).ravel()
    return dr.ravel(), dc.ravel(), cell


def dominant_orientation(mim: np.ndarray, amp: np.ndarray, rc: np.ndarray, radius: int, n_orient: int) -> np.ndarray:
    """(K,) dominant orientation m in 1..No per keypoint (0 when the window holds no MIM value)."""
    k = len(rc)
    dr, dc, w = _orientation_window(radius)
    mim_p = np.pad(mim, radius)
    amp_p = np.pad(amp, radius)
    rows = rc[:, 0:1] + radius + dr[None, :]
    cols = rc[:, 1:2] + radius + dc[None, :]
    vals = mim_p[rows, cols].astype(np.int64)
    weights = amp_p[rows, cols] * w[None, :]
    idx = np.arange(k)[:, None] * (n_orient + 1) + vals
    hist = np.bincount(idx.ravel(), weights=weights.ravel(), minlength=k * (n_orient + 1))
    hist = hist.reshape(k, n_orient + 1)[:, 1:]
    m0 = hist.argmax(axis=1)  # 0-based
    lower = hist[np.arange(k), (m0 - 1) % n_orient]
    upper = hist[np.arange(k), (m0 + 1) % n_orient]
    m0 = np.where(lower > upper, (m0 - 1) % n_orient, m0)
    m = m0 + 1
    m[hist.max(axis=1) <= 0] = 0
    return m


def bvft_descriptors(mim: np.ndarray, amp: np.ndarray, rc: np.ndarray, cfg: FeatureConfig | None = None,
                     n_orient: int = 12) -> np.ndarray:
    """MIM (uint8, 0..No), max amplitude, (K, 2) keypoints (row, col) -> (K, D) float32 descriptors, unit norm
    (all-zero for an empty patch). D = l*l*No/2 when cfg.merge_bins (216 by default), else l*l*No."""
    cfg = cfg or FeatureConfig()
    rc = np.asarray(rc, dtype=np.int64).reshape(-1, 2)
    k = len(rc)
    n_bins = n_orient // 2 if cfg.merge_bins else n_orient
    n_cells = cfg.grid * cfg.grid
    if k == 0:
        return np.zeros((0, n_cells * n_bins), dtype=np.float32)

    radius = int(np.ceil(cfg.patch_px * np.sqrt(2) / 2))  # 69 px for J = 96
    m = dominant_orientation(mim, amp, rc, radius, n_orient)

    # Sample the J x J window on a grid rotated by 15 deg * (m - 1) (display counter-clockwise), nearest px.
    dr, dc, cell = _descriptor_grid(cfg.patch_px, cfg.grid)
    ang = (np.maximum(m, 1) - 1) * (np.pi / n_orient)
    cos, sin = np.cos(ang)[:, None], np.sin(ang)[:, None]
    src_r = rc[:, 0:1] + dr[None, :] * cos - dc[None, :] * sin
    src_c = rc[:, 1:2] + dc[None, :] * cos + dr[None, :] * sin
    mim_p = np.pad(mim, radius)
    rows = np.clip(np.floor(src_r + 0.5).astype(np.int64) + radius, 0, mim_p.shape[0] - 1)
    cols = np.clip(np.floor(src_c + 0.5).astype(np.int64) + radius, 0, mim_p.shape[1] - 1)
    v = mim_p[rows, cols].astype(np.int64)

    # Shift values so the dominant orientation becomes 1: v' = ((v - m) mod No) + 1, 0 stays 0.
    v_shift = np.where(v > 0, (v - m[:, None]) % n_orient + 1, 0)
    lit = v_shift > 0
    b = (v_shift - 1) // 2 if cfg.merge_bins else v_shift - 1
    idx = (np.arange(k)[:, None] * n_cells + cell[None, :]) * n_bins + b
    desc = np.bincount(idx[lit], minlength=k * n_cells * n_bins).astype(np.float32).reshape(k, -1)
    norm = np.linalg.norm(desc, axis=1, keepdims=True)
    return desc / np.maximum(norm, 1e-12)


def flip_180(desc: np.ndarray, cfg: FeatureConfig | None = None) -> np.ndarray:
    """The descriptor of the same patch rotated by 180 deg: the cells in reverse order, bins unchanged."""
    cfg = cfg or FeatureConfig()
    k, d = desc.shape
    n_cells = cfg.grid * cfg.grid
    return desc.reshape(k, n_cells, d // n_cells)[:, ::-1, :].reshape(k, d).copy()
