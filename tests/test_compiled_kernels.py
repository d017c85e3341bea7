"""The engine's compiled hot loops against plain Python/numpy versions of the same math (the independent truth):
the acquisition's pose vote, the refinement's nearest-pixel look-up."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from bb_align.engine.acquire import _VOTE_BUFFER, _vote, ego_pairs
from bb_align.engine.bev import make_bev
from bb_align.engine.config import BevConfig
from bb_align.engine.geometry import se2
from bb_align.engine.refine import _clearance, bev_cloud
from synthetic import synthetic_world, view_from


def _vote_reference(kp_src, kp_dst, cand, min_d, len_tol, yaw_bin, t_bin, t_half, n_yaw, n_t):
    """The vote as first written: the pose of every agreeing candidate pair from arctan2 of its two vectors."""
    acc = np.zeros((n_yaw, n_t, n_t))
    q, k = cand.shape
    for a in range(q):
        for b in range(a + 1, q):
            sx, sy = kp_src[b] - kp_src[a]
            ds = math.hypot(sx, sy)
            if ds < min_d:
                continue
            msx, msy = 0.5 * (kp_src[a] + kp_src[b])
            for i in cand[a]:
                for j in cand[b]:
                    dx, dy = kp_dst[j] - kp_dst[i]
                    if i == j or abs(ds - math.hypot(dx, dy)) > len_tol:
                        continue
                    cr, dt = sx * dy - sy * dx, sx * dx + sy * dy
                    th, nrm = math.atan2(cr, dt), math.hypot(cr, dt)
                    c, s = dt / nrm, cr / nrm
                    mdx, mdy = 0.5 * (kp_dst[i] + kp_dst[j])
                    f = ((th + np.pi) / yaw_bin - 0.5, (mdx - (c * msx - s * msy) + t_half) / t_bin - 0.5)
                    f += ((mdy - (s * msx + c * msy) + t_half) / t_bin - 0.5,)
                    lo = [math.floor(x) for x in f]
                    for e in np.ndindex(2, 2, 2):
                        yy, xx, zz = (lo[0] + e[0]) % n_yaw, lo[1] + e[1], lo[2] + e[2]
                        if 0 <= xx < n_t and 0 <= zz < n_t:
                            w = [(f[m] - lo[m]) if e[m] else 1.0 - (f[m] - lo[m]) for m in range(3)]
                            acc[yy, xx, zz] += w[0] * w[1] * w[2]
    return acc


def test_vote_equals_the_reference_vote():
    """A true pose hidden among random candidates, enough votes to fill the vote buffer several times."""
    rng = np.random.default_rng(3)
    T = se2(np.radians(-71.0), 14.0, 9.0)
    kp_src = rng.uniform(-40, 40, (70, 2))
    kp_dst = np.concatenate(
        [kp_src @ T[:2, :2].T + T[:2, 2] + rng.normal(0, 0.3, (70, 2)), rng.uniform(-50, 50, (50, 2))]
    )
    cand = np.stack([np.arange(70)] + [rng.integers(0, 120, 70) for _ in range(3)], axis=1)
    cand[::7, 0] = rng.integers(0, 120, 10)  # some keypoints without their true partner
    yaw_bin, n_yaw = 2 * np.pi / 120, 120
    args = (3.0, 4.0, yaw_bin, 3.0, 75.0, n_yaw, 50)
    acc = _vote(kp_src, kp_dst, cand, *ego_pairs(kp_dst), *args)
    ref = _vote_reference(kp_src, kp_dst, cand, *args)
    assert ref.sum() > 2 * _VOTE_BUFFER
    np.testing.assert_allclose(acc, ref, rtol=1e-6, atol=1e-5)
    peak = np.unravel_index(np.argmax(acc), acc.shape)
    assert peak == np.unravel_index(np.argmax(ref), ref.shape)
    assert abs((peak[0] + 0.5) * yaw_bin - np.pi - np.radians(-71.0)) < 2 * yaw_bin


@pytest.mark.parametrize("gate", [0.3, 0.4, 1.0, 2.0, 5.0])
def test_grid_nearest_equals_brute_force_index_and_distance(gate):
    """The compiled look-up (clearance-narrowed scan) returns exactly the brute-force nearest: the same distance
    and, among equally near pixels (points on centres, midway between two, at a square's centre), the lowest
    index."""
    bev = make_bev(view_from(synthetic_world(seed=2)[0], np.eye(4)), BevConfig(range_m=30.0))
    cloud = bev_cloud(bev)
    rng = np.random.default_rng(int(gate * 10))
    xy, res = cloud.xy, cloud.resolution_m
    pick = rng.integers(len(xy), size=(4, 400))
    pts = np.concatenate(
        [
            xy[pick[0]] + rng.normal(0, gate, (400, 2)),
            xy[pick[1]],  # on a centre
            xy[pick[2]] + np.array([0.5 * res, 0.0]),  # midway to the next pixel (a tie when both are lit)
            xy[pick[3]] + np.array([0.5 * res, -0.5 * res]),  # a square's centre
            (xy[pick[0]] + xy[pick[1]]) / 2,
            rng.uniform(-30, 30, (600, 2)),
            rng.uniform(-32, 32, (300, 2)),  # some off the image
        ]
    )
    d, j = cloud.nearest(pts, gate)
    # The brute-force nearest: over the centres of the pixels within the gate's square (rows and columns within
    # gate / resolution of the point's, as the look-up rounds them), rounded like the look-up's (xy - p), strictly
    # inside the gate, the lowest index on ties.
    d2 = ((xy[None, :, 0] - pts[:, None, 0]) ** 2) + ((xy[None, :, 1] - pts[:, None, 1]) ** 2)
    rc = np.argwhere(cloud.index >= 0)  # the pixel of each cloud point (row-major, as the index numbers them)
    for axis in range(2):
        u = ((cloud.range_m - pts[:, axis]) / res - 0.5)[:, None]
        d2[(rc[None, :, axis] < np.ceil(u - gate / res)) | (rc[None, :, axis] > np.floor(u + gate / res))] = np.inf
    j_ref = np.argmin(d2, axis=1)
    found = d2[np.arange(len(pts)), j_ref] < gate * gate
    j_ref = np.where(found, j_ref, -1)
    assert found.sum() > 500 and (~found).sum() > 100
    ties = (d2 == d2.min(axis=1, keepdims=True)).sum(axis=1) > 1
    assert (ties & found).sum() > 20  # the tie rule is exercised
    np.testing.assert_array_equal(j, j_ref)
    np.testing.assert_array_equal(d[found], np.sqrt(d2[found, j_ref[found]]))
    assert np.all(np.isinf(d[~found]))


def test_clearance_is_the_exact_distance_to_the_nearest_lit_pixel():
    lit = np.random.default_rng(4).random((300, 240)) < 0.003
    np.testing.assert_allclose(_clearance(lit), distance_transform_edt(~lit), atol=1e-4)
    assert np.all(np.isinf(_clearance(np.zeros((5, 5), bool))))
