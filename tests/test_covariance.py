"""Pose covariance from the refinement's point-to-line normal equations: a straight corridor must show a large
variance along it (and be refused), a structured street a small one, and over seeded runs the covariance must
cover the true error of the refinement (checked against known transforms)."""

from __future__ import annotations

import numpy as np
import pytest

from bb_align import AlignConfig, Aligner
from bb_align.engine.bev import BevImage, make_bev
from bb_align.engine.config import BevConfig
from bb_align.engine.covariance import mahalanobis2, params_covariance, pose_covariance
from bb_align.engine.geometry import se2, se2_params, se3_from_se2, worst_sigma_m
from bb_align.engine.refine import bev_cloud, bev_points, refine_icp
from bb_align.engine.result import AlignResult
from synthetic import synthetic_world, view_from

RANGE = 40.0
RES = 0.4
CHI2_3_99 = 11.345


def _corridor_image(seed: int) -> BevImage:
    """Two long parallel walls along x (y = +-7 m) with a little noise: nothing pins the motion along x."""
    n = int(2 * RANGE / RES)
    rng = np.random.default_rng(seed)
    img = np.zeros((n, n), np.uint8)
    for y in (-7.0, 7.0):
        col = int(round((RANGE - y) / RES - 0.5))
        keep = rng.random(n) > 0.1
        img[keep, col] = 120
    return BevImage(img, RES, RANGE, "max_height", 0.3, 12.0)


def test_corridor_has_large_variance_along_it_and_is_refused():
    ego = _corridor_image(0)
    cloud = bev_cloud(ego)
    T = se2(0.0, 0.0, 0.0)
    peer_pts = bev_points(_corridor_image(1))
    cov = params_covariance(pose_covariance(cloud, peer_pts, T, 0.4, inflation=1.0), T)
    evals, evecs = np.linalg.eigh(cov[1:, 1:])
    along = evecs[:, -1]
    assert abs(along[0]) > 0.99  # the worst direction is the corridor's (x)
    assert np.sqrt(cov[1, 1]) > 100 * np.sqrt(cov[2, 2])  # x unconstrained, y well pinned
    assert worst_sigma_m(cov) > 1.0
    # The success rule refuses such a pose.
    from bb_align.engine.covariance import pose_uncertainty

    aligner = Aligner(AlignConfig(bev=BevConfig(range_m=RANGE, resolution_m=RES)))
    prepared = aligner.prepare(ego)
    result = AlignResult(success=False, T_ego_peer=np.eye(4), T_bv=T, T_box=np.eye(3))
    result.covariance = pose_uncertainty(
        prepared.cloud(aligner.config.refine), (peer_pts, None), T, 0.4, aligner.config.covariance
    )
    reason = aligner.verdict.uncertain(result)
    assert reason is not None and reason.value == "degenerate_pose"
    assert result.covariance.shape == (3, 3)


def test_structured_street_is_well_constrained():
    pts_w, _ = synthetic_world(seed=3)
    bev_cfg = BevConfig(range_m=RANGE)
    ego = bev_cloud(make_bev(view_from(pts_w, np.eye(4), seed=0), bev_cfg))
    peer = bev_points(make_bev(view_from(pts_w, np.eye(4), seed=1), bev_cfg), max_points=2000)
    cov = pose_covariance(ego, peer, np.eye(3), 0.4, inflation=AlignConfig().covariance.inflation)
    assert worst_sigma_m(cov) < 0.3
    assert np.degrees(np.sqrt(cov[0, 0])) < 0.3


def test_params_covariance_carries_yaw_into_translation():
    cov_left = np.diag([1e-4, 1e-4, 1e-4])
    T = se2(0.0, 50.0, 0.0)  # a yaw increment on the left moves a point 50 m ahead sideways
    cov = params_covariance(cov_left, T)
    assert cov[2, 2] == pytest.approx(1e-4 + 50.0**2 * 1e-4)
    assert cov[1, 1] == pytest.approx(1e-4)


def test_covariance_covers_the_true_error_over_seeded_runs():
    """Refine from a perturbed start on seeded synthetic pairs (different sensor heights and point drops, so the
    two images differ as two cars' do); the squared Mahalanobis distance of the remaining true error under the
    configured covariance must lie within the chi2(3) 99 % bound for (nearly) all runs, and not be absurdly
    small (a covariance a hundred times too large would be useless)."""
    cfg = AlignConfig()
    bev_cfg = BevConfig(range_m=60.0)
    d2 = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        pts_w, _ = synthetic_world(seed=10 + seed)
        T_world_peer = se2(rng.uniform(-np.pi, np.pi), *rng.uniform(-20, 20, 2))
        ego = bev_cloud(make_bev(view_from(pts_w, np.eye(4), seed=seed), bev_cfg))
        peer = bev_points(
            make_bev(
                view_from(pts_w, se3_from_se2(T_world_peer), seed=seed + 100, sensor_height=1.5, drop=0.5), bev_cfg
            ),
            max_points=cfg.refine.max_peer_points,
            seed=seed,
        )
        T_start = se2(*rng.normal(0, [0.01, 0.5, 0.5])) @ T_world_peer
        rf = cfg.refine
        ref = refine_icp(ego, peer, T_start, rf)
        cov = params_covariance(
            pose_covariance(
                ego, peer, ref.T, rf.gates_m[-1], cfg.covariance.inflation, cfg.covariance.min_residual_sigma_m
            ),
            ref.T,
        )
        y_t, x_t, z_t = se2_params(T_world_peer)
        y, x, z = se2_params(ref.T)
        d2.append(mahalanobis2(cov, np.array([(y_t - y + np.pi) % (2 * np.pi) - np.pi, x_t - x, z_t - z])))
    d2 = np.array(d2)
    assert np.mean(d2 <= CHI2_3_99) >= 0.9, d2
    assert np.median(d2) > 0.01, d2  # not absurdly loose


def test_fuse_poses_by_hand():
    """Two measurements of one pose, 2 m apart along x: variances 4 and 1 along x give the weighted mean
    2 * (1/1) / (1/4 + 1) = 1.6 m and variance 1 / (1/4 + 1) = 0.8; across (y) the first one's 0.01 m^2 keeps it;
    20 m apart they disagree (squared Mahalanobis 400 / 5 > chi2(3) 99 %) and are not fused."""
    from bb_align.engine.covariance import fuse_poses

    C_a, C_b = np.diag([1e-4, 4.0, 0.01]), np.diag([1e-4, 1.0, 1.0])
    T, C = fuse_poses(se2(0.0, 0.0, 0.0), C_a, se2(0.0, 2.0, 0.0), C_b, CHI2_3_99)
    np.testing.assert_allclose(se2_params(T), (0.0, 1.6, 0.0), atol=1e-12)
    np.testing.assert_allclose(np.diag(C), (5e-5, 0.8, 0.01 / 1.01), rtol=1e-9)
    assert fuse_poses(se2(0.0, 0.0, 0.0), C_a, se2(0.0, 20.0, 0.0), C_b, CHI2_3_99) is None
