"""Descriptor matching: brute-force L2 nearest neighbour (optionally mutual and/or ratio-tested)."""

from __future__ import annotations

import numpy as np


def match_descriptors(desc_query: np.ndarray, desc_train: np.ndarray, *, mutual: bool = False,
                      ratio: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i_query, i_train) of each query descriptor's nearest train descriptor.

    Empty (all-zero) query descriptors never match. ``ratio`` < 1 keeps a match only when its distance is below
    ratio x the second-best distance; ``mutual`` keeps it only when the query is also the train's nearest.
    """
    q = np.asarray(desc_query, dtype=np.float32)
    t = np.asarray(desc_train, dtype=np.float32)
    if len(q) == 0 or len(t) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d2 = (q * q).sum(1)[:, None] + (t * t).sum(1)[None, :] - 2.0 * (q @ t.T)
    np.maximum(d2, 0.0, out=d2)
    nn = d2.argmin(axis=1)
    keep = (q * q).sum(1) > 0
    if ratio < 1.0 and t.shape[0] > 1:
        part = np.partition(d2, 1, axis=1)
        keep &= np.sqrt(part[:, 0]) < ratio * np.sqrt(part[:, 1])
    if mutual:
        back = d2.argmin(axis=0)
        keep &= back[nn] == np.arange(len(q))
    i_q = np.flatnonzero(keep)
    return i_q, nn[i_q]
