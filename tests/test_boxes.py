import numpy as np
import pytest

from bb_align.engine.boxes import align_boxes, as_boxes, box_corners_bev, match_corners, transform_boxes
from bb_align.engine.geometry import pose_error, se2


def test_corner_order_hand_worked():
    # A 4 x 2 box at (10, 5) heading +y (yaw 90 deg): front is +y, its right side is +x.
    c = box_corners_bev([[10, 5, 0, 4, 2, 1.5, np.pi / 2]])[0]
    np.testing.assert_allclose(c, [[11, 7], [9, 7], [9, 3], [11, 3]], atol=1e-12)


def test_transform_boxes_moves_centre_and_heading():
    b = transform_boxes(se2(np.pi / 2, 1.0, 0.0), [[2, 0, 0.5, 4, 2, 1.5, 0.1]])[0]
    np.testing.assert_allclose(b, [1, 2, 0.5, 4, 2, 1.5, 0.1 + np.pi / 2], atol=1e-12)


@pytest.mark.parametrize("flip", [np.pi, np.pi / 2, -np.pi / 2])
def test_corner_pairing_survives_heading_flips(flip):
    boxes = np.array([[10, 5, 0, 2.0, 2.0, 1.5, 0.3]])  # square: a 90-degree flip is a plausible detector error
    ego = box_corners_bev(boxes)
    flipped = boxes.copy()
    flipped[:, 6] += flip
    peer = match_corners(ego, box_corners_bev(flipped))
    np.testing.assert_allclose(peer, ego, atol=1e-9)


def test_stage2_recovers_a_small_offset_with_flipped_detections():
    rng = np.random.default_rng(0)
    n = 8
    boxes_ego = np.column_stack(
        [
            rng.uniform(-40, 40, (n, 2)),
            np.full(n, 0.8),
            rng.uniform(3.8, 4.8, n),
            rng.uniform(1.7, 2.0, n),
            np.full(n, 1.5),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )
    T_ego_peer = se2(np.radians(30.0), 12.0, -7.0)
    boxes_peer = transform_boxes(np.linalg.inv(T_ego_peer), boxes_ego)
    boxes_peer[::3, 6] += np.pi  # the peer's detector flips every third heading
    boxes_peer[:, :2] += rng.normal(0, 0.05, (n, 2))
    T_bv = se2(np.radians(30.6), 12.5, -7.6)  # stage 1 is off by 0.6 deg / 0.8 m
    res = align_boxes(boxes_ego, boxes_peer, T_bv)
    assert res.pairs == n and res.inliers >= 4 * n - 2
    t_err, r_err = pose_error(res.T_box @ T_bv, T_ego_peer)
    assert t_err < 0.15 and r_err < 0.2


def test_no_overlap_gives_no_pairs():
    boxes_ego = [[0, 0, 0, 4, 2, 1.5, 0]]
    res = align_boxes(boxes_ego, [[50, 50, 0, 4, 2, 1.5, 0]], np.eye(3))
    assert res.pairs == 0 and res.inliers == 0


def test_box_validation_names_the_problem():
    with pytest.raises(ValueError, match=r"\(K, 7\)"):
        as_boxes(np.zeros((3, 6)))
    with pytest.raises(ValueError, match="finite"):
        as_boxes([[0, 0, 0, 4, 2, np.nan, 0]])
    assert as_boxes(None).shape == (0, 7)


def test_box_measurement_recovers_a_known_transform_and_its_covariance_by_hand():
    from bb_align.engine.boxes import box_measurement

    T_ego_peer = se2(np.radians(20.0), 30.0, -4.0)
    # Two cars both see, 10 m either side of the ego along its x axis (in the ego frame), and the same cars as
    # the peer detects them (its own frame): noise-free, so the fit is exact.
    cars_ego = np.array([[10.0, 0.0, 0.0, 4.5, 1.9, 1.6, 0.3], [-10.0, 0.0, 0.0, 4.2, 1.8, 1.5, -0.1]])
    cars_peer = transform_boxes(np.linalg.inv(T_ego_peer), cars_ego)
    T_pred = se2(np.radians(1.0), 1.0, -0.7) @ T_ego_peer  # a track's prediction, 1.2 m / 1 deg off
    T, cov = box_measurement(cars_ego, cars_peer, T_pred, sigma_m=1.0)
    np.testing.assert_allclose(T, T_ego_peer, atol=1e-6)
    # By hand: centres (10, 0) and (-10, 0); rows [0 1 0], [10 0 1], [0 1 0], [-10 0 1]: H = diag(200, 2, 2).
    np.testing.assert_allclose(cov, np.diag([1 / 200, 0.5, 0.5]), atol=1e-9)
    assert box_measurement(cars_ego[:1], cars_peer[:1], T_pred, sigma_m=1.0) is None  # one pair is not enough
    assert box_measurement(cars_ego, cars_peer, se2(0.0, 5.0, 0.0) @ T_pred, sigma_m=1.0) is None  # out of gate
