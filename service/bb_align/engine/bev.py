"""Bird's-eye-view (BV) height image of a LiDAR cloud (paper Eq. 4), its pixel<->metre mapping and PNG codec.

Pixel convention (sensor frame x forward, y left): the sensor sits at the image centre, rows grow with -x
(forward is up), columns grow with -y (left is left). Pixel (r, c) covers x in (R - (r+1)c, R - rc] and its
centre, the integer pixel coordinate used everywhere (OpenCV keypoints included), is at
``x = R - (r + 0.5) c``, ``y = R - (c_idx + 0.5) c``.

Heights are measured above a local ground estimate (a min-filtered coarse grid of the lowest points), so
cars with different mounting heights and gently sloped roads give comparable images, and ground returns
stay dark.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import minimum_filter

from .config import BevConfig

# The ground under each pixel: the lowest return in a GROUND_CELL_M grid, min-filtered over GROUND_WINDOW_CELLS
# cells (a car's roof in one cell is no ground); the heights are measured from it.
GROUND_CELL_M = 2.0
GROUND_WINDOW_CELLS = 3


@dataclass(frozen=True)
class BevImage:
    """A uint8 BV image and everything needed to map its pixels to metres in the sensor frame."""

    image: np.ndarray  # (H, W) uint8
    resolution_m: float
    range_m: float
    mode: str = "max_height"
    ground_clearance_m: float = 0.3
    max_height_m: float = 12.0

    def __post_init__(self) -> None:
        img = self.image
        if not (isinstance(img, np.ndarray) and img.ndim == 2 and img.dtype == np.uint8):
            raise ValueError("BevImage.image must be a 2-D uint8 array")
        if not (self.resolution_m > 0 and self.range_m > 0):
            raise ValueError("BevImage.resolution_m and range_m must be positive")

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape  # type: ignore[return-value]

    def pixel_to_metre(self, rc: np.ndarray) -> np.ndarray:
        """(N, 2) pixel coordinates (row, col) -> (N, 2) metres (x, y) in the sensor frame."""
        rc = np.asarray(rc, dtype=float).reshape(-1, 2)
        x = self.range_m - (rc[:, 0] + 0.5) * self.resolution_m
        y = self.range_m - (rc[:, 1] + 0.5) * self.resolution_m
        return np.stack([x, y], axis=1)

    def metre_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) metres (x, y) -> (N, 2) continuous pixel coordinates (row, col)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        r = (self.range_m - xy[:, 0]) / self.resolution_m - 0.5
        c = (self.range_m - xy[:, 1]) / self.resolution_m - 0.5
        return np.stack([r, c], axis=1)

    def heights_m(self) -> np.ndarray:
        """Decode pixel values back to metres above ground (max_height mode; 0 where empty)."""
        if self.mode != "max_height":
            raise ValueError("heights_m is defined for mode='max_height' only")
        v = self.image.astype(np.float32)
        h = self.ground_clearance_m + (v - 1.0) / 254.0 * (self.max_height_m - self.ground_clearance_m)
        return np.where(v > 0, h, 0.0)

    def to_png(self, compression: int = 6) -> bytes:
        return encode_png(self.image, compression)

    def meta(self) -> dict:
        """Everything but the pixels, as plain numbers (for the wire)."""
        return {
            "resolution_m": self.resolution_m,
            "range_m": self.range_m,
            "mode": self.mode,
            "ground_clearance_m": self.ground_clearance_m,
            "max_height_m": self.max_height_m,
        }

    @classmethod
    def from_png(cls, data: bytes, **meta) -> BevImage:
        return cls(image=decode_png(data), **meta)


def image_size_px(config: BevConfig) -> int:
    return int(round(2 * config.range_m / config.resolution_m))


def ground_height_map(pts_sensor: np.ndarray, config: BevConfig) -> tuple[np.ndarray, float]:
    """Coarse local ground height (grid of ``GROUND_CELL_M``): min z per cell, min-filtered; and the cell size."""
    g = GROUND_CELL_M
    n = int(np.ceil(2 * config.range_m / g))
    gi = np.clip(((config.range_m - pts_sensor[:, 0]) / g).astype(np.int64), 0, n - 1)
    gj = np.clip(((config.range_m - pts_sensor[:, 1]) / g).astype(np.int64), 0, n - 1)
    cell_min = np.full(n * n, np.inf, dtype=np.float32)
    np.minimum.at(cell_min, gi * n + gj, pts_sensor[:, 2].astype(np.float32))
    cell_min = cell_min.reshape(n, n)
    finite = np.isfinite(cell_min)
    fallback = float(np.percentile(cell_min[finite], 10)) if finite.any() else 0.0
    ground = minimum_filter(np.where(finite, cell_min, np.inf), size=GROUND_WINDOW_CELLS, mode="nearest")
    ground[~np.isfinite(ground)] = fallback
    return ground, g


def make_bev(points: np.ndarray, config: BevConfig | None = None) -> BevImage:
    """Cloud (N, 3+) in the sensor frame (x forward, y left, z up, metres) -> uint8 BV height image."""
    config = config or BevConfig()
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, 3+), got shape {pts.shape}")
    pts = pts[:, :3].astype(np.float64, copy=False)
    R, c = config.range_m, config.resolution_m
    n = image_size_px(config)
    keep = np.all(np.isfinite(pts), axis=1) & (np.abs(pts[:, 0]) < R) & (np.abs(pts[:, 1]) < R)
    pts = pts[keep]
    image = np.zeros((n, n), dtype=np.uint8)
    if len(pts) == 0:
        return _bev(image, config)

    ground, g = ground_height_map(pts, config)
    ng = ground.shape[0]
    gi = np.clip(((R - pts[:, 0]) / g).astype(np.int64), 0, ng - 1)
    gj = np.clip(((R - pts[:, 1]) / g).astype(np.int64), 0, ng - 1)
    h = pts[:, 2] - ground[gi, gj]

    rows = np.clip(np.floor((R - pts[:, 0]) / c).astype(np.int64), 0, n - 1)
    cols = np.clip(np.floor((R - pts[:, 1]) / c).astype(np.int64), 0, n - 1)
    sel = h >= config.ground_clearance_m
    rows, cols, h = rows[sel], cols[sel], np.minimum(h[sel], config.max_height_m)
    flat = rows * n + cols

    if config.mode == "max_height":
        span = config.max_height_m - config.ground_clearance_m
        v = 1.0 + np.round((h - config.ground_clearance_m) / span * 254.0)
        out = np.zeros(n * n, dtype=np.float32)
        np.maximum.at(out, flat, v.astype(np.float32))
        image = out.reshape(n, n).astype(np.uint8)
    else:  # slices: 10 per occupied z-slice, capped at 100 (the reference's height proxy)
        n_slices = int(np.ceil((config.max_height_m - config.ground_clearance_m) / config.slice_m)) + 1
        s = ((h - config.ground_clearance_m) / config.slice_m).astype(np.int64)
        occupied = np.unique(flat * n_slices + s) // n_slices
        counts = np.bincount(occupied, minlength=n * n)
        image = np.minimum(counts * 10, 100).astype(np.uint8).reshape(n, n)
    return _bev(image, config)


def _bev(image: np.ndarray, config: BevConfig) -> BevImage:
    return BevImage(
        image=image,
        resolution_m=config.resolution_m,
        range_m=config.range_m,
        mode=config.mode,
        ground_clearance_m=config.ground_clearance_m,
        max_height_m=config.max_height_m,
    )


def encode_png(image: np.ndarray, compression: int = 6) -> bytes:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)])
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def decode_png(data: bytes) -> np.ndarray:
    """PNG bytes -> 2-D uint8 array. Callers facing untrusted input validate the header first (bb_align.protocol)."""
    arr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise ValueError("not a decodable PNG image")
    if arr.ndim != 2 or arr.dtype != np.uint8:
        raise ValueError(f"BV image must be 8-bit single channel, got shape {arr.shape} dtype {arr.dtype}")
    return arr
