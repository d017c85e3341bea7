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


def _seed_support_reference(c_peer, h_peer, c_ego, h_ego, size_ok, gate, tol):
    """Every seed's support by brute force, in numpy: each peer box under the seed's pose against every ego box."""
    sup = []
    for i in range(len(c_peer)):
        for k in range(len(c_ego)):
            for f in range(2):
                if not size_ok[i, k]:
                    sup.append(0)
                    continue
                th = h_ego[k] - h_peer[i] + f * np.pi
                T = se2(th, *(c_ego[k] - se2(th, 0.0, 0.0)[:2, :2] @ c_peer[i]))
                p = c_peer @ T[:2, :2].T + T[:2, 2]
                near = np.hypot(p[:, None, 0] - c_ego[None, :, 0], p[:, None, 1] - c_ego[None, :, 1]) < gate
                g = np.mod((h_peer + th)[:, None] - h_ego[None, :], np.pi)
                sup.append(int((near & (np.minimum(g, np.pi - g) < tol) & size_ok).any(axis=1).sum()))
    return np.array(sup)


def test_seed_support_on_the_grid_equals_brute_force():
    """A parking lot: 30 ego cars on a 5 m lattice (many within one grid cell's reach), the peer's 25 of them seen
    from another pose with noise, some flipped, two trucks; the compiled, grid-looked-up support equals the count
    over every ego box, seed by seed."""
    from bb_align.engine.box_poses import _seeds, same_size

    rng = np.random.default_rng(4)
    world = [_box(5.0 * (n % 6), 5.0 * (n // 6), rng.uniform(-np.pi, np.pi)) for n in range(30)]
    world[3][3:5] = world[17][3:5] = [9.0, 2.5]  # trucks
    boxes_ego = np.array(world)
    T_peer_ego = se2(np.radians(35.0), -12.0, 7.0)
    seen = boxes_ego[rng.choice(30, 25, replace=False)]
    boxes_peer = transform_boxes(T_peer_ego, seen)
    boxes_peer[:, :2] += rng.normal(0, 0.8, (25, 2))
    boxes_peer[::4, 6] += np.pi
    cfg = AcquireConfig()
    ego, peer = BoxSet.of(boxes_ego), BoxSet.of(boxes_peer)
    size_ok, tol = same_size(peer, ego, cfg), np.radians(cfg.box_heading_tol_deg)
    gate = cfg.box_seed_gate_m
    *_, sup = _seeds(peer.centres, peer.headings, ego.centres, ego.headings, size_ok, gate**2, tol)
    ref = _seed_support_reference(peer.centres, peer.headings, ego.centres, ego.headings, size_ok, gate, tol)
    assert sup.max() >= 20 and (sup > 0).sum() > 100  # the true seeds and many partial ones
    np.testing.assert_array_equal(sup, ref)
