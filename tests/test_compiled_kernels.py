"""The engine's compiled hot loops against plain Python/numpy versions of the same math (the independent truth):
the acquisition's pose vote, the refinement's nearest-pixel look-up, the ICP iterations and the acquisition's coarse
verification."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from bb_align import AlignConfig
from bb_align.engine.acquisition.hypotheses import vote
from bb_align.engine.acquisition.kernels import VoteGrid, ego_pairs, keypoints
from bb_align.engine.acquisition.verification import (
    COARSE_POINTS,
    coarse_config,
    coarse_verification,
    covisible_fraction,
    covisible_map,
)
from bb_align.engine.bev import make_bev
from bb_align.engine.config import BevConfig
from bb_align.engine.geometry import distinct_pose, pose_is_distinct, se2, se2_params
from bb_align.engine.refine import (
    CONVERGED_M,
    CONVERGED_RAD,
    HUBER_FRACTION,
    POINT_WEIGHT,
    STEP_RELAXATION,
    Refinement,
    _normal_equations,
    bev_cloud,
    bev_points,
    clearance_map,
    overlap_fitness,
    peer_normals,
    refine_icp,
)
from synthetic import synthetic_world, view_from


def _covisible_numpy(mask: np.ndarray, cloud, pts: np.ndarray, T: np.ndarray) -> float:
    """The reference for verification.covisible_fraction, in numpy: the share of points on a pixel of the mask."""
    p = pts @ T[:2, :2].T + T[:2, 2]
    r = np.floor((cloud.range_m - p[:, 0]) / cloud.resolution_m).astype(np.int64)
    c = np.floor((cloud.range_m - p[:, 1]) / cloud.resolution_m).astype(np.int64)
    h, w = mask.shape
    ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    return float(mask[r[ok], c[ok]].sum() / len(pts))


def poses_near(params: np.ndarray, pose: tuple[float, float, float], dist_m: float, deg: float) -> np.ndarray:
    """The reference, in numpy: which rows of (N, 3) (yaw_rad, tx, ty) lie closer than ``dist_m`` and ``deg``."""
    p = np.asarray(params, dtype=float).reshape(-1, 3)
    dyaw = np.abs((p[:, 0] - pose[0] + np.pi) % (2 * np.pi) - np.pi)
    return (np.hypot(p[:, 1] - pose[1], p[:, 2] - pose[2]) < dist_m) & (np.degrees(dyaw) < deg)


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


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_vote_equals_the_reference_vote(threads):
    """A true pose hidden among random candidates; small vote buffers, so casting resumes many times. Any number
    of threads gives the same accumulator, bit for bit (each cell's votes are added in the order they were cast)."""
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
    kps, grid = keypoints(kp_src, kp_dst, cand), VoteGrid(*args[:5])
    acc = vote(kps, ego_pairs(kps.dst), grid, n_yaw, 50, threads=threads, chunk=500)
    ref = _vote_reference(kp_src, kp_dst, cand, *args)
    assert ref.sum() > 8 * 500
    np.testing.assert_allclose(acc, ref, rtol=1e-6, atol=1e-5)
    one_thread_one_buffer = vote(kps, ego_pairs(kps.dst), grid, n_yaw, 50, threads=1, chunk=10**6)
    assert np.array_equal(acc, one_thread_one_buffer)
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
    np.testing.assert_allclose(clearance_map(lit), distance_transform_edt(~lit), atol=1e-4)
    assert np.all(np.isinf(clearance_map(np.zeros((5, 5), bool))))


def _refine_icp_reference(ego, pts_peer, T_init, cfg, normals=None):
    """refine_icp as first written, its iterations in numpy (each step's look-up and normal equations compiled);
    the facing test in numpy: a pair whose ego normal and rotated peer normal disagree is no pair."""
    gates = cfg.gates_m
    T = np.array(T_init, dtype=float)
    prev = None
    none = np.zeros((len(pts_peer), 2))
    for gate in gates:
        for _ in range(cfg.iters_per_gate):
            p = pts_peer @ T[:2, :2].T + T[:2, 2]
            d, j = ego.nearest(p, gate)
            if normals is not None:
                alike = (ego.normals[j] * (normals @ T[:2, :2].T)).sum(axis=1) >= cfg.facing_min_cos
                j = np.where(alike, j, -1)
            if (j >= 0).sum() < cfg.min_points:
                T0 = np.array(T_init, dtype=float)
                return Refinement(T0, *overlap_fitness(ego, pts_peer, T0, gates[-1]), False)
            H, g, _ = _normal_equations(
                p, ego.xy, ego.normals, j, HUBER_FRACTION * gate, POINT_WEIGHT, none, 1.0, 0.0, -1.0
            )
            delta = np.linalg.solve(H, -g)
            if prev is not None and float(delta @ prev) > 0:
                delta = delta * STEP_RELAXATION
            prev = delta
            T = se2(delta[0], delta[1], delta[2]) @ T
            if np.abs(delta[0]) < CONVERGED_RAD and np.abs(delta[1:]).max() < CONVERGED_M:
                break
    yaw, tx, ty = se2_params(T @ np.linalg.inv(T_init))
    accepted = bool(np.hypot(tx, ty) <= cfg.max_correction_m and abs(np.degrees(yaw)) <= cfg.max_correction_deg)
    T_out = T if accepted else np.array(T_init, dtype=float)
    return Refinement(T_out, *overlap_fitness(ego, pts_peer, T_out, gates[-1]), accepted)


@pytest.fixture(scope="module")
def sim_pair():
    """A simulated pair 30 m apart at the default BV range: the ego cloud, co-visibility mask and peer points, the
    true pose, and starts around it (near: accepted corrections; farther: beyond max_correction; far: few matches)."""
    from bb_align.lab.sim import simulate_sequence

    cfg = AlignConfig()
    frame = simulate_sequence(3, 1, 2, 30.0)[0]
    ego_car, peer_car = frame.agents["0"], frame.agents["1"]
    ego_bev, peer_bev = make_bev(ego_car.points, cfg.bev), make_bev(peer_car.points, cfg.bev)
    cloud = bev_cloud(ego_bev, cfg.refine)
    covis = covisible_map(ego_bev.image, cfg.refine.min_pixel_value, 5)
    T_true = np.linalg.inv(ego_car.T_world_sensor) @ peer_car.T_world_sensor
    T_true = se2(*se2_params(T_true))
    rng = np.random.default_rng(11)
    starts = [
        se2(rng.normal(0, np.radians(s)), *rng.normal(0, m, 2)) @ T_true for s, m in [(1, 0.5)] * 8 + [(4, 2.5)] * 8
    ]
    starts += [se2(rng.uniform(-np.pi, np.pi), *rng.uniform(-60, 60, 2)) for _ in range(8)]
    return cfg, cloud, covis, peer_bev, starts


@pytest.mark.parametrize(("min_points", "threads", "facing"), [(None, 1, True), (100, 1, False), (None, 3, True)])
def test_coarse_verification_equals_refine_icp_and_overlap(sim_pair, min_points, threads, facing):
    """min_points 100: some far starts match fewer pixels at some step (the start pose kept). threads 3: the poses
    verified in three groups at once, the same answers in the same order. facing: with the peer normals' test."""
    cfg, cloud, covis, peer_bev, starts = sim_pair
    coarse = coarse_config(cfg.refine)
    if min_points is not None:
        coarse = coarse.model_copy(update={"min_points": min_points})
    pts = bev_points(peer_bev, cfg.refine.min_pixel_value, COARSE_POINTS, seed=cfg.seed)
    normals = peer_normals(peer_bev, pts, cfg.refine) if facing else None
    Ts, fitness, rmse, covisible = coarse_verification(
        cloud, covis, pts, starts, coarse, cfg.refine.gates_m[-1], threads, normals
    )
    accepted = 0
    for n, T0 in enumerate(starts):
        ref = _refine_icp_reference(cloud, pts, T0, coarse, normals)
        accepted += ref.accepted and not np.array_equal(ref.T, T0)
        np.testing.assert_allclose(Ts[n], ref.T, rtol=0, atol=1e-9)
        fit_ref, rmse_ref = overlap_fitness(cloud, pts, ref.T, cfg.refine.gates_m[-1])
        assert fitness[n] == fit_ref
        np.testing.assert_allclose(rmse[n], rmse_ref, rtol=1e-9)
        assert (
            covisible[n] == covisible_fraction(covis, cloud, pts, ref.T) == _covisible_numpy(covis, cloud, pts, ref.T)
        )
    assert 4 <= accepted < len(starts)  # both outcomes exercised
    assert fitness.max() > 0.3 and fitness.min() < 0.1


def test_refine_icp_equals_the_numpy_iterations(sim_pair):
    cfg, cloud, _, peer_bev, starts = sim_pair
    pts = bev_points(peer_bev, cfg.refine.min_pixel_value, cfg.refine.max_peer_points, seed=cfg.seed)
    normals = peer_normals(peer_bev, pts, cfg.refine)
    outcomes = set()
    for n, T0 in enumerate(starts[::2]):
        pn = normals if n % 2 else None  # with and without the facing test
        ref, new = _refine_icp_reference(cloud, pts, T0, cfg.refine, pn), refine_icp(cloud, pts, T0, cfg.refine, pn)
        outcomes.add(ref.accepted)
        assert new.accepted == ref.accepted and new.fitness == ref.fitness
        np.testing.assert_allclose(new.T, ref.T, rtol=0, atol=1e-9)
        np.testing.assert_allclose(new.rmse_m, ref.rmse_m, rtol=1e-9)
    assert outcomes == {True, False}


def test_pose_is_distinct_equals_poses_near():
    """Random poses, many of them just inside or outside the distance and angle (also across +-pi)."""
    rng = np.random.default_rng(8)
    outcomes = []
    for _ in range(300):
        pose = (rng.uniform(-np.pi, np.pi), *rng.uniform(-50, 50, 2))
        n = rng.integers(0, 6)
        ang = rng.uniform(0, 2 * np.pi) if rng.random() < 0.5 else rng.uniform(0, 0.1)
        params = np.stack(
            [
                (pose[0] + rng.choice([-1, 1], n) * np.radians(2.0 + rng.normal(0, 1e-9, n)) + np.pi) % (2 * np.pi)
                - np.pi,
                pose[1] + 2.0 * np.cos(ang) * (1 + rng.normal(0, 1e-9, n)),
                pose[2] + 2.0 * np.sin(ang) * (1 + rng.normal(0, 1e-9, n)),
            ],
            axis=1,
        )
        params[rng.random(n) < 0.3] += rng.normal(0, 1.0, 3)
        truth = not poses_near(params, pose, 2.0, 2.0).any()
        outcomes.append(truth)
        assert pose_is_distinct(params, pose, 2.0, 2.0) == truth
        assert distinct_pose(se2(*pose), [se2(*p) for p in params], 2.0, 2.0) == (
            not poses_near(
                np.array([se2_params(se2(*p)) for p in params]).reshape(-1, 3), se2_params(se2(*pose)), 2.0, 2.0
            ).any()
        )
    assert 50 < sum(outcomes) < 250
    across = np.array([[-np.pi + 0.01, 1.0, 2.0], [np.pi - 0.01, 1.0, 2.0]])  # 1.15 degrees apart, across +-pi
    assert not pose_is_distinct(across[:1], tuple(across[1]), 2.0, 2.0)
    assert not pose_is_distinct(across[1:], tuple(across[0]), 2.0, 2.0)
