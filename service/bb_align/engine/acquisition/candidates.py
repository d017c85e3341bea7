"""Step 1 of the acquisition: each peer keypoint's ``top_k`` nearest ego keypoints by descriptor."""

from __future__ import annotations

import numpy as np

from ..matching import sq_distances


def topk_candidates(
    desc_peer: np.ndarray, desc_ref: np.ndarray, n_ego: int, k: int, threads: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """(peer rows with a usable descriptor (Q,), their ``k`` nearest distinct ego keypoints (Q, k), nearest
    first). ``desc_ref`` holds several descriptions of each ego keypoint (row r describes keypoint r % n_ego);
    the closest one counts."""
    q = np.asarray(desc_peer, dtype=np.float32)
    t = np.asarray(desc_ref, dtype=np.float32)
    valid = np.flatnonzero((q * q).sum(1) > 0) if len(q) else np.zeros(0, np.int64)
    if len(valid) == 0 or n_ego == 0:
        return np.zeros(0, np.int64), np.zeros((0, max(1, min(k, n_ego))), np.int64)
    d2 = sq_distances(q[valid], t, threads).reshape(len(valid), -1, n_ego).min(axis=1)  # (Q, n_ego)
    k = min(k, n_ego)
    cand = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < n_ego else np.tile(np.arange(n_ego), (len(valid), 1))
    order = np.argsort(np.take_along_axis(d2, cand, axis=1), axis=1)
    return valid, np.take_along_axis(cand, order, axis=1)
