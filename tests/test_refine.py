"""Dense BV refinement: the grid nearest-point look-up against a KD-tree, and ICP against a known transform."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bb_align.engine.bev import make_bev
from bb_align.engine.config import BevConfig
from bb_align.engine.geometry import pose_error, se2, se3_from_se2
from bb_align.engine.refine import bev_cloud, bev_points, refine_icp
from synthetic import synthetic_world, view_from


@pytest.mark.parametrize("gate", [0.3, 0.4, 1.0, 2.0, 5.0])
def test_grid_nearest_equals_kd_tree(gate):
    bev = make_bev(view_from(synthetic_world(seed=2)[0], np.eye(4)), BevConfig(range_m=30.0))
    cloud = bev_cloud(bev)
    rng = np.random.default_rng(int(gate * 10))
    # Around lit pixels (the ICP's case), anywhere in the image, and off the image.
    pts = np.concatenate(
        [
            cloud.xy[rng.integers(len(cloud.xy), size=3000)] + rng.normal(0, gate, (3000, 2)),
            rng.uniform(-30, 30, (1000, 2)),
            rng.uniform(-40, 40, (500, 2)),
        ]
    )
    d, j = cloud.nearest(pts, gate)
    d_ref, j_ref = cKDTree(cloud.xy).query(pts, distance_upper_bound=gate)
    found = np.isfinite(d_ref)
    assert found.sum() > 1000 and (~found).sum() > 100
    np.testing.assert_array_equal(np.isfinite(d), found)
    np.testing.assert_allclose(d[found], d_ref[found], rtol=1e-12)
    assert np.all(j[~found] == -1)
    # Same point, or an equally distant one.
    np.testing.assert_allclose(np.linalg.norm(cloud.xy[j[found]] - pts[found], axis=1), d_ref[found], rtol=1e-12)


def test_grid_nearest_of_non_finite_and_far_points_is_none():
    bev = make_bev(view_from(synthetic_world(seed=2)[0], np.eye(4)), BevConfig(range_m=30.0))
    cloud = bev_cloud(bev)
    pts = np.array([[np.nan, 0.0], [0.0, np.inf], [-np.inf, np.nan], [1e300, -1e300], cloud.xy[0]])
    d, j = cloud.nearest(pts, 2.0)
    assert j.tolist()[:4] == [-1, -1, -1, -1] and np.all(np.isinf(d[:4]))
    assert j[4] == 0 and d[4] == 0.0


def test_icp_recovers_a_known_pose_from_a_perturbed_start():
    world, _ = synthetic_world(seed=5)
    T_world_ego = np.eye(4)
    T_world_peer = se3_from_se2(se2(np.radians(20.0), 12.0, -3.0))
    ego = make_bev(view_from(world, T_world_ego))
    peer = make_bev(view_from(world, T_world_peer))
    T_ego_peer = np.linalg.inv(T_world_ego) @ T_world_peer
    T_true = se2(np.radians(20.0), 12.0, -3.0)
    T_start = se2(np.radians(0.8), 0.5, -0.4) @ T_true  # what keypoint RANSAC might leave
    ref = refine_icp(bev_cloud(ego), bev_points(peer, max_points=2000), T_start)
    assert ref.accepted
    t_err, r_err = pose_error(se3_from_se2(ref.T), T_ego_peer)
    t_start, r_start = pose_error(se3_from_se2(T_start), T_ego_peer)
    assert t_err < 0.1 and r_err < 0.1, (t_err, r_err)
    assert t_err < t_start / 5 and r_err < r_start / 5
    assert ref.fitness > 0.5
