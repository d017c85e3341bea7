"""One car's frame with its engine features (Algorithm 1 lines 6-8 computed once, reused against many frames)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .bev import BevImage
from .config import FeatureConfig, RefineConfig
from .descriptors import bvft_descriptors, flip_180
from .parallel import run_parts
from .refine import BevCloud, bev_cloud

# The matched-against (ego) side also describes each keypoint as if its dominant orientation were the neighbouring
# bins: a peer whose orientation estimate is one bin off still finds its match (+35 % correct matches at 40-70 m).
REFERENCE_ORIENTATION_OFFSETS = (0, -1, 1)


def _no_features() -> np.ndarray:
    return np.zeros((0, 2))


@dataclass
class PreparedFrame:
    """One car's frame with its engine features computed (reusable against many other frames).

    A frame prepared for tracking only (``Aligner.prepare(..., features=False)``) has its BV image and boxes but
    no MIM, keypoints or descriptors yet: the dense refinement needs none of them. ``ensure_features`` computes them
    the first time an acquisition needs them (once, whichever thread asks first)."""

    bev: BevImage
    boxes: np.ndarray  # (K, 7) [x, y, z, l, w, h, yaw], sensor frame
    keypoints_rc: np.ndarray = field(default_factory=_no_features)  # (K, 2) pixels (row, col)
    keypoints_xy: np.ndarray = field(default_factory=_no_features)  # (K, 2) metres in the sensor frame
    descriptors: np.ndarray = field(default_factory=_no_features)  # (K, D)
    descriptors_flipped: np.ndarray = field(default_factory=_no_features)  # (K, D) the same patches rotated 180 deg
    orientations: np.ndarray | None = None  # (K,) dominant MIM orientation of each keypoint (1..No, 0: none)
    mim: np.ndarray | None = None  # kept for plots when keep_maps=True
    num_points: int | None = None  # raw cloud size when known
    timings_ms: dict[str, float] = field(default_factory=dict)
    _maps: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)  # (MIM, max amplitude)
    _cloud: BevCloud | None = field(default=None, repr=False)
    _reference: np.ndarray | None = field(default=None, repr=False)
    _derived: dict = field(default_factory=dict, repr=False)  # other per-frame products, built on first use
    _features: Callable[[BevImage], dict] | None = field(default=None, repr=False)  # pending: computes them
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def has_features(self) -> bool:
        return self._features is None

    def ensure_features(self) -> PreparedFrame:
        """Compute the MIM, keypoints and descriptors now if this frame was prepared without them."""
        if self._features is not None:
            with self._lock:
                if self._features is not None:
                    fields = self._features(self.bev)
                    for name, value in fields.items():
                        setattr(self, name, value)
                    self._features = None
        return self

    def reference_descriptors(self, features: FeatureConfig, n_orient: int) -> np.ndarray:
        """What this frame offers when it is the side matched against (the ego frame): for each orientation
        offset in ``REFERENCE_ORIENTATION_OFFSETS`` the descriptors and their 180-degree copies,
        (2 x offsets x K, D); row i describes keypoint i % K. Built on first use (an ego frame pays it once)."""
        if self._reference is None:

            def describe(offset: int) -> list[np.ndarray]:
                if offset == 0:
                    return [self.descriptors, self.descriptors_flipped]
                d = bvft_descriptors(
                    *self._maps,
                    self.keypoints_rc,
                    features,
                    n_orient,
                    orientation_offset=offset,
                    orientations=self.orientations,
                )
                return [d, flip_180(d, features)]

            self._reference = np.concatenate(sum(run_parts(describe, REFERENCE_ORIENTATION_OFFSETS), []))
        return self._reference

    def cloud(self, cfg: RefineConfig) -> BevCloud:
        """Lit pixels with normals and their index image (built on first use: an ego frame pays it once)."""
        if self._cloud is None:
            self._cloud = bev_cloud(self.bev, cfg)
        return self._cloud

    def cached(self, key, build):
        """A product of this frame that steps reuse (e.g. the acquisition's co-visibility mask), built once."""
        if key not in self._derived:
            self._derived[key] = build()
        return self._derived[key]

    @property
    def lit_pixels(self) -> int:
        return int(np.count_nonzero(self.bev.image))
