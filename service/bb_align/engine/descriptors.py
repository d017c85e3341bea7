"""Rotation-invariant BVFT descriptors on the Maximum Index Map, vectorised over keypoints.

Per keypoint: the dominant MIM orientation m of a disc of radius J/sqrt(2) (histogram of MIM values weighted by
(1 - d/radius)^2 times the max amplitude); MIM values shifted so m becomes 1 (rotating the scene shifts the
values); the J x J window sampled on a grid rotated by 15 deg * (m - 1) (nearest neighbour); an l x l grid of
value histograms, L2-normalised. Orientations live in [0, pi), so a scene rotated by 180 deg gives the same m
and a descriptor whose cells are in reverse order: :func:`flip_180` makes that copy for the matching side.

The two histogram passes (orientation disc, rotated window) are small compiled loops (numba, no GIL: the
engine's threads describe keypoint groups in parallel); the 12 possible rotated sampling grids are cached, and
the value shift, the bin merge and the normalisation run on the small (K, cells, values) histograms.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from .config import FeatureConfig


@lru_cache(maxsize=4)
def _orientation_window(radius: int, width: int, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Flat offsets (in an image ``width`` px wide) of the disc of ``radius`` px, every ``stride``-th pixel
    each way (symmetric about the centre), and the weights (1 - d/radius)^2."""
    off = np.arange(-(radius // stride) * stride, radius + 1, stride)
    dr, dc = np.meshgrid(off, off, indexing="ij")
    d = np.hypot(dr, dc)
    inside = d < radius
    return (dr[inside] * width + dc[inside]).astype(np.int64), (1.0 - d[inside] / radius) ** 2


@lru_cache(maxsize=4)
def _rotated_grids(patch: int, grid: int, n_orient: int, width: int, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(No, S) flat offsets of the J x J window (every ``stride``-th sample each way, S = (J/stride)^2) rotated by
    180/No deg * (m - 1) counter-clockwise on screen (symmetric about the keypoint, nearest pixel), and the (S,)
    cell index of each sample."""
    idx = np.arange(stride // 2, patch, stride)
    q = idx - (patch - 1) / 2.0
    dr, dc = (a.ravel() for a in np.meshgrid(q, q, indexing="ij"))
    offsets = np.empty((n_orient, len(idx) ** 2), dtype=np.int64)
    for m0 in range(n_orient):
        a = m0 * np.pi / n_orient
        # Exact cos/sin at quarter turns (cos(pi/2) = 6e-17 would break the half-pixel ties unevenly).
        c, sn = np.round(np.cos(a), 12), np.round(np.sin(a), 12)
        rr = np.floor(dr * c - dc * sn + 0.5).astype(np.int64)
        cc = np.floor(dc * c + dr * sn + 0.5).astype(np.int64)
        offsets[m0] = rr * width + cc
    cell_px = patch // grid
    ci = np.minimum(idx // cell_px, grid - 1)
    cell = (ci[:, None] * grid + ci[None, :]).ravel().astype(np.int64)
    return offsets, cell


def dominant_orientation(
    mim: np.ndarray, amp: np.ndarray, rc: np.ndarray, radius: int, n_orient: int, stride: int = 1
) -> np.ndarray:
    """(K,) dominant orientation m in 1..No per keypoint (0 when the disc holds no MIM value).

    If the lower cyclic neighbour of the peak bin beats the upper one, the lower bin is taken (the reference's
    rule: the peak's lower edge is the canonical direction).
    """
    width = mim.shape[1] + 2 * radius
    offsets, w = _orientation_window(radius, width, stride)
    mim_p = np.pad(mim, radius).ravel()
    amp_p = np.pad(amp.astype(np.float64), radius).ravel()
    base = (rc[:, 0] + radius) * width + rc[:, 1] + radius
    hist = _weighted_histograms(mim_p, amp_p, base, offsets, w, n_orient + 1)
    hist = hist[:, 1:]
    m0 = hist.argmax(axis=1)  # 0-based
    rows = np.arange(len(rc))
    lower = hist[rows, (m0 - 1) % n_orient]
    upper = hist[rows, (m0 + 1) % n_orient]
    m0 = np.where(lower > upper, (m0 - 1) % n_orient, m0)
    return np.where(hist.max(axis=1) > 0, m0 + 1, 0)


def descriptor_radius(cfg: FeatureConfig) -> int:
    """Radius of the dominant-orientation disc, J / sqrt(2) rounded up (68 px for J = 96): it also holds the
    J x J window at any rotation."""
    return int(np.ceil(cfg.patch_px * np.sqrt(2) / 2))


def keypoint_orientations(
    mim: np.ndarray, amp: np.ndarray, rc: np.ndarray, cfg: FeatureConfig | None = None, n_orient: int = 12
) -> np.ndarray:
    """(K,) dominant orientation m in 1..No of each keypoint (0: empty disc), as the descriptors use it."""
    cfg = cfg or FeatureConfig()
    rc = np.asarray(rc, dtype=np.int64).reshape(-1, 2)
    return dominant_orientation(mim, amp, rc, descriptor_radius(cfg), n_orient, cfg.orientation_stride)


def bvft_descriptors(
    mim: np.ndarray,
    amp: np.ndarray,
    rc: np.ndarray,
    cfg: FeatureConfig | None = None,
    n_orient: int = 12,
    orientation_offset: int = 0,
    orientations: np.ndarray | None = None,
) -> np.ndarray:
    """MIM (uint8, 0..No), max amplitude, (K, 2) keypoints (row, col) -> (K, D) float32 descriptors, unit norm
    (all-zero for an empty patch). D = l*l*No/2 when cfg.merge_bins (216 by default), else l*l*No.
    ``orientations``: the keypoints' dominant orientations when already known (:func:`keypoint_orientations`)."""
    cfg = cfg or FeatureConfig()
    rc = np.asarray(rc, dtype=np.int64).reshape(-1, 2)
    k = len(rc)
    n_bins = n_orient // 2 if cfg.merge_bins else n_orient
    n_cells = cfg.grid * cfg.grid
    if k == 0:
        return np.zeros((0, n_cells * n_bins), dtype=np.float32)

    radius = descriptor_radius(cfg)
    m = keypoint_orientations(mim, amp, rc, cfg, n_orient) if orientations is None else np.asarray(orientations)
    if orientation_offset:  # describe as if the dominant orientation were a neighbouring bin
        m = np.where(m > 0, (m - 1 + orientation_offset) % n_orient + 1, 0)

    width = mim.shape[1] + 2 * radius
    offsets, cell = _rotated_grids(cfg.patch_px, cfg.grid, n_orient, width, cfg.window_stride)
    mim_p = np.pad(mim, radius).ravel()
    base = (rc[:, 0] + radius) * width + rc[:, 1] + radius
    # Raw counts of MIM values (0..No) per keypoint and cell, each window on the grid rotated by its m.
    shift = np.maximum(m, 1) - 1
    counts = _cell_histograms(mim_p, base, offsets, shift, cell, n_cells, n_orient + 1)
    desc = _shifted_bins(counts, shift, n_orient, cfg.merge_bins)
    norm = np.linalg.norm(desc, axis=1, keepdims=True)
    return desc / np.maximum(norm, 1e-12)


@njit(cache=True, nogil=True)
def _weighted_histograms(values, weights_image, base, offsets, weights, n_slots):
    """(K, n_slots) float64: per keypoint k, sum of weights_image[p] * weights[j] into slot values[p], over the
    samples p = base[k] + offsets[j] (in order, as a sequential bincount would add them)."""
    out = np.zeros((len(base), n_slots))
    for k in range(len(base)):
        for j in range(len(offsets)):
            p = base[k] + offsets[j]
            out[k, values[p]] += weights_image[p] * weights[j]
    return out


@njit(cache=True, nogil=True)
def _cell_histograms(values, base, offsets, grid_index, cell, n_cells, n_slots):
    """(K, n_cells, n_slots) int32 counts of values[base[k] + offsets[grid_index[k], j]] per cell[j] (an integer
    increment does not wait on a float add: twice as fast as counting in float32)."""
    counts = np.zeros((len(base), n_cells, n_slots), dtype=np.int32)
    for k in range(len(base)):
        row = offsets[grid_index[k]]
        b = base[k]
        for j in range(len(cell)):
            counts[k, cell[j], values[b + row[j]]] += 1
    return counts


@njit(cache=True, nogil=True)
def _shifted_bins(counts, shift, n_orient, merge):
    """(K, n_cells * n_bins) float32 descriptors (not normalised) from (K, n_cells, No + 1) counts: the value
    shift v' = ((v - m) mod No) + 1 only permutes the bins 1..No (``shift[k]`` = m - 1), so it is applied to the
    small histograms; with ``merge`` the bins are summed in pairs (No / 2 bins). Every count and pair sum is exact
    in float32: the same floats as the permutation and sum in numpy, 6x faster."""
    k, n_cells = counts.shape[0], counts.shape[1]
    n_bins = n_orient // 2 if merge else n_orient
    out = np.empty((k, n_cells * n_bins), dtype=np.float32)
    for q in range(k):
        s = shift[q]
        for c in range(n_cells):
            src = counts[q, c]
            for j in range(n_bins):
                if merge:
                    v = src[(2 * j + s) % n_orient + 1] + src[(2 * j + 1 + s) % n_orient + 1]
                else:
                    v = src[(j + s) % n_orient + 1]
                out[q, c * n_bins + j] = np.float32(v)
    return out


def flip_180(desc: np.ndarray, cfg: FeatureConfig | None = None) -> np.ndarray:
    """The descriptor of the same patch rotated by 180 deg: the cells in reverse order, bins unchanged."""
    cfg = cfg or FeatureConfig()
    k, d = desc.shape
    n_cells = cfg.grid * cfg.grid
    return desc.reshape(k, n_cells, d // n_cells)[:, ::-1, :].reshape(k, d).copy()
