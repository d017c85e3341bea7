"""FAST keypoints on the BV image itself (not on the MIM), strongest first."""

from __future__ import annotations

import cv2
import numpy as np

from .config import FeatureConfig

FAST_THRESHOLD = 10  # FAST intensity threshold on the 0-255 height image: ~0.5 m of height step at 12 m / 255


def detect_keypoints(image: np.ndarray, cfg: FeatureConfig | None = None) -> np.ndarray:
    """uint8 BV image -> (K, 2) int32 pixel coordinates (row, col), at most ``cfg.max_keypoints``, by response."""
    cfg = cfg or FeatureConfig()
    fast = cv2.FastFeatureDetector_create(
        threshold=FAST_THRESHOLD, nonmaxSuppression=True, type=cv2.FAST_FEATURE_DETECTOR_TYPE_9_16
    )
    kps = fast.detect(image, None)
    if not kps:
        return np.zeros((0, 2), dtype=np.int32)
    response = np.array([k.response for k in kps], dtype=np.float32)
    pts = np.array([k.pt for k in kps], dtype=np.float32)  # (x=col, y=row)
    # Strongest first; ties broken by position so the order is deterministic.
    order = np.lexsort((pts[:, 0], pts[:, 1], -response))[: cfg.max_keypoints]
    rc = np.round(pts[order][:, ::-1]).astype(np.int32)
    return rc
