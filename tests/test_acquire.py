"""Multi-hypothesis acquisition (bb_align.acquire): top-k candidates against brute force, pose hypotheses against
a known transform hidden among wrong candidates, and the engine's multi path end to end on known transforms."""

from __future__ import annotations

import numpy as np
import pytest

from bb_align import AlignConfig, Aligner
from bb_align.engine.acquire import pose_hypotheses, topk_candidates
from bb_align.engine.config import AcquireConfig
from bb_align.engine.geometry import pose_error, se2, se2_params, se3_from_se2
from synthetic import synthetic_world, view_from


def test_topk_candidates_are_the_nearest_distinct_keypoints():
    rng = np.random.default_rng(0)
    n_ego, copies = 50, 3
    ref = rng.normal(size=(n_ego * copies, 16)).astype(np.float32)  # row r describes keypoint r % n_ego
    peer = rng.normal(size=(20, 16)).astype(np.float32)
    peer[3] = 0.0  # an empty descriptor never matches
    rows, cand = topk_candidates(peer, ref, n_ego, 4)
    assert 3 not in rows and len(rows) == 19
    d = np.linalg.norm(peer[:, None, :] - ref[None, :, :], axis=2).reshape(20, copies, n_ego).min(axis=1)
    for r, c in zip(rows, cand):
        np.testing.assert_array_equal(c, np.argsort(d[r])[:4])


def test_pose_hypotheses_find_a_pose_supported_by_few_candidates_among_many():
    """300 peer keypoints, 5 candidates each; only 25 keypoints have their true partner among them, at a random
    rank (as at 70 m: the nearest descriptor is mostly wrong). The true pose must be the first hypothesis."""
    rng = np.random.default_rng(1)
    T = se2(np.radians(137.0), 61.0, -23.0)
    kp_peer = rng.uniform(-80, 80, (300, 2))
    kp_ego = rng.uniform(-80, 80, (400, 2))
    true_rows = rng.choice(300, 25, replace=False)
    partners = rng.choice(400, 25, replace=False)
    kp_ego[partners] = kp_peer[true_rows] @ T[:2, :2].T + T[:2, 2] + rng.normal(0, 0.4, (25, 2))
    cand = rng.integers(0, 400, (300, 5))
    cand[true_rows, rng.integers(0, 5, 25)] = partners
    cfg = AcquireConfig()
    hyps = pose_hypotheses(kp_peer, kp_ego, cand, cfg, threshold=2.0, t_half=120.0)
    assert hyps, "no hypothesis"
    t_err, r_err = pose_error(se3_from_se2(hyps[0].T), se3_from_se2(T))
    assert t_err < 1.0 and r_err < 1.0
    assert hyps[0].inliers >= 20
    assert all(h.inliers < 15 for h in hyps[1:])  # the others are noise
    # Distinct: no two hypotheses within distinct_m and distinct_deg of each other.
    for i, a in enumerate(hyps):
        for b in hyps[i + 1 :]:
            ya, xa, za = se2_params(a.T)
            yb, xb, zb = se2_params(b.T)
            assert np.hypot(xa - xb, za - zb) >= cfg.distinct_m or abs(np.degrees(ya - yb)) >= cfg.distinct_deg


@pytest.fixture(scope="module")
def world():
    return synthetic_world(seed=0, extent=110.0)


@pytest.mark.parametrize("yaw_deg,t_xy", [(8.0, (45.0, 2.0)), (-170.0, (-30.0, -35.0))])
def test_multi_path_recovers_known_pose_with_covariance(world, yaw_deg, t_xy):
    pts_w, _ = world
    T_true = se3_from_se2(se2(np.radians(yaw_deg), *t_xy))
    pts_ego = view_from(pts_w, np.eye(4), seed=0)
    pts_peer = view_from(pts_w, T_true, seed=1, sensor_height=1.5)
    aligner = Aligner(AlignConfig(acquire=AcquireConfig(mode="multi")))
    res = aligner.align(aligner.warm(aligner.prepare(pts_ego)), aligner.prepare(pts_peer))
    assert res.success, (res.reason, res.acquisition)
    t_err, r_err = pose_error(res.T_ego_peer, T_true)
    assert t_err < 0.5 and r_err < 0.5
    assert res.acquisition["hypotheses"] >= 1 and res.acquisition["margin"] >= aligner.config.acquire.min_margin
    assert res.covariance is not None and res.covariance.shape == (3, 3)
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)
    d = res.to_dict()
    assert len(d["covariance"]) == 3 and d["acquisition"]["margin"] == res.acquisition["margin"]


def test_multi_path_fails_without_overlap(world):
    pts_w, _ = world
    other, _ = synthetic_world(seed=5)
    aligner = Aligner(AlignConfig(acquire=AcquireConfig(mode="multi")))
    res = aligner.align(
        aligner.prepare(view_from(pts_w, np.eye(4), seed=0)), aligner.prepare(view_from(other, np.eye(4), seed=1))
    )
    assert not res.success
    assert res.reason in {"ambiguous_bv", "inconsistent_overlap", "too_few_inliers_bv", "degenerate_pose"}


def test_paper_mode_is_still_available(world):
    pts_w, _ = world
    T_true = se3_from_se2(se2(np.radians(20.0), 15.0, 3.0))
    aligner = Aligner(AlignConfig(acquire=AcquireConfig(mode="paper")))
    res = aligner.align(
        aligner.prepare(view_from(pts_w, np.eye(4), seed=0)), aligner.prepare(view_from(pts_w, T_true, seed=1))
    )
    assert res.success and res.acquisition is None
    assert pose_error(res.T_ego_peer, T_true)[0] < 0.3
