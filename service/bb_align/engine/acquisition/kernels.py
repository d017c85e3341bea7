"""The acquisition's compiled loops (numba): the pose vote, the peaks' support and refit, the accumulator scan.

They take their inputs as small named tuples (``Keypoints``, ``VoteGrid``) rather than long positional lists; numba
compiles a named tuple's fields as plain arguments, so the arithmetic (and its result) is that of the loops written
out. Here, apart from the Python around them: numba's on-disk cache is invalidated by its own file's changes only.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit


class Keypoints(NamedTuple):
    """The candidate correspondences the loops read: peer keypoints, ego keypoints and the candidate table."""

    src: np.ndarray  # (Q, 2) float64: the peer keypoints with candidates (metres, peer sensor frame)
    dst: np.ndarray  # (N, 2) float64: the ego keypoints (metres, ego sensor frame)
    cand: np.ndarray  # (Q, k) int64: row q lists the ego keypoints that may be peer keypoint q's partner


class VoteGrid(NamedTuple):
    """Which candidate pairs vote and the (yaw, tx, ty) accumulator they vote in."""

    min_d: float  # peer pairs shorter than this (metres) do not vote
    len_tol: float  # a candidate pair votes only if its length agrees with the peer pair's within this (metres)
    yaw_bin: float  # yaw cell, radians
    t_bin: float  # translation cell, metres
    t_half: float  # the accumulator spans [-t_half, t_half) in tx and ty, metres


def keypoints(kp_src: np.ndarray, kp_dst: np.ndarray, cand: np.ndarray) -> Keypoints:
    """The loops' contiguous float64 / int64 copies (no copy when already so)."""
    return Keypoints(
        np.ascontiguousarray(kp_src, np.float64),
        np.ascontiguousarray(kp_dst, np.float64),
        np.ascontiguousarray(cand, np.int64),
    )


@njit(cache=True, nogil=True)
def scatter(acc, cell, frac, n, n_t, y_lo, y_hi):
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
def cast(kps, pairs, grid, a, b, a_end, cell, frac):
    """The votes of the peer pairs (a, b), a < b, from the given (a, b) on, in order, while a < ``a_end`` and the
    buffers (``cell``, ``frac``: see scatter) have room for a whole pair's votes. Every pair of peer keypoints at
    least ``grid.min_d`` apart, with candidates (i, j) among their ego candidates ``kps.cand`` (Q, k) whose distance
    agrees within ``grid.len_tol``, votes for the rigid pose it implies. ``pairs``: ``ego_pairs(kps.dst)``; the
    pose's yaw is the ego pair's direction minus the peer pair's (one arctan2 per peer pair, not per vote).
    Returns (votes written, the (a, b) to resume from)."""
    kp_src, kp_dst, cand = kps
    d_e, phi = pairs
    min_d, len_tol, yaw_bin, t_bin, t_half = grid
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


@njit(cache=True, nogil=True)
def peak_support(kps, yaw, tx, ty, thr2):
    """For each pose (yaw[h], tx[h], ty[h]): the number of peer keypoints with a candidate within sqrt(thr2)."""
    kp_src, kp_dst, cand = kps
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
def _inlier_rows(kps, yaw, tx, ty, thr):
    """The candidate rows (over cand.ravel()) within sqrt(thr) of their peer keypoint under the pose, and the number
    of distinct peer keypoints with one."""
    kp_src, kp_dst, cand = kps
    q, k = cand.shape
    c, s = np.cos(yaw), np.sin(yaw)
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
    return new, n_new


@njit(cache=True, nogil=True)
def _kabsch(kps, mask):
    """The rigid least-squares pose (2-D Kabsch) of the candidate rows in ``mask``: (ok, yaw, tx, ty); ok False
    with fewer than two rows."""
    kp_src, kp_dst, cand = kps
    k = cand.shape[1]
    m = 0
    msx = msy = mdx = mdy = 0.0
    for r in range(len(mask)):
        if mask[r]:
            a = r // k
            j = cand[a, r % k]
            msx += kp_src[a, 0]
            msy += kp_src[a, 1]
            mdx += kp_dst[j, 0]
            mdy += kp_dst[j, 1]
            m += 1
    if m < 2:
        return False, 0.0, 0.0, 0.0
    msx /= m
    msy /= m
    mdx /= m
    mdy /= m
    sxx = sxy = 0.0
    for r in range(len(mask)):
        if mask[r]:
            a = r // k
            j = cand[a, r % k]
            ax, ay = kp_src[a, 0] - msx, kp_src[a, 1] - msy
            bx, by = kp_dst[j, 0] - mdx, kp_dst[j, 1] - mdy
            sxx += ax * bx + ay * by
            sxy += ax * by - ay * bx
    yaw = np.arctan2(sxy, sxx)
    c, s = np.cos(yaw), np.sin(yaw)
    return True, yaw, mdx - (c * msx - s * msy), mdy - (s * msx + c * msy)


@njit(cache=True, nogil=True)
def refit(kps, yaw, tx, ty, thr2_wide, thr2, refits):
    """From a coarse pose: candidate inliers within sqrt(thr2_wide), then up to ``refits`` rigid least-squares
    refits (2-D Kabsch) on the inliers within sqrt(thr2), stopping when the inlier set no longer changes.
    Returns (yaw, tx, ty, distinct peer keypoints with an inlier, inlier mask over kps.cand.ravel())."""
    q, k = kps.cand.shape
    mask = np.zeros(q * k, np.bool_)
    n = 0
    for it in range(refits + 1):
        new, n_new = _inlier_rows(kps, yaw, tx, ty, thr2_wide if it == 0 else thr2)
        if it > 0 and n_new < 2:
            break
        same = it > 0 and np.array_equal(new, mask)
        mask, n = new, n_new
        if same or it == refits:
            break
        ok, y, x, z = _kabsch(kps, mask)
        if not ok:
            break
        yaw, tx, ty = y, x, z
    return yaw, tx, ty, n, mask


@njit(cache=True, nogil=True)
def cells_above(flat, floor):
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
