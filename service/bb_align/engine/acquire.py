"""Multi-hypothesis acquisition: stage 1 for pairs 40-100 m apart (not in the paper; docs/acquisition.md).

At long range the nearest-neighbour descriptor match is right for only a few peer keypoints, but the true partner
is usually among the few nearest. So, instead of the paper's one RANSAC fit on nearest neighbours:

1. candidates: the ``top_k`` nearest ego keypoints (by descriptor, over all orientation offsets and 180-degree
   copies) of every peer keypoint;
2. hypotheses: every pair of candidates whose lengths agree votes for the rigid pose it implies, in a coarse
   (yaw, tx, ty) accumulator (soft, 2x2x2 cells); the strongest distinct peaks are each refitted on their
   candidate inliers (Kabsch), giving up to ``max_hypotheses`` distinct poses. Exhaustive over pairs and
   deterministic (no sampling: a pose supported by 15 right candidates among 2000 still stands out);
3. verification: each hypothesis is refined coarsely (dense point-to-line ICP on a small subset of the peer's lit
   pixels) and scored by its dense overlap; the ``finalists`` best are refined fully and scored again;
4. decision: the best must beat the runner-up (a distinct pose) by ``min_margin`` and its overlap must be a
   sufficient fraction of what the two images can share at that pose (``relative fitness``), else failure.

Everything here is config-driven (``AcquireConfig``) and reuses the ego frame's cached features.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit

from .box_poses import BoxSet, box_agreement, box_poses, same_size
from .config import AcquireConfig, AlignConfig, CovarianceConfig, RefineConfig
from .covariance import params_covariance, pose_covariance
from .freespace import conflict, free_space_map, tall_points
from .geometry import distinct_pose, pose_is_distinct, se2, se2_params
from .matching import sq_distances
from .parallel import contiguous, run_parts
from .refine import (
    BevCloud,
    bev_samples,
    coarse_verification_loop,
    covisible_share,
    facing_args,
    icp_params,
    peer_normals,
    refine_icp,
)
from .result import AlignResult
from .verdict import FailureReason

# ---- 1. candidates -------------------------------------------------------------------------------------------


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


# ---- 2. hypotheses -------------------------------------------------------------------------------------------


_VOTE_CHUNK = 65536  # votes per buffer: a peer pair is cast whole into one buffer (see vote)


@njit(cache=True, nogil=True)
def _scatter(acc, cell, frac, n, n_t, y_lo, y_hi):
    """Adds the first ``n`` buffered votes to the accumulator, in order, each split over its 2x2x2 nearest cells:
    ``cell`` (n, 3) the lower corner (yaw, tx, ty), ``frac`` (n, 3) the vote's offsets from it (the weights). Only
    the yaw cells y_lo <= yaw < y_hi are written: threads owning disjoint slabs add every cell's votes in the order
    they were cast, so the sums are the same as one thread's."""
    n_yaw = acc.shape[0]
    for m in range(n):
        y0, x0, z0 = cell[m, 0], cell[m, 1], cell[m, 2]
        ay, ax, az = frac[m, 0], frac[m, 1], frac[m, 2]
        for e1 in range(2):
            yy = (y0 + e1) % n_yaw
            if yy < y_lo or yy >= y_hi:
                continue
            wy = ay if e1 else 1.0 - ay
            for e2 in range(2):
                xx = x0 + e2
                if xx < 0 or xx >= n_t:
                    continue
                wx = ax if e2 else 1.0 - ax
                for e3 in range(2):
                    zz = z0 + e3
                    if zz < 0 or zz >= n_t:
                        continue
                    acc[yy, xx, zz] += wy * wx * (az if e3 else 1.0 - az)


@njit(cache=True, nogil=True)
def ego_pairs(kp_dst):
    """What the vote needs of every ordered pair (i, j) of ego keypoints, computed once per ego frame: the distance
    (float32, (n, n)) and the direction angle of j - i (radians, (n, n))."""
    n_e = len(kp_dst)
    d_e = np.empty((n_e, n_e), np.float32)
    phi = np.empty((n_e, n_e))
    for i in range(n_e):
        for j in range(n_e):
            dx, dy = kp_dst[j, 0] - kp_dst[i, 0], kp_dst[j, 1] - kp_dst[i, 1]
            d_e[i, j] = np.sqrt(dx * dx + dy * dy)
            phi[i, j] = np.arctan2(dy, dx)
    return d_e, phi


@njit(cache=True, nogil=True)
def _cast(kp_src, kp_dst, cand, d_e, phi, min_d, len_tol, yaw_bin, t_bin, t_half, a, b, a_end, cell, frac):
    """The votes of the peer pairs (a, b), a < b, from the given (a, b) on, in order, while a < ``a_end`` and the
    buffers (``cell``, ``frac``: see _scatter) have room for a whole pair's votes. Every pair of peer keypoints at
    least ``min_d`` apart, with candidates (i, j) among their ego candidates ``cand`` (Q, k) whose distance agrees
    within ``len_tol``, votes for the rigid pose it implies. ``d_e``, ``phi``: ``ego_pairs(kp_dst)``; the pose's
    yaw is the ego pair's direction minus the peer pair's (one arctan2 per peer pair, not per vote).
    Returns (votes written, the (a, b) to resume from)."""
    q, k = cand.shape
    nb = 0
    while a < a_end:
        while b < q:
            if nb + k * k > len(cell):
                return nb, a, b
            sx, sy = kp_src[b, 0] - kp_src[a, 0], kp_src[b, 1] - kp_src[a, 1]
            ds = np.sqrt(sx * sx + sy * sy)
            if ds >= min_d:
                msx, msy = 0.5 * (kp_src[a, 0] + kp_src[b, 0]), 0.5 * (kp_src[a, 1] + kp_src[b, 1])
                psi = np.nan  # the peer pair's direction, computed at its first vote
                for u in range(k):
                    i = cand[a, u]
                    for v in range(k):
                        j = cand[b, v]
                        if i == j or abs(ds - d_e[i, j]) > len_tol:
                            continue
                        if psi != psi:
                            psi = np.arctan2(sy, sx)
                        th = phi[i, j] - psi
                        if th > np.pi:
                            th -= 2 * np.pi
                        elif th <= -np.pi:
                            th += 2 * np.pi
                        dx, dy = kp_dst[j, 0] - kp_dst[i, 0], kp_dst[j, 1] - kp_dst[i, 1]
                        cr, dt = sx * dy - sy * dx, sx * dx + sy * dy
                        nrm = np.sqrt(cr * cr + dt * dt)
                        c, s = dt / nrm, cr / nrm
                        mdx, mdy = 0.5 * (kp_dst[i, 0] + kp_dst[j, 0]), 0.5 * (kp_dst[i, 1] + kp_dst[j, 1])
                        tx = mdx - (c * msx - s * msy)
                        ty = mdy - (s * msx + c * msy)
                        fy = (th + np.pi) / yaw_bin - 0.5
                        fx = (tx + t_half) / t_bin - 0.5
                        fz = (ty + t_half) / t_bin - 0.5
                        y0, x0, z0 = int(np.floor(fy)), int(np.floor(fx)), int(np.floor(fz))
                        cell[nb, 0], cell[nb, 1], cell[nb, 2] = y0, x0, z0
                        frac[nb, 0], frac[nb, 1], frac[nb, 2] = fy - y0, fx - x0, fz - z0
                        nb += 1
            b += 1
        a += 1
        b = a + 1
    return nb, a, b


def _even_rows(q: int, parts: int) -> list[tuple[int, int]]:
    """Row ranges [a0, a1) of the peer pairs (a, b > a) holding about equal numbers of pairs, in order."""
    after = np.cumsum(np.arange(q - 1, -1, -1))  # pairs with first index <= a
    cuts = np.searchsorted(after, after[-1] * np.arange(1, parts) / parts) if q else np.zeros(parts - 1, int)
    bounds = [0, *(int(c) + 1 for c in cuts), q]
    return [(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True) if hi > lo]


def vote(
    kp_src, kp_dst, cand, pairs, min_d, len_tol, yaw_bin, t_bin, t_half, n_yaw, n_t, threads=1, chunk=_VOTE_CHUNK
) -> np.ndarray:
    """The (n_yaw, n_t, n_t) float32 accumulator of every candidate pair's pose vote (``_cast``), each vote split
    over the 2x2x2 nearest cells. In two parallel phases with the same result for any ``threads``: the votes are
    cast into buffers by ranges of peer rows, then added by yaw slabs, each slab reading every buffer in the order
    the votes were cast. Buffering also lets the accumulator (several MB) be written in a tight loop whose cache
    misses overlap. Transient memory: 36 bytes per vote (1.5 MB on a close pair's first pass, ~16 MB on a far
    pair's 12-candidate search); ``chunk``: votes per buffer."""
    d_e, phi = pairs
    k = cand.shape[1]
    args = (kp_src, kp_dst, cand, d_e, phi, min_d, len_tol, yaw_bin, t_bin, t_half)
    chunk = max(chunk, k * k)

    def cast(rows: tuple[int, int]) -> list[tuple[np.ndarray, np.ndarray, int]]:
        a, a_end = rows
        b, out = a + 1, []
        while a < a_end:
            cell, frac = np.empty((chunk, 3), np.int32), np.empty((chunk, 3))
            n, a, b = _cast(*args, a, b, a_end, cell, frac)
            out.append((cell, frac, n))
        return out

    buffers = [buf for part in run_parts(cast, _even_rows(len(cand), threads)) for buf in part]
    acc = np.zeros((n_yaw, n_t, n_t), np.float32)

    def add(slab: tuple[int, int]) -> None:
        for cell, frac, n in buffers:
            _scatter(acc, cell, frac, n, n_t, slab[0], slab[1])

    run_parts(add, [(r.start, r.stop) for r in contiguous(range(n_yaw), threads)])
    return acc


@njit(cache=True, nogil=True)
def _peak_support(kp_src, kp_dst, cand, yaw, tx, ty, thr2):
    """For each pose (yaw[h], tx[h], ty[h]): the number of peer keypoints with a candidate within sqrt(thr2)."""
    out = np.zeros(len(yaw), np.int64)
    q, k = cand.shape
    for h in range(len(yaw)):
        c, s = np.cos(yaw[h]), np.sin(yaw[h])
        n = 0
        for a in range(q):
            px = c * kp_src[a, 0] - s * kp_src[a, 1] + tx[h]
            py = s * kp_src[a, 0] + c * kp_src[a, 1] + ty[h]
            for u in range(k):
                j = cand[a, u]
                dx, dy = px - kp_dst[j, 0], py - kp_dst[j, 1]
                if dx * dx + dy * dy < thr2:
                    n += 1
                    break
        out[h] = n
    return out


@njit(cache=True, nogil=True)
def _refit(kp_src, kp_dst, cand, yaw, tx, ty, thr2_wide, thr2, refits):
    """From a coarse pose: candidate inliers within sqrt(thr2_wide), then up to ``refits`` rigid least-squares
    refits (2-D Kabsch) on the inliers within sqrt(thr2), stopping when the inlier set no longer changes.
    Returns (yaw, tx, ty, distinct peer keypoints with an inlier, inlier mask over cand.ravel())."""
    q, k = cand.shape
    mask = np.zeros(q * k, np.bool_)
    n = 0
    for it in range(refits + 1):
        c, s = np.cos(yaw), np.sin(yaw)
        thr = thr2_wide if it == 0 else thr2
        new = np.zeros(q * k, np.bool_)
        n_new = 0
        for a in range(q):
            px = c * kp_src[a, 0] - s * kp_src[a, 1] + tx
            py = s * kp_src[a, 0] + c * kp_src[a, 1] + ty
            hit = False
            for u in range(k):
                j = cand[a, u]
                dx, dy = px - kp_dst[j, 0], py - kp_dst[j, 1]
                if dx * dx + dy * dy < thr:
                    new[a * k + u] = True
                    hit = True
            if hit:
                n_new += 1
        if it > 0 and n_new < 2:
            break
        same = it > 0 and np.array_equal(new, mask)
        mask, n = new, n_new
        if same or it == refits:
            break
        # Kabsch on the inlier pairs.
        m = 0
        msx = msy = mdx = mdy = 0.0
        for r in range(q * k):
            if mask[r]:
                a = r // k
                j = cand[a, r % k]
                msx += kp_src[a, 0]
                msy += kp_src[a, 1]
                mdx += kp_dst[j, 0]
                mdy += kp_dst[j, 1]
                m += 1
        if m < 2:
            break
        msx /= m
        msy /= m
        mdx /= m
        mdy /= m
        sxx = sxy = 0.0
        for r in range(q * k):
            if mask[r]:
                a = r // k
                j = cand[a, r % k]
                ax, ay = kp_src[a, 0] - msx, kp_src[a, 1] - msy
                bx, by = kp_dst[j, 0] - mdx, kp_dst[j, 1] - mdy
                sxx += ax * bx + ay * by
                sxy += ax * by - ay * bx
        yaw = np.arctan2(sxy, sxx)
        c, s = np.cos(yaw), np.sin(yaw)
        tx = mdx - (c * msx - s * msy)
        ty = mdy - (s * msx + c * msy)
    return yaw, tx, ty, n, mask


@njit(cache=True, nogil=True)
def _cells_above(flat, floor):
    """Indices of the accumulator cells holding more than ``floor`` votes (one pass, no sort of the whole)."""
    n = 0
    for i in range(len(flat)):
        if flat[i] > floor:
            n += 1
    out = np.empty(n, np.int64)
    n = 0
    for i in range(len(flat)):
        if flat[i] > floor:
            out[n] = i
            n += 1
    return out


@dataclass
class Hypothesis:
    T: np.ndarray  # 3x3 ego <- peer
    inliers: int  # distinct peer keypoints with a candidate within the inlier threshold
    votes: float = 0.0
    fitness: float = 0.0  # dense overlap (fraction of peer pixels within the finest gate)
    covisible: float = 0.0  # fraction of peer pixels within AcquireConfig.covisible_m of ego structure
    rmse_m: float = float("inf")
    refined: bool = False
    inlier_mask: np.ndarray | None = field(default=None, repr=False)
    source: str = "keypoints"  # what proposed it: "keypoints" (descriptor votes), "boxes" or "prior"
    box_pairs: int = 0  # peer boxes paired with an agreeing ego box under T (box_poses.box_agreement)
    box_score: float = 0.0  # the boxes' soft score under T (box_poses.box_agreement)
    conflict: float = 0.0  # free-space conflict under T, the larger of the two directions (engine.freespace)
    _params: tuple = field(default=(None, None), init=False, repr=False, compare=False)

    @property
    def params(self) -> tuple[float, float, float]:
        """se2_params(T), kept until T is replaced (T is assigned anew, never changed in place)."""
        of, params = self._params
        if of is not self.T:
            params = se2_params(self.T)
            self._params = (self.T, params)
        return params

    @property
    def relative_fitness(self) -> float:
        return self.fitness / self.covisible if self.covisible > 0 else 0.0


def _inliers(T, src, dst, k, thr2):
    """Candidate inlier mask and the number of distinct peer keypoints with an inlier (rows come k per keypoint)."""
    p = src @ T[:2, :2].T + T[:2, 2]
    mask = ((p - dst) ** 2).sum(1) < thr2
    return mask, int(mask.reshape(-1, k).any(axis=1).sum())


def _distinct(T: np.ndarray, chosen: list[Hypothesis], dist_m: float, deg: float) -> bool:
    return not chosen or pose_is_distinct(np.array([h.params for h in chosen]), se2_params(T), dist_m, deg)


@dataclass(frozen=True)
class PriorWindow:
    """Where a prior pose (e.g. from both cars' reported GNSS poses) says the true pose lies: within ``max_m`` of
    its translation and ``max_deg`` of its yaw (config.prior). Hypotheses outside it are not formed, not verified
    and are no rivals."""

    T: np.ndarray  # 3x3 ego <- peer
    max_m: float
    max_deg: float

    @property
    def params(self) -> tuple[float, float, float]:
        return se2_params(self.T)

    def holds(self, T: np.ndarray) -> bool:
        return not distinct_pose(T, [self.T], self.max_m, self.max_deg)

    def mask_accumulator(self, acc: np.ndarray, yaw_bin: float, t_bin: float, t_half: float) -> None:
        """Zero (in place) every (yaw, tx, ty) cell whose centre lies more than one cell beyond the window."""
        yaw0, tx0, ty0 = self.params
        yaw_c = (np.arange(acc.shape[0]) + 0.5) * yaw_bin - np.pi
        t_c = (np.arange(acc.shape[1]) + 0.5) * t_bin - t_half
        off_yaw = np.abs((yaw_c - yaw0 + np.pi) % (2 * np.pi) - np.pi) > np.radians(self.max_deg) + yaw_bin
        acc[off_yaw] = 0.0
        acc[:, np.abs(t_c - tx0) > self.max_m + t_bin] = 0.0
        acc[:, :, np.abs(t_c - ty0) > self.max_m + t_bin] = 0.0


@dataclass
class SearchMemo:
    """What one alignment's searches of the same two frames share: the first search fills it, a second (inside a
    prior's window, pipeline.Aligner._within_prior) reads it. Lives for one alignment: nothing here outlives it."""

    candidates: tuple[np.ndarray, np.ndarray] | None = None  # topk_candidates' (rows, cand)
    proposed: list[Hypothesis] | None = None  # the boxes' poses, before any window
    votes: dict[int, np.ndarray] = field(default_factory=dict)  # candidates per keypoint -> unmasked accumulator


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
    q, k = cand.shape
    if q < 2:
        return []
    d_e, phi = ego_pairs(np.ascontiguousarray(kp_ego, np.float64)) if pairs is None else pairs
    yaw_bin = np.radians(cfg.vote_yaw_deg)
    n_yaw = int(np.ceil(2 * np.pi / yaw_bin))
    yaw_bin = 2 * np.pi / n_yaw
    n_t = int(np.ceil(2 * t_half / cfg.vote_t_m))
    acc = None if votes is None else votes.get(k)
    if acc is None:
        acc = vote(
            np.ascontiguousarray(kp_peer, np.float64),
            np.ascontiguousarray(kp_ego, np.float64),
            np.ascontiguousarray(cand, np.int64),
            (d_e, phi),
            cfg.min_sample_dist_m,
            cfg.length_tolerance_m,
            yaw_bin,
            cfg.vote_t_m,
            t_half,
            n_yaw,
            n_t,
            cfg.threads,
        )
        if votes is not None:
            votes[k] = acc
    if window is not None:
        acc = acc.copy() if votes is not None else acc
        window.mask_accumulator(acc, yaw_bin, cfg.vote_t_m, t_half)
    flat = acc.ravel()
    idx = _cells_above(flat, cfg.min_votes)
    if len(idx) == 0:
        return []
    idx = idx[np.argsort(-flat[idx], kind="stable")[: cfg.peaks]]
    iy, ix, iz = np.unravel_index(idx, acc.shape)
    yaw = (iy + 0.5) * yaw_bin - np.pi  # cell centres, all in (-pi, pi)
    tx, ty = (ix + 0.5) * cfg.vote_t_m - t_half, (iz + 0.5) * cfg.vote_t_m - t_half
    # The cell centres are coarse: score them all with a wide threshold (compiled, no (peaks x M) arrays), refit
    # the strongest.
    kp_src = np.ascontiguousarray(kp_peer, np.float64)
    kp_dst = np.ascontiguousarray(kp_ego, np.float64)
    cand_c = np.ascontiguousarray(cand, np.int64)
    n_wide = _peak_support(kp_src, kp_dst, cand_c, yaw, tx, ty, (2 * threshold) ** 2)
    thr2 = threshold * threshold
    out: list[Hypothesis] = []
    found = np.empty((cfg.max_hypotheses, 3))  # se2_params of out's poses
    attempts = 0
    for h in np.argsort(-n_wide, kind="stable"):
        if (
            len(out) >= cfg.max_hypotheses
            or n_wide[h] < cfg.min_hypothesis_inliers
            or attempts >= cfg.max_refit_attempts
        ):
            break
        if not pose_is_distinct(
            found[: len(out)],
            (yaw[h], tx[h], ty[h]),
            cfg.distinct_m + cfg.vote_t_m,
            cfg.distinct_deg + cfg.vote_yaw_deg,
        ):
            continue  # a neighbouring cell of a pose already found
        attempts += 1
        y, x, z, n, mask = _refit(
            kp_src, kp_dst, cand_c, float(yaw[h]), float(tx[h]), float(ty[h]), (2 * threshold) ** 2, thr2, cfg.refits
        )
        T = se2(y, x, z)
        params = se2_params(T)
        if window is not None and not window.holds(T):
            continue
        if n < cfg.min_hypothesis_inliers or not pose_is_distinct(
            found[: len(out)], params, cfg.distinct_m, cfg.distinct_deg
        ):
            continue
        found[len(out)] = params
        out.append(Hypothesis(T=T, inliers=n, votes=float(flat[idx[h]]), inlier_mask=mask))
    out.sort(key=lambda h: -h.inliers)
    return out


# ---- 2b. hypotheses from the boxes both cars detected (bb_align.engine.box_poses) -------------------------------


def box_hypotheses(boxes_ego: np.ndarray, boxes_peer: np.ndarray, cfg: AcquireConfig) -> list[Hypothesis]:
    """The poses the boxes both cars detected propose (``box_poses``), as hypotheses (votes = paired boxes)."""
    return [
        Hypothesis(T=b.T, inliers=0, votes=float(b.pairs), source="boxes")
        for b in box_poses(boxes_ego, boxes_peer, cfg)
    ]


def _with_keypoint_inliers(
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
        if _distinct(h.T, have, cfg.distinct_m, cfg.distinct_deg):
            mask, n = _inliers(h.T, src, dst, k, thr * thr)
            out.append(Hypothesis(T=h.T.copy(), inliers=n, votes=h.votes, inlier_mask=mask, source=h.source))
    return out


# ---- 3. dense verification -------------------------------------------------------------------------------------


def covisible_map(ego_image: np.ndarray, min_value: int, radius_px: int) -> np.ndarray:
    """uint8 mask of the ego image's pixels within ``radius_px`` of a lit one: where the ego car saw structure."""
    lit = (ego_image >= min_value).astype(np.uint8)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
    return cv2.dilate(lit, k)


def covisible_fraction(mask: np.ndarray, cloud: BevCloud, pts: np.ndarray, T: np.ndarray) -> float:
    """Fraction of peer points that land, under T, where the ego car saw structure (its dilated lit pixels)."""
    if len(pts) == 0:
        return 0.0
    p = np.ascontiguousarray(pts @ T[:2, :2].T + T[:2, 2])
    return float(covisible_share(mask, p, cloud.range_m, cloud.resolution_m))


def coarse_verification(
    cloud: BevCloud,
    covis: np.ndarray,
    pts: np.ndarray,
    Ts: list[np.ndarray],
    coarse: RefineConfig,
    final_gate: float,
    threads: int = 1,
    normals: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each pose of ``Ts`` refined (refine_icp with ``coarse``; ``normals``: the peer points' normals, see
    refine_icp) and scored at it (overlap_fitness within ``final_gate``, covisible_fraction), in one compiled call
    per group of poses (``threads`` groups in parallel; the poses are independent): (poses (H, 3, 3), fitness,
    rmse_m, covisible)."""
    T = np.ascontiguousarray(np.array(Ts, dtype=np.float64).reshape(-1, 3, 3))
    p = np.ascontiguousarray(pts, dtype=np.float64)
    pn, min_cos = facing_args(p, normals, coarse.facing_min_cos)
    fixed = (cloud.index, cloud.clearance, cloud.xy, cloud.normals, cloud.range_m, cloud.resolution_m, covis, p, pn)
    tail = (*icp_params(coarse), min_cos, coarse.max_correction_m, coarse.max_correction_deg, final_gate)

    def run(group: np.ndarray):
        return coarse_verification_loop(*fixed, np.ascontiguousarray(group), *tail)

    parts = run_parts(run, contiguous(T, threads) or [T])
    return tuple(np.concatenate([part[m] for part in parts]) for m in range(4))  # type: ignore[return-value]


@dataclass
class Acquisition:
    best: Hypothesis | None
    runner_up: Hypothesis | None
    hypotheses: list[Hypothesis]
    candidates: int
    margin: float  # best score / runner-up score (inf without a runner-up)
    timings_ms: dict[str, float] = field(default_factory=dict)

    def diagnostics(self) -> dict:
        def h(x: Hypothesis | None):
            if x is None:
                return None
            yaw, tx, ty = se2_params(x.T)
            return {
                "yaw_deg": float(np.degrees(yaw)),
                "tx": float(tx),
                "ty": float(ty),
                "inliers": x.inliers,
                "fitness": x.fitness,
                "covisible": x.covisible,
                "relative_fitness": x.relative_fitness,
                "refined": x.refined,
                "source": x.source,
                "box_pairs": x.box_pairs,
                "box_score": x.box_score,
                "conflict": x.conflict,
            }

        return {
            "candidates": self.candidates,
            "hypotheses": len(self.hypotheses),
            "margin": self.margin,
            "best": h(self.best),
            "runner_up": h(self.runner_up),
            "all": [h(x) for x in self.hypotheses],
        }


def dense_score(h: Hypothesis, cfg: AcquireConfig) -> float:
    """The images' evidence for a hypothesis: dense overlap (optionally normalised by the co-visible fraction)."""
    if cfg.score == "fitness":
        return h.fitness
    return h.relative_fitness * h.fitness**0.5 if cfg.score == "blend" else h.relative_fitness


def score(h: Hypothesis, cfg: AcquireConfig) -> float:
    """What ranks verified hypotheses: the dense score plus ``box_weight`` per peer box landing on an ego box."""
    return dense_score(h, cfg) + cfg.box_weight * h.box_pairs


def verify(
    hyps: list[Hypothesis],
    ego_cloud: BevCloud,
    covis: np.ndarray,
    coarse_sample: tuple[np.ndarray, np.ndarray | None],
    full_sample: tuple[np.ndarray, np.ndarray | None],
    config: AlignConfig,
    coarse: RefineConfig,
    boxes: tuple[BoxSet, BoxSet] | None = None,
    window: PriorWindow | None = None,
) -> None:
    """Coarse dense refinement (``coarse``, on ``coarse_sample``: peer points and their normals, or None) + score
    for every hypothesis, then a full refinement of the finalists on ``full_sample`` (in place). ``boxes``: the
    (ego, peer) boxes, paired per pose. ``window``: a hypothesis the refinement carries out of the prior's window is
    dropped (the list may end empty)."""
    a, rf = config.acquire, config.refine
    final_gate = rf.gates_m[-1]
    ego_boxes, peer_boxes = boxes if boxes is not None else (BoxSet.of(np.zeros((0, 7))),) * 2
    size_ok = same_size(peer_boxes, ego_boxes, a)  # the boxes' footprint agreement, the same under every pose
    full_pts, full_normals = full_sample
    Ts, fitness, rmse, covisible = coarse_verification(
        ego_cloud, covis, coarse_sample[0], [h.T for h in hyps], coarse, final_gate, a.threads, coarse_sample[1]
    )
    for n, h in enumerate(hyps):
        h.T, h.fitness, h.rmse_m, h.covisible = Ts[n], float(fitness[n]), float(rmse[n]), float(covisible[n])
        h.box_pairs, h.box_score = box_agreement(h.T, peer_boxes, ego_boxes, a, size_ok)
    if window is not None:
        hyps[:] = [h for h in hyps if window.holds(h.T)]
    hyps.sort(key=lambda x: -score(x, a))
    finalists = hyps[: a.finalists]
    refined = run_parts(
        lambda hs: [refine_icp(ego_cloud, full_pts, h.T, rf, full_normals) for h in hs],
        contiguous(finalists, a.threads),
    )
    for h, ref in zip(finalists, [r for part in refined for r in part], strict=True):
        _take_refinement(h, ref, ego_cloud, covis, full_pts, (ego_boxes, peer_boxes), a, size_ok)
    if window is not None:
        hyps[:] = [h for h in hyps if not h.refined or window.holds(h.T)]
    finals = sorted([h for h in hyps if h.refined], key=lambda x: -score(x, a))
    hyps[: len(finals)] = finals
    if not hyps:
        return
    _merge_neighbours(hyps, ego_cloud, full_sample, config)


def _take_refinement(h: Hypothesis, ref, ego_cloud, covis, pts, boxes, a: AcquireConfig, size_ok) -> None:
    """A hypothesis refined fully (``ref``: refine_icp's result on ``pts``): its pose, overlap, co-visible share and
    the (ego, peer) ``boxes`` paired under it."""
    h.T, h.fitness, h.rmse_m, h.refined = ref.T, ref.fitness, ref.rmse_m, True
    h.covisible = covisible_fraction(covis, ego_cloud, pts, h.T)
    h.box_pairs, h.box_score = box_agreement(h.T, boxes[1], boxes[0], a, size_ok)


def _merge_neighbours(
    hyps: list[Hypothesis], ego_cloud: BevCloud, full_sample: tuple[np.ndarray, np.ndarray | None], config: AlignConfig
) -> None:
    """A rival close to the best (within merge_within_m and merge_within_deg) may be the same basin, only not yet
    converged by the coarse stage. Refine it fully: if it meets the best it is the same pose and no longer a rival;
    if not, it keeps its coarse values (the margin's calibration). Rivals only ever go away, so margins only grow
    when a 'rival' was the best pose itself."""
    a = config.acquire
    for _ in range(a.merge_checks):
        best, rivals = hyps[0], _rivals(hyps, a)
        rival = max(rivals, key=lambda h: dense_score(h, a), default=None)  # the one the margin is taken over
        if rival is None or rival.refined or _distinct(rival.T, [best], a.merge_within_m, a.merge_within_deg):
            return
        T = refine_icp(ego_cloud, full_sample[0], rival.T, config.refine, full_sample[1]).T
        if _distinct(T, [best], a.distinct_m, a.distinct_deg):
            return
        rival.T = T  # the same pose as the best: _rivals skips it from now on


def _conflict_note(value: float) -> str:
    return f"free-space conflict {value:.2f}: structure where the other car saw through"


def _margin(hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float = 1.0) -> float:
    """The images' margin: the first hypothesis's dense score over the best dense score of any distinct one
    (floored at cfg.runner_up_floor; the floor alone without one). The boxes, which helped rank, are left out: they
    are judged on their own (``_box_confirmed``), not counted twice. ``max_conflict``: see ``_rivals``."""
    best_rival = max((dense_score(h, cfg) for h in _rivals(hyps, cfg, max_conflict)), default=0.0)
    return float(dense_score(hyps[0], cfg) / max(best_rival, cfg.runner_up_floor))


def _box_confirmed(hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float = 1.0) -> bool:
    """The boxes single out the best pose (``hyps[0]``) among its rivals (``_rivals``, ``max_conflict``)."""
    others = max((h.box_pairs for h in _rivals(hyps, cfg, max_conflict)), default=0)
    return _boxes_single_out(hyps[0].box_pairs, others, cfg)


def _box_contradicted(
    hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float, reach: tuple[float, float]
) -> Hypothesis | None:
    """The rival (``_rivals``) the boxes single out over the best pose, if any: the images and the boxes then vouch
    for two different poses, and neither is trusted. Only a rival beyond stage 2's ``reach`` (m, deg: a nearer one is
    stage 2's to judge, box against image) whose dense overlap reaches ``runner_up_floor`` counts: where the two
    images share nothing, boxes that pair say nothing about the scene."""
    seen = [
        h
        for h in _rivals(hyps, cfg, max_conflict)
        if h.fitness >= cfg.runner_up_floor and _distinct(h.T, [hyps[0]], *reach)
    ]
    rival = max(seen, key=lambda h: h.box_pairs, default=None)
    return rival if rival is not None and _boxes_single_out(rival.box_pairs, hyps[0].box_pairs, cfg) else None


def _boxes_single_out(pairs: int, others: int, cfg: AcquireConfig) -> bool:
    """``pairs`` peer boxes on ego boxes under one pose single it out over ``others`` under any other: at least
    ``box_confirm_pairs``, and at least ``box_confirm_margin`` more and ``box_confirm_ratio`` times as many (a row of
    parked cars seen from its two ends pairs many boxes at a wrong pose too)."""
    if cfg.box_confirm_pairs == 0 or pairs < cfg.box_confirm_pairs:
        return False
    return pairs - others >= cfg.box_confirm_margin and pairs >= cfg.box_confirm_ratio * others


def _rivals(hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float = 1.0) -> list[Hypothesis]:
    """The hypotheses distinct from the first, in order (after refinement two may have met); those whose free-space
    conflict exceeds ``max_conflict`` are no rivals (a pose the two LiDARs' free space rules out)."""
    return [
        h
        for h in hyps[1:]
        if h.conflict <= max_conflict and _distinct(h.T, [hyps[0]], cfg.distinct_m, cfg.distinct_deg)
    ]


def runner_up_of(hyps: list[Hypothesis], cfg: AcquireConfig, max_conflict: float = 1.0) -> Hypothesis | None:
    """The best-scoring hypothesis distinct from the first (and within ``max_conflict``, see ``_rivals``)."""
    return next(iter(_rivals(hyps, cfg, max_conflict)), None)


# ---- pipeline steps ------------------------------------------------------------------------------------------


def pose_uncertainty(
    ego_cloud: BevCloud,
    peer_sample: tuple[np.ndarray, np.ndarray | None],
    T: np.ndarray,
    gate: float,
    cfg: CovarianceConfig,
    min_cos: float = -1.0,
) -> np.ndarray:
    """3x3 covariance of (yaw, tx, ty) of the pose T (3x3 ego <- peer), from the refinement's normal equations
    (``peer_sample``: the peer points and their normals; ``min_cos``: the refinement's facing test)."""
    pts, normals = peer_sample
    cov_left = pose_covariance(ego_cloud, pts, T, gate, cfg.inflation, cfg.min_residual_sigma_m, normals, min_cos)
    return params_covariance(cov_left, T)


class Acquirer:
    """Stage 1 in multi mode as a pipeline step, built once from the config: candidates, hypotheses by voting,
    dense verification, decision by margin and relative fitness. ``__call__`` fills the result (T_bv, inliers,
    fitness, acquisition diagnostics) and returns (FailureReason or None, the refinement's peer points and their
    normals)."""

    def __init__(self, config: AlignConfig):
        if not config.refine.enabled:
            raise ValueError(
                "acquire.mode='multi' verifies hypotheses with the dense refinement: refine.enabled must be True"
            )
        self.config = config
        a, rf = config.acquire, config.refine
        self.coarse = rf.model_copy(update={"gates_m": a.coarse_gates_m, "iters_per_gate": a.coarse_iters_per_gate})

    def __call__(
        self,
        ego,
        peer,
        result: AlignResult,
        timed,
        window: PriorWindow | None = None,
        memo: SearchMemo | None = None,
    ) -> tuple[FailureReason | None, tuple[np.ndarray, np.ndarray] | None]:
        """``window``: only hypotheses inside it are formed, verified and counted as rivals, and its prior pose is
        verified as one more hypothesis (config.prior.verify_prior_pose). ``memo``: what an earlier search of the
        same two frames found (read) or an empty one (filled)."""
        cfg = self.config
        a, rf = cfg.acquire, cfg.refine
        keep_votes = memo is not None  # a lone search does not hold its first pass's votes (5 MB) through the second
        memo = memo or SearchMemo()
        with timed("matching"):
            if memo.candidates is None:
                desc_ref = ego.reference_descriptors(cfg.features, cfg.mim.n_orient)
                memo.candidates = topk_candidates(
                    peer.descriptors, desc_ref, len(ego.descriptors), a.top_k, threads=cfg.match.threads
                )
            rows, cand = memo.candidates
        result.matches_bv = int(cand.size)
        if len(rows) < 2:
            return FailureReason.too_few_matches, None
        t_half = 1.5 * max(ego.bev.range_m, peer.bev.range_m)
        kp = peer.keypoints_xy[rows]
        ego_cloud = ego.cloud(rf)
        covis = self._covisible(ego)

        # The peer's pixels, sampled once (seeded) for every verification of this frame.
        coarse_pts, full_pts = bev_samples(
            peer.bev, rf.min_pixel_value, [a.coarse_points, rf.max_peer_points], cfg.seed
        )
        coarse_sample, full_sample = ((p, peer_normals(peer.bev, p, rf)) for p in (coarse_pts, full_pts))

        with timed("hypotheses"):
            if memo.proposed is None:
                memo.proposed = box_hypotheses(ego.boxes, peer.boxes, a)  # poses not from the keypoint vote
            proposed = memo.proposed
            if window is not None:
                proposed = [h for h in proposed if window.holds(h.T)]
                if cfg.prior.verify_prior_pose:
                    proposed.append(Hypothesis(T=window.T.copy(), inliers=0, source="prior"))
        boxes = (BoxSet.of(ego.boxes), BoxSet.of(peer.boxes))

        def run(c: np.ndarray) -> tuple[list[Hypothesis], float]:
            with timed("hypotheses"):
                pairs = ego.cached("ego_pairs", lambda: ego_pairs(np.ascontiguousarray(ego.keypoints_xy, np.float64)))
                hs = pose_hypotheses(
                    kp,
                    ego.keypoints_xy,
                    c,
                    a,
                    cfg.ransac.inlier_threshold_m,
                    t_half,
                    pairs,
                    window,
                    memo.votes if keep_votes else None,
                )
                hs += _with_keypoint_inliers(proposed, hs, kp, ego.keypoints_xy, c, a, cfg.ransac.inlier_threshold_m)
            if not hs:
                return hs, 0.0
            with timed("verify"):
                verify(hs, ego_cloud, covis, coarse_sample, full_sample, cfg, self.coarse, boxes, window)
            return hs, (_margin(hs, a) if hs else 0.0)

        hyps: list[Hypothesis] = []
        used = cand
        if 0 < a.first_k < cand.shape[1]:
            # Cheap first: the few nearest candidates only (a close pair needs no more); kept only when its
            # evidence is far above the success threshold, else the full top-k search runs.
            used = np.ascontiguousarray(cand[:, : a.first_k])
            hyps, margin = run(used)
            if not hyps or margin * hyps[0].relative_fitness < a.first_pass_evidence:
                hyps = []
            else:
                result.notes.append(f"acquired on the first {a.first_k} candidates per keypoint")
        if not hyps:
            used = cand
            hyps, margin = run(cand)
        if not hyps:
            return FailureReason.too_few_inliers_bv, None
        fs = cfg.free_space
        bound = fs.rival_conflict if fs.enabled else 1.0  # rivals the free space rules out do not count
        gave_way = False  # the best scorers were ruled out by the free space: the one chosen must be clear of it
        if fs.enabled:
            with timed("free_space"):
                self._conflicts(ego, peer, hyps)
                bound = self._rival_bound(hyps, bound)
                if fs.ruled_out_first and hyps[0].conflict > bound:
                    kept = self._without_ruled_out(ego, peer, hyps, ego_cloud, covis, full_sample, boxes, bound)
                    if kept:  # else the ruled-out best stands, and is refused below
                        result.notes.append(
                            f"the free space rules out {len(hyps) - len(kept)} hypotheses (best conflict "
                            f"{hyps[0].conflict:.2f}); the best of the others is judged"
                        )
                        hyps, gave_way = kept, True
            margin = _margin(hyps, a, bound)
        best = hyps[0]
        result.acquisition = Acquisition(best, runner_up_of(hyps, a, bound), hyps, int(cand.size), margin).diagnostics()
        result.acquisition["gave_way"] = gave_way
        result.T_bv, result.inliers_bv, result.refine_fitness = best.T, best.inliers, best.fitness
        result.ambiguity_bv = 1.0 / max(1.0, margin)
        mask = best.inlier_mask
        result.inlier_xy_peer = np.repeat(peer.keypoints_xy[rows], used.shape[1], axis=0)[mask]
        result.inlier_xy_ego = ego.keypoints_xy[used.ravel()][mask]
        dense_ok = margin >= a.min_margin and margin * best.relative_fitness >= a.min_evidence
        weighed = window is not None and cfg.landscape.enabled
        if not dense_ok and weighed:
            # Inside a prior's window the rivals are weighed in the answer's covariance instead (pipeline._judge): a
            # street's repeated structure then widens the uncertainty along it rather than refusing the pose.
            result.notes.append(f"margin {margin:.2f} inside the prior's window: the rivals are weighed instead")
        elif not dense_ok and gave_way:
            # Chosen because better-scoring poses gave way: the images misled once already, and the boxes pair at
            # many poses along rows of parked cars, so the images' own evidence must carry it.
            result.notes.append("chosen after better-scoring poses gave way: box evidence alone does not carry it")
            return FailureReason.ambiguous_bv, full_sample
        elif not dense_ok and not _box_confirmed(hyps, a, bound):
            return FailureReason.ambiguous_bv, full_sample
        reach = (cfg.box.max_correction_m, cfg.box.max_correction_deg)
        if (rival := _box_contradicted(hyps, a, bound, reach)) is not None:
            result.notes.append(
                f"the boxes vouch for another pose: {rival.box_pairs} cars on cars, {best.box_pairs} here"
            )
            return FailureReason.ambiguous_bv, full_sample
        if not dense_ok and not weighed:
            result.notes.append(f"acquired on box evidence: {best.box_pairs} cars on cars, distinct poses fewer")
        if best.fitness < a.min_fitness or best.relative_fitness < a.min_relative_fitness:
            return FailureReason.inconsistent_overlap, full_sample
        if fs.enabled and best.conflict > (fs.gave_way_max_conflict if gave_way else fs.max_conflict):
            result.notes.append(_conflict_note(best.conflict))
            return FailureReason.free_space_conflict, full_sample
        return None, full_sample

    def _rival_bound(self, hyps: list[Hypothesis], bound: float) -> float:
        """The conflict above which a hypothesis is ruled out: ``bound`` (free_space.rival_conflict), or the lower
        free_space.alias_conflict when the best is above it and a distinct hypothesis with some overlap
        (acquire.runner_up_floor) is clear of the free space (gave_way_max_conflict): the two LiDARs' free space
        then sets the two apart (on real streets an overlay of the two cars' near fields, 0.05-0.15, against the
        truth's at most 0.03)."""
        fs, a = self.config.free_space, self.config.acquire
        if fs.alias_conflict is None or hyps[0].conflict <= fs.alias_conflict:
            return bound
        clean = any(
            h.conflict <= min(fs.gave_way_max_conflict, fs.alias_conflict)
            and h.fitness >= a.runner_up_floor
            and _distinct(h.T, [hyps[0]], a.distinct_m, a.distinct_deg)
            for h in hyps[1:]
        )
        return min(bound, fs.alias_conflict) if clean else bound

    def _covisible(self, frame) -> np.ndarray:
        """The frame's co-visibility mask (covisible_map within acquire.covisible_m), built once per frame."""
        a, mv = self.config.acquire, self.config.refine.min_pixel_value
        return frame.cached(
            ("covisible", a.covisible_m, mv),
            lambda: covisible_map(frame.bev.image, mv, max(1, int(round(a.covisible_m / frame.bev.resolution_m)))),
        )

    def _without_ruled_out(self, ego, peer, hyps, ego_cloud, covis, full_sample, boxes, bound) -> list[Hypothesis]:
        """The hypotheses the free space does not rule out (conflict <= ``bound``), best first; the new best is
        refined fully (as verify's finalists are) and its conflict measured again at the refined pose, until the first
        is refined and not ruled out (at most ``acquire.finalists`` such refinements: then none is kept)."""
        cfg, a = self.config, self.config.acquire
        size_ok = same_size(boxes[1], boxes[0], a)
        kept = [h for h in hyps if h.conflict <= bound]
        for _ in range(a.finalists):
            if not kept or kept[0].refined:
                return kept  # refined hypotheses first, as verify orders them
            h = kept[0]
            ref = refine_icp(ego_cloud, full_sample[0], h.T, cfg.refine, full_sample[1])
            _take_refinement(h, ref, ego_cloud, covis, full_sample[0], boxes, a, size_ok)
            self._conflicts(ego, peer, [h])
            if h.conflict > bound:
                kept.pop(0)  # refined into a pose the free space rules out
        return kept if kept and kept[0].refined else []

    def _conflicts(self, ego, peer, hyps: list[Hypothesis]) -> None:
        """The free-space conflict of every hypothesis: the peer's tall structure in the ego car's free space under T,
        and the ego's in the peer's under T^-1; the larger (engine.freespace). Each frame's maps are built once;
        "near structure" is the co-visibility mask (acquire.covisible_m)."""
        fs, mv, seed = self.config.free_space, self.config.refine.min_pixel_value, self.config.seed

        def maps(frame):
            def build():
                near = self._covisible(frame)
                return free_space_map(frame.bev, mv, near, fs), near, tall_points(frame.bev, fs, seed)

            return frame.cached(("free_space", fs, mv, self.config.acquire.covisible_m), build)

        (ego_free, ego_near, ego_tall), (peer_free, peer_near, peer_tall) = maps(ego), maps(peer)
        for h in hyps:
            h.conflict = max(
                conflict(ego_free, ego_near, ego.bev, peer_tall, h.T),
                conflict(peer_free, peer_near, peer.bev, ego_tall, np.linalg.inv(h.T)),
            )
