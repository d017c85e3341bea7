"""Box-proposed poses (bb_align.engine.box_poses): the agreement of two cars' boxes worked by hand, and a decoy
that pairs more boxes by place alone than the truth but disagrees in heading."""

from __future__ import annotations

import numpy as np

from bb_align.engine.box_poses import BoxSet, box_agreement, box_poses
from bb_align.engine.boxes import transform_boxes
from bb_align.engine.config import AcquireConfig
from bb_align.engine.geometry import se2


def _box(x, y, heading, length=4.5, width=1.9):
    return [x, y, 0.8, length, width, 1.6, heading]


def test_box_agreement_by_hand():
    """Four peer boxes over four ego boxes: one agrees (reported backwards, 0.5 m off), one is turned 90 degrees, one
    is a truck over a car, one agrees but lies 3 m off (outside the 2 m pairing gate, inside the soft score)."""
    cfg = AcquireConfig()  # gate 2 m, heading 20 deg (mod 180), size 1 m, sigma 0.7 m
    ego = np.array([_box(10, 0, 0.0), _box(20, 0, 0.0), _box(30, 0, 0.0), _box(40, 0, 0.0)])
    peer_in_ego = np.array(
        [_box(10.5, 0, np.pi), _box(20, 0, np.pi / 2), _box(30, 0, 0.0, 8.0, 2.5), _box(40, 3, 0.05)]
    )
    expected_score = np.exp(-(0.5**2) / (2 * 0.7**2)) + np.exp(-(3.0**2) / (2 * 0.7**2))
    for T_ego_peer in (np.eye(3), se2(np.radians(-75.0), 31.0, -12.0)):
        peer = transform_boxes(np.linalg.inv(T_ego_peer), peer_in_ego)  # the same boxes, seen from the peer
        pairs, score = box_agreement(T_ego_peer, BoxSet.of(peer), BoxSet.of(ego), cfg)
        assert pairs == 1
        assert np.isclose(score, expected_score)
    assert box_agreement(np.eye(3), BoxSet.of(np.zeros((0, 7))), BoxSet.of(ego), cfg) == (0, 0.0)


def _decoy_scene(turn_deg: float, decoy_size: tuple[float, float]):
    """The peer sees 7 cars, 5 of which the ego sees too. The ego also sees 7 decoys placed exactly where the peer's
    7 land under a wrong pose, turned ``turn_deg`` from the heading that pose implies and of ``decoy_size``."""
    rng = np.random.default_rng(3)
    T_true, T_wrong = se2(np.radians(35.0), 62.0, -8.0), se2(np.radians(-20.0), 15.0, 40.0)
    peer = np.array([_box(*rng.uniform(-40, 40, 2), rng.uniform(-np.pi, np.pi)) for _ in range(7)])
    decoys = transform_boxes(T_wrong, peer)
    decoys[:, 6] += np.radians(turn_deg)
    decoys[:, 3:5] = decoy_size
    ego = np.vstack([transform_boxes(T_true, peer[:5]), decoys])
    ego[:, :2] += rng.normal(0, 0.1, (len(ego), 2))
    return ego, peer, T_true, T_wrong


def _first_pose(ego, peer, cfg):
    poses = box_poses(ego, peer, cfg)
    assert poses
    return poses[0]


def test_a_decoy_that_pairs_more_boxes_by_place_but_not_by_heading_loses():
    """By place alone the wrong pose pairs 7 boxes and the truth 5; with headings compared (mod 180) the truth is the
    first pose and the decoy pairs none."""
    ego, peer, T_true, T_wrong = _decoy_scene(60.0, (4.5, 1.9))
    best = _first_pose(ego, peer, AcquireConfig())
    assert np.abs(best.T - T_true).max() < 0.2 and best.pairs == 5
    assert box_agreement(T_wrong, BoxSet.of(peer), BoxSet.of(ego), AcquireConfig())[0] == 0
    assert box_agreement(T_wrong, BoxSet.of(peer), BoxSet.of(ego), AcquireConfig(box_heading_tol_deg=90.0))[0] == 7


def test_a_decoy_of_trucks_where_the_peer_saw_cars_loses():
    ego, peer, T_true, T_wrong = _decoy_scene(0.0, (9.0, 2.6))
    best = _first_pose(ego, peer, AcquireConfig())
    assert np.abs(best.T - T_true).max() < 0.2 and best.pairs == 5
    # the contrast: sizes ignored, the decoy wins by place (7 pairs)
    blind = _first_pose(ego, peer, AcquireConfig(box_size_tol_m=100.0))
    assert np.abs(blind.T - T_wrong).max() < 0.2 and blind.pairs == 7
