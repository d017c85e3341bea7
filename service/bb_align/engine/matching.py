"""Descriptor matching: brute-force L2 nearest neighbour (optionally mutual and/or ratio-tested)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .config import FeatureConfig, MatchConfig, PriorConfig
from .geometry import ground_se2
from .parallel import run_parts

if TYPE_CHECKING:
    from .frame import PreparedFrame


def sq_distances(q: np.ndarray, t: np.ndarray, threads: int = 1) -> np.ndarray:
    """(Q, T) float32 squared L2 distances, |q|^2 + |t|^2 - 2 q.t, built in place (no large temporaries); with
    threads > 1 blocks of query rows are multiplied in parallel (the same numbers)."""
    d2 = np.empty((len(q), len(t)), dtype=np.float32)
    qq, tt = (q * q).sum(1), (t * t).sum(1)

    def block(rows: slice) -> None:
        out = d2[rows]
        np.matmul(q[rows], t.T, out=out)
        out *= -2.0
        out += qq[rows, None]
        out += tt[None, :]
        np.maximum(out, 0.0, out=out)

    step = -(-len(q) // max(1, threads))
    run_parts(block, [slice(i, i + step) for i in range(0, len(q), step)])
    return d2


def match_descriptors(
    desc_query: np.ndarray, desc_train: np.ndarray, *, mutual: bool = False, ratio: float = 1.0, threads: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i_query, i_train) of each query descriptor's nearest train descriptor.

    Empty (all-zero) query descriptors never match. ``ratio`` < 1 keeps a match only when its distance is below
    ratio x the second-best distance; ``mutual`` keeps it only when the query is also the train's nearest.
    ``threads``: query blocks whose distances are computed in parallel (the same result).
    """
    q = np.asarray(desc_query, dtype=np.float32)
    t = np.asarray(desc_train, dtype=np.float32)
    if len(q) == 0 or len(t) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d2 = sq_distances(q, t, threads)
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


def match_with_prior(
    desc_query: np.ndarray,
    desc_train: np.ndarray,
    xy_query: np.ndarray,
    xy_train: np.ndarray,
    T_train_query: np.ndarray,
    *,
    max_translation: float,
    max_yaw_rad: float,
    top_k: int,
    threads: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """The ``top_k`` nearest train descriptors of each query, kept only where the prior pose T_train_query (3x3)
    puts the two keypoints within ``max_translation`` plus the displacement a ``max_yaw_rad`` rotation error
    causes at the query's range. Returns (i_query, i_train) pairs (a query may keep several)."""
    q = np.asarray(desc_query, dtype=np.float32)
    t = np.asarray(desc_train, dtype=np.float32)
    if len(q) == 0 or len(t) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    k = min(top_k, len(t))
    d2 = sq_distances(q, t, threads)
    cand = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < len(t) else np.tile(np.arange(len(t)), (len(q), 1))
    pred = xy_query @ T_train_query[:2, :2].T + T_train_query[:2, 2]
    gate = max_translation + np.linalg.norm(xy_query, axis=1) * 2.0 * np.sin(max_yaw_rad / 2.0)
    dist = np.linalg.norm(pred[:, None, :] - xy_train[cand], axis=2)
    ok = (dist < gate[:, None]) & ((q * q).sum(1) > 0)[:, None]
    i_q, j = np.nonzero(ok)
    return i_q, cand[i_q, j]


class Matcher:
    """Algorithm 1 lines 9-10 as a pipeline step, built once from the config: the peer's descriptors against the
    ego frame's reference descriptors (every orientation offset, and the 180-degree copies), by nearest neighbour
    or, given a prior pose, the top-k gated by it. Returns the matched keypoints (P_src, P_dest) in metres."""

    def __init__(self, match: MatchConfig, prior: PriorConfig, features: FeatureConfig, n_orient: int):
        self.match, self.prior, self.features, self.n_orient = match, prior, features, n_orient

    def __call__(
        self, ego: PreparedFrame, peer: PreparedFrame, T_prior: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        desc_ego = ego.reference_descriptors(self.features, self.n_orient)
        n_ego = len(ego.descriptors)
        if T_prior is None:
            i_peer, i_ego = match_descriptors(
                peer.descriptors, desc_ego, mutual=self.match.mutual, ratio=self.match.ratio, threads=self.match.threads
            )
        else:
            xy_ego = np.tile(ego.keypoints_xy, (len(desc_ego) // n_ego, 1))  # row i is keypoint i % K
            i_peer, i_ego = match_with_prior(
                peer.descriptors,
                desc_ego,
                peer.keypoints_xy,
                xy_ego,
                ground_se2(T_prior),
                max_translation=self.prior.max_translation_m,
                max_yaw_rad=np.radians(self.prior.max_yaw_deg),
                top_k=self.prior.top_k,
                threads=self.match.threads,
            )
        return peer.keypoints_xy[i_peer], ego.keypoints_xy[i_ego % n_ego]
