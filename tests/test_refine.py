"""Dense BV refinement: the grid nearest-point look-up against a KD-tree, and ICP against a known transform."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bb_align.engine.bev import BevImage, make_bev
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


# ---- the facing test: two faces of one object are not one surface ------------------------------------------------

RES, RANGE = 0.4, 60.0


def _draw(segments_m: list[tuple[float, float, float, float]]) -> BevImage:
    """A BV image (RANGE, RES) lit along the given segments (x0, y0, x1, y1 in the sensor frame, metres)."""
    img = np.zeros((int(2 * RANGE / RES),) * 2, np.uint8)
    bev = BevImage(img, RES, RANGE)
    for x0, y0, x1, y1 in segments_m:
        n = int(np.hypot(x1 - x0, y1 - y0) / (RES / 4)) + 1
        rc = np.round(bev.metre_to_pixel(np.linspace([x0, y0], [x1, y1], n))).astype(int)
        rc = rc[np.all((rc >= 0) & (rc < img.shape[0]), axis=1)]  # beyond the range: unseen
        img[rc[:, 0], rc[:, 1]] = 200
    return bev


def _street(T_world_sensor: np.ndarray, sensor_x: float) -> BevImage:
    """What one car on a straight street (walls at y = +-9 m, x -15..45 m) sees: the walls, a 2.4 m cross wall at
    x = 50.2 m (both cars see its -x face) and the face turned towards it of eight 0.4 m thick posts between the
    cars (poles, trunks), every 4 m from x = 4 m. Coordinates on pixel centres, so that a pose of whole pixels and
    no yaw draws both views without rounding."""
    segs = [(-15, 9, 45, 9), (-15, -9, 45, -9), (50.2, -1.2, 50.2, 1.2)]
    for k in range(8):
        x, y = 4.0 + 4.0 * k, -6.2 + 1.6 * k
        face = x - 0.2 if sensor_x < x else x + 0.2
        segs.append((face, y - 0.8, face, y + 0.8))
    T_sensor_world = np.linalg.inv(T_world_sensor)
    out = []
    for x0, y0, x1, y1 in segs:
        (a, b), (c, d) = (T_sensor_world[:2, :2] @ np.array([[x0, x1], [y0, y1]]) + T_sensor_world[:2, 2:]).T
        out.append((a, b, c, d))
    return _draw(out)


def test_the_facing_test_keeps_two_faces_of_one_post_from_pulling_the_cars_together():
    """Hand-worked: between the cars each sees the near face of every post; without the facing test the two faces
    (a pixel apart) pair and the refinement, started at the truth, pulls the peer towards the ego car; with it only
    the surfaces both saw from one side pair (the walls, the cross wall) and it stays at the truth."""
    from bb_align.engine.config import RefineConfig
    from bb_align.engine.refine import peer_normals

    T_true = se2(0.0, 40.0, 0.8)  # the peer 40 m ahead: whole pixels, both views drawn alike
    ego, peer = _street(np.eye(3), 0.0), _street(T_true, 40.0)
    cfg = RefineConfig()
    cloud, pts = bev_cloud(ego, cfg), bev_points(peer, max_points=4000)
    blind = refine_icp(cloud, pts, T_true, cfg)
    seeing = refine_icp(cloud, pts, T_true, cfg, peer_normals(peer, pts, cfg))
    drift = lambda T: float(T[0, 2] - T_true[0, 2])  # noqa: E731  along the street (+: away from the ego car)
    assert drift(blind.T) < -0.2  # -0.36 m
    assert abs(drift(seeing.T)) < 0.02
    t_err, r_err = pose_error(se3_from_se2(seeing.T), se3_from_se2(T_true))
    assert t_err < 0.02 and r_err < 0.05


def test_normals_face_their_sensor():
    """The ego cloud's PCA normals and the peer points' window normals are the walls' normals turned towards the
    sensor; a lone pixel's is the direction to the sensor (the face it shows)."""
    from bb_align.engine.config import RefineConfig
    from bb_align.engine.refine import peer_normals

    bev = _draw([(-20, 9, 30, 9), (40, -9, 40, 9), (10.2, -30.2, 10.2, -30.2)])
    cfg = RefineConfig()
    cloud = bev_cloud(bev, cfg)
    on_side = (np.abs(cloud.xy[:, 1] - 9) < 0.3) & (cloud.xy[:, 0] < 31)
    on_cross = (np.abs(cloud.xy[:, 0] - 40) < 0.3) & (np.abs(cloud.xy[:, 1]) < 8)
    assert np.all(cloud.normals[on_side, 1] < -0.99) and np.all(cloud.normals[on_cross, 0] < -0.99)
    pts = cloud.xy[on_side | on_cross]
    n = peer_normals(bev, pts, cfg)
    np.testing.assert_allclose(n, cloud.normals[on_side | on_cross], atol=1e-9)
    lone = cloud.xy[np.hypot(cloud.xy[:, 0] - 10.2, cloud.xy[:, 1] + 30.2) < 0.5]
    assert len(lone) == 1
    np.testing.assert_allclose(peer_normals(bev, lone, cfg)[0], -lone[0] / np.linalg.norm(lone[0]), atol=1e-12)
