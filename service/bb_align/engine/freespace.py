"""Free space: where a car's LiDAR saw through, and the other car's structure that lands there under a pose.

A BV image keeps what stands above the ground; the ground stays dark. Along each azimuth from the sensor (the
image centre) the nearest lit pixel is where the beams stopped: the pixels nearer than it were seen through. Under
the right pose the other car's tall structure does not land there (apart from what moved); under an alias (the
same street a block further along, a half turn) it does: a wall where this car saw an empty road. That is evidence
against a pose from neither the descriptors nor the boxes, so it can check poses the two of them agree on.

Plain functions on images and point arrays; the pipeline caches each frame's map (``PreparedFrame.cached``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from .bev import BevImage
from .config import FreeSpaceConfig
from .refine import covisible_share


@lru_cache(maxsize=4)
def _polar(h: int, w: int, range_m: float, res: float, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel centre's azimuth bin and range from the sensor, for one image geometry (shared by all frames)."""
    x = range_m - (np.arange(h) + 0.5) * res
    y = range_m - (np.arange(w) + 0.5) * res
    X, Y = np.meshgrid(x, y, indexing="ij")
    bins = ((np.arctan2(Y, X) + np.pi) / (2 * np.pi) * n_bins).astype(np.int32) % n_bins
    return bins, np.hypot(X, Y).astype(np.float32)


@njit(cache=True, nogil=True)
def _free_map(image, min_value, bins, dist, near, n_bins, min_range_m, margin_m, open_m, spread):
    """uint8 mask: 1 where a pixel lies nearer than the first hit of its azimuth bin (and of ``spread`` bins either
    side) by ``margin_m``, beyond ``min_range_m``, off the ``near`` mask; bins with no hit are free up to
    ``open_m``."""
    h, w = image.shape
    hits = np.full(n_bins, np.inf)
    for r in range(h):
        for c in range(w):
            if image[r, c] >= min_value and dist[r, c] >= min_range_m and dist[r, c] < hits[bins[r, c]]:
                hits[bins[r, c]] = dist[r, c]
    # Each bin's limit once (the same floats as per pixel): free up to the nearest hit of the bin and its
    # neighbours minus the margin, or up to open_m when none of them has a hit.
    limit = np.empty(n_bins)
    for b in range(n_bins):
        stop = np.inf
        for k in range(-spread, spread + 1):
            stop = min(stop, hits[(b + k) % n_bins])
        limit[b] = open_m if stop == np.inf else stop - margin_m
    out = np.zeros((h, w), np.uint8)
    for r in range(h):
        for c in range(w):
            d = dist[r, c]
            if d < limit[bins[r, c]] and d >= min_range_m and not near[r, c]:
                out[r, c] = 1
    return out


def free_space_map(bev: BevImage, min_value: int, near: np.ndarray, cfg: FreeSpaceConfig) -> np.ndarray:
    """uint8 (H, W) mask of the pixels this car saw through (see the module doc). ``near``: uint8 mask of the pixels
    near its structure (``acquire.covisible_map``), never free: a wall's own pixels and their quantisation."""
    n_bins = max(8, int(round(360.0 / cfg.bin_deg)))
    h, w = bev.shape
    bins, dist = _polar(h, w, float(bev.range_m), float(bev.resolution_m), n_bins)
    return _free_map(
        np.ascontiguousarray(bev.image),
        min_value,
        bins,
        dist,
        np.ascontiguousarray(near, dtype=np.uint8),
        n_bins,
        cfg.min_range_m,
        cfg.margin_m,
        cfg.open_m,
        cfg.spread_bins,
    )


def tall_points(bev: BevImage, cfg: FreeSpaceConfig, seed: int = 0) -> np.ndarray:
    """(N, 2) metres of the pixels standing at least ``cfg.tall_m`` above the ground (a seeded subset of at most
    ``cfg.max_points``): structure the other car's beams would not have missed."""
    span = bev.max_height_m - bev.ground_clearance_m
    v_min = 1 + int(np.ceil((cfg.tall_m - bev.ground_clearance_m) / span * 254.0)) if bev.mode == "max_height" else 1
    rc = np.argwhere(bev.image >= max(1, v_min))
    if len(rc) > cfg.max_points:
        rc = rc[np.random.default_rng(seed).choice(len(rc), cfg.max_points, replace=False)]
    return bev.pixel_to_metre(rc)


def conflict(free: np.ndarray, covis: np.ndarray, bev: BevImage, pts: np.ndarray, T: np.ndarray) -> float:
    """Of the points ``pts`` (another car's tall structure, its own frame) moved by ``T`` into this car's frame and
    landing where this car saw something (free space, or within reach of its structure: ``covis``), the share in its
    free space. 0 when none lands there."""
    if len(pts) == 0:
        return 0.0
    p = np.ascontiguousarray(pts @ T[:2, :2].T + T[:2, 2])
    in_free = covisible_share(free, p, bev.range_m, bev.resolution_m)  # shares of all the points: their ratio is
    near = covisible_share(covis, p, bev.range_m, bev.resolution_m)  # the ratio of the counts
    return float(in_free / (in_free + near)) if in_free + near else 0.0
