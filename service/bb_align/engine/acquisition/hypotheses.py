"""Step 2 of the acquisition: distinct pose hypotheses from the candidates.

Every pair of peer keypoints whose candidate partners' lengths agree votes for the rigid pose it implies, in a
coarse (yaw, tx, ty) accumulator (soft, 2x2x2 cells); the strongest distinct peaks are each refitted on their
candidate inliers (Kabsch). Exhaustive over pairs and deterministic (no sampling: a pose supported by 15 right
candidates among 2000 still stands out). The boxes both cars detected and a prior propose further poses.
"""

from __future__ import annotations

import numpy as np

from ..box_poses import box_poses
from ..config import AcquireConfig
from ..geometry import pose_is_distinct, se2, se2_params
from ..parallel import contiguous, run_parts
from .kernels import Keypoints, VoteGrid, cast, cells_above, ego_pairs, keypoints, peak_support, refit, scatter
from .model import Hypothesis, PriorWindow, distinct

VOTE_CHUNK = 65536  # votes per buffer: a peer pair is cast whole into one buffer (see vote)

# The pose accumulator's cells (degrees, metres): coarse, and every vote is split over its 2x2x2 nearest cells.
VOTE_YAW_DEG, VOTE_T_M = 3.0, 3.0
MIN_VOTES = 2.0  # cells with fewer (soft) votes are not examined
LENGTH_TOLERANCE_M = 1.5  # a candidate pair votes only if its length and the peer pair's differ less
MIN_HYPOTHESIS_INLIERS = 6  # hypotheses with fewer distinct inlier keypoints are not verified
REFITS = 4  # Kabsch refits of a peak on its candidate inliers


def _even_rows(q: int, parts: int) -> list[tuple[int, int]]:
    """Row ranges [a0, a1) of the peer pairs (a, b > a) holding about equal numbers of pairs, in order."""
    after = np.cumsum(np.arange(q - 1, -1, -1))  # pairs with first index <= a
    cuts = np.searchsorted(after, after[-1] * np.arange(1, parts) / parts) if q else np.zeros(parts - 1, int)
    bounds = [0, *(int(c) + 1 for c in cuts), q]
    return [(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True) if hi > lo]


def vote(
    kps: Keypoints, pairs, grid: VoteGrid, n_yaw: int, n_t: int, threads: int = 1, chunk: int = VOTE_CHUNK
) -> np.ndarray:
    """The (n_yaw, n_t, n_t) float32 accumulator of every candidate pair's pose vote (``kernels.cast``), each vote
    split over the 2x2x2 nearest cells. In two parallel phases with the same result for any ``threads``: the votes
    are cast into buffers by ranges of peer rows, then added by yaw slabs, each slab reading every buffer in the
    order the votes were cast. Buffering also lets the accumulator (several MB) be written in a tight loop whose
    cache misses overlap. Transient memory: 36 bytes per vote (1.5 MB on a close pair's first pass, ~16 MB on a far
    pair's 12-candidate search); ``chunk``: votes per buffer; ``pairs``: ``ego_pairs(kps.dst)``."""
    chunk = max(chunk, kps.cand.shape[1] ** 2)

    def cast_rows(rows: tuple[int, int]) -> list[tuple[np.ndarray, np.ndarray, int]]:
        a, a_end = rows
        b, out = a + 1, []
        while a < a_end:
            cell, frac = np.empty((chunk, 3), np.int32), np.empty((chunk, 3))
            n, a, b = cast(kps, pairs, grid, a, b, a_end, cell, frac)
            out.append((cell, frac, n))
        return out

    buffers = [buf for part in run_parts(cast_rows, _even_rows(len(kps.cand), threads)) for buf in part]
    acc = np.zeros((n_yaw, n_t, n_t), np.float32)

    def add(slab: tuple[int, int]) -> None:
        for cell, frac, n in buffers:
            scatter(acc, cell, frac, n, n_t, slab[0], slab[1])

    run_parts(add, [(r.start, r.stop) for r in contiguous(range(n_yaw), threads)])
    return acc


def _accumulator(kps: Keypoints, pairs, cfg: AcquireConfig, t_half: float, window, votes) -> tuple[np.ndarray, float]:
    """The vote accumulator (read from / kept in ``votes`` by candidates per keypoint; masked to ``window``) and its
    yaw cell (radians, a whole number of cells per turn)."""
    yaw_bin = np.radians(VOTE_YAW_DEG)
    n_yaw = int(np.ceil(2 * np.pi / yaw_bin))
    yaw_bin = 2 * np.pi / n_yaw
    n_t = int(np.ceil(2 * t_half / VOTE_T_M))
    k = kps.cand.shape[1]
    acc = None if votes is None else votes.get(k)
    if acc is None:
        grid = VoteGrid(cfg.min_sample_dist_m, LENGTH_TOLERANCE_M, yaw_bin, VOTE_T_M, t_half)
        acc = vote(kps, pairs, grid, n_yaw, n_t, cfg.threads)
        if votes is not None:
            votes[k] = acc
    if window is not None:
        acc = acc.copy() if votes is not None else acc
        window.mask_accumulator(acc, yaw_bin, VOTE_T_M, t_half)
    return acc, yaw_bin


def _peaks(acc: np.ndarray, yaw_bin: float, cfg: AcquireConfig, t_half: float):
    """The strongest ``cfg.peaks`` cells above ``MIN_VOTES``: (their votes, yaw, tx, ty at the cell centres), or
    None."""
    flat = acc.ravel()
    idx = cells_above(flat, MIN_VOTES)
    if len(idx) == 0:
        return None
    idx = idx[np.argsort(-flat[idx], kind="stable")[: cfg.peaks]]
    iy, ix, iz = np.unravel_index(idx, acc.shape)
    yaw = (iy + 0.5) * yaw_bin - np.pi  # cell centres, all in (-pi, pi)
    tx, ty = (ix + 0.5) * VOTE_T_M - t_half, (iz + 0.5) * VOTE_T_M - t_half
    return flat[idx], yaw, tx, ty


def pose_hypotheses(
    kp_peer: np.ndarray,
    kp_ego: np.ndarray,
    cand: np.ndarray,
    cfg: AcquireConfig,
    threshold: float,
    t_half: float,
    pairs: tuple[np.ndarray, np.ndarray] | None = None,
    window: PriorWindow | None = None,
    votes: dict[int, np.ndarray] | None = None,
) -> list[Hypothesis]:
    """Up to cfg.max_hypotheses distinct poses (most inliers first) from the candidates ``cand`` (Q, k): row q
    lists the ego keypoints that may be peer keypoint q's partner. ``pairs``: ``ego_pairs(kp_ego)`` when cached.
    ``window``: only poses inside it (the accumulator is searched there alone, so weaker in-window peaks are not
    crowded out by strong poses elsewhere). ``votes``: accumulators by candidates per keypoint, read when there
    and filled when not (SearchMemo.votes; never masked in place)."""
    if cand.shape[0] < 2:
        return []
    kps = keypoints(kp_peer, kp_ego, cand)
    pairs = ego_pairs(kps.dst) if pairs is None else pairs
    acc, yaw_bin = _accumulator(kps, pairs, cfg, t_half, window, votes)
    peaks = _peaks(acc, yaw_bin, cfg, t_half)
    return [] if peaks is None else _refit_peaks(kps, peaks, cfg, threshold, window)


def _refit_peaks(kps: Keypoints, peaks, cfg: AcquireConfig, threshold: float, window) -> list[Hypothesis]:
    """The peaks refitted on their candidate inliers, strongest support first, each kept when distinct from those
    kept before (and inside ``window``); most inliers first."""
    votes, yaw, tx, ty = peaks
    # The cell centres are coarse: score them all with a wide threshold (compiled, no (peaks x M) arrays), refit
    # the strongest.
    n_wide = peak_support(kps, yaw, tx, ty, (2 * threshold) ** 2)
    out: list[Hypothesis] = []
    found = np.empty((cfg.max_hypotheses, 3))  # se2_params of out's poses
    attempts = 0
    for h in np.argsort(-n_wide, kind="stable"):
        if len(out) >= cfg.max_hypotheses or n_wide[h] < MIN_HYPOTHESIS_INLIERS or attempts >= cfg.max_refit_attempts:
            break
        near = (cfg.distinct_m + VOTE_T_M, cfg.distinct_deg + VOTE_YAW_DEG)
        if not pose_is_distinct(found[: len(out)], (yaw[h], tx[h], ty[h]), *near):
            continue  # a neighbouring cell of a pose already found
        attempts += 1
        y, x, z, n, mask = refit(
            kps, float(yaw[h]), float(tx[h]), float(ty[h]), (2 * threshold) ** 2, threshold * threshold, REFITS
        )
        T = se2(y, x, z)
        params = se2_params(T)
        if window is not None and not window.holds(T):
            continue
        if n < MIN_HYPOTHESIS_INLIERS or not pose_is_distinct(
            found[: len(out)], params, cfg.distinct_m, cfg.distinct_deg
        ):
            continue
        found[len(out)] = params
        out.append(Hypothesis(T=T, inliers=n, votes=float(votes[h]), inlier_mask=mask))
    out.sort(key=lambda h: -h.inliers)
    return out


def box_hypotheses(boxes_ego: np.ndarray, boxes_peer: np.ndarray, cfg: AcquireConfig) -> list[Hypothesis]:
    """The poses the boxes both cars detected propose (``box_poses``), as hypotheses (votes = paired boxes)."""
    return [
        Hypothesis(T=b.T, inliers=0, votes=float(b.pairs), source="boxes")
        for b in box_poses(boxes_ego, boxes_peer, cfg)
    ]


def _inliers(T, src, dst, k, thr2):
    """Candidate inlier mask and the number of distinct peer keypoints with an inlier (rows come k per keypoint)."""
    p = src @ T[:2, :2].T + T[:2, 2]
    mask = ((p - dst) ** 2).sum(1) < thr2
    return mask, int(mask.reshape(-1, k).any(axis=1).sum())


def with_keypoint_inliers(
    extra: list[Hypothesis], have: list[Hypothesis], kp_peer, kp_ego, cand: np.ndarray, cfg: AcquireConfig, thr: float
) -> list[Hypothesis]:
    """Copies of the ``extra`` hypotheses distinct from ``have``, with their keypoint candidate inliers counted as
    pose_hypotheses counts them (so every verified hypothesis reports the same evidence)."""
    if not extra:
        return []
    k = cand.shape[1]
    src, dst = np.repeat(kp_peer, k, axis=0), kp_ego[cand.ravel()]
    out = []
    for h in extra:
        if distinct(h.T, have, cfg.distinct_m, cfg.distinct_deg):
            mask, n = _inliers(h.T, src, dst, k, thr * thr)
            out.append(Hypothesis(T=h.T.copy(), inliers=n, votes=h.votes, inlier_mask=mask, source=h.source))
    return out
