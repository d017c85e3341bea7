"""The free-space check (engine.freespace) against images worked by hand: a wall ahead of the sensor."""

from __future__ import annotations

import numpy as np

from bb_align.engine.acquisition import acquirer, free_space, hypotheses
from bb_align.engine.acquisition.model import Hypothesis
from bb_align.engine.acquisition.verification import covisible, covisible_map
from bb_align.engine.bev import BevImage
from bb_align.engine.config import FreeSpaceConfig, with_overrides
from bb_align.engine.freespace import conflict, free_space_map, tall_points
from bb_align.engine.geometry import pose_error, se2, se3_from_se2
from bb_align.engine.pipeline import Aligner
from synthetic import synthetic_world, view_from

RES, RANGE = 0.5, 50.0  # 200 x 200 pixels, the sensor at the centre


def _image(points_xy: np.ndarray, value: int = 200) -> BevImage:
    """A BV image lighting the pixels of the given (x, y) metres (sensor frame)."""
    bev = BevImage(image=np.zeros((200, 200), np.uint8), resolution_m=RES, range_m=RANGE)
    rc = np.floor(bev.metre_to_pixel(points_xy) + 0.5).astype(int)
    bev.image[rc[:, 0], rc[:, 1]] = value
    return bev


def _wall(x: float, y0: float, y1: float) -> np.ndarray:
    """A wall across the forward axis at ``x`` metres, from y0 to y1 (one point per 0.1 m)."""
    y = np.arange(y0, y1, 0.1)
    return np.column_stack([np.full_like(y, x), y])


def _is_free(free: np.ndarray, bev: BevImage, x: float, y: float) -> bool:
    r, c = np.floor(bev.metre_to_pixel(np.array([[x, y]])) + 0.5).astype(int)[0]
    return bool(free[r, c])


def test_free_space_is_what_lies_before_the_first_hit_of_each_azimuth():
    cfg = FreeSpaceConfig(margin_m=2.0, min_range_m=3.0, open_m=30.0)
    bev = _image(_wall(20.0, -10.0, 10.0))  # a wall 20 m ahead, 20 m wide
    free = free_space_map(bev, 1, covisible_map(bev.image, 1, 4), cfg)  # 2 m about the wall is near it
    assert _is_free(free, bev, 10.0, 0.0)  # between the sensor and the wall
    assert _is_free(free, bev, 15.0, 5.0)
    assert not _is_free(free, bev, 1.0, 0.0)  # inside min_range_m (the car itself)
    assert not _is_free(free, bev, 19.0, 0.0)  # within the margin before the wall
    assert not _is_free(free, bev, 30.0, 0.0)  # behind the wall: occluded, unknown
    # Azimuths with no hit at all (backwards): free up to open_m only.
    assert _is_free(free, bev, -25.0, 0.0)
    assert not _is_free(free, bev, -35.0, 0.0)
    # By default an azimuth with no hit is unknown (no return may mean a blocked beam), not free.
    assert not free_space_map(bev, 1, covisible_map(bev.image, 1, 4), FreeSpaceConfig())[150:, :].any()


def test_a_wall_moved_into_the_other_cars_free_space_conflicts_and_the_true_pose_does_not():
    cfg = FreeSpaceConfig(margin_m=2.0, min_range_m=3.0, open_m=30.0, tall_m=1.0)
    structure = np.concatenate([_wall(20.0, -10.0, 10.0), _wall(-15.0, -8.0, 8.0)])
    ego = _image(structure)
    T_ego_peer = se2(0.3, 4.0, -2.0)  # the peer's sensor in the ego frame
    T_peer_ego = np.linalg.inv(T_ego_peer)
    peer = _image(structure @ T_peer_ego[:2, :2].T + T_peer_ego[:2, 2])  # the same walls, seen from the peer
    covis = covisible_map(ego.image, 1, 4)  # within 2 m of the ego's structure
    free = free_space_map(ego, 1, covis, cfg)
    pts_peer = tall_points(peer, cfg)
    assert len(pts_peer) > 50
    assert conflict(free, covis, ego, pts_peer, T_ego_peer) == 0.0
    # A half turn about the ego sensor puts the front wall where the ego car saw through (and the back one in front).
    T_alias = se2(np.pi, 0.0, 0.0) @ T_ego_peer
    assert conflict(free, covis, ego, pts_peer, T_alias) > 0.5
    # Slid 8 m forward, the front wall lands behind the ego's (unseen: not counted), the back wall in free space.
    assert conflict(free, covis, ego, pts_peer, se2(0.0, 8.0, 0.0) @ T_ego_peer) == 1.0
    # Slid 1 m, both walls stay within reach of the ego's (covis): no conflict; what lands nowhere seen counts for 0.
    assert conflict(free, covis, ego, pts_peer, se2(0.0, 1.0, 0.0) @ T_ego_peer) == 0.0
    assert conflict(free, covis, ego, pts_peer, se2(0.0, 500.0, 0.0)) == 0.0


def test_only_tall_structure_is_checked():
    cfg = FreeSpaceConfig(tall_m=1.5)
    low = _image(_wall(20.0, -5.0, 5.0), value=10)  # about 0.7 m above the ground (max_height 12 m, clearance 0.3 m)
    assert len(tall_points(low, cfg)) == 0
    high = _image(_wall(20.0, -5.0, 5.0), value=60)  # about 3 m
    assert len(tall_points(high, cfg)) == len(np.argwhere(high.image > 0))


def _street_pair(T_ego_peer: np.ndarray):
    """The synthetic street seen by two sensors (the peer at T_ego_peer), prepared by a default Aligner."""
    pts_w, _ = synthetic_world(seed=0, extent=110.0)
    aligner = Aligner()
    ego = aligner.prepare(view_from(pts_w, np.eye(4), seed=0))
    peer = aligner.prepare(view_from(pts_w, se3_from_se2(T_ego_peer), seed=1, sensor_height=1.5))
    return aligner, ego, peer


def test_on_a_street_the_true_pose_has_no_conflict_and_a_half_turn_has_much():
    """Against the known pose: the peer's structure lands on the ego's (not in its free space); turned by 180
    degrees about the peer's sensor (the alias cars on both sides of a street invite) it lands on the empty road."""
    T_true = se2(np.radians(8.0), 45.0, 2.0)
    aligner, ego, peer = _street_pair(T_true)
    cfg, mv = aligner.config.free_space, aligner.config.refine.min_pixel_value
    near_ego, near_peer = covisible_map(ego.bev.image, mv, 5), covisible_map(peer.bev.image, mv, 5)
    free_ego, free_peer = free_space_map(ego.bev, mv, near_ego, cfg), free_space_map(peer.bev, mv, near_peer, cfg)
    tall_ego, tall_peer = tall_points(ego.bev, cfg), tall_points(peer.bev, cfg)

    def both(T):
        return max(
            conflict(free_ego, near_ego, ego.bev, tall_peer, T),
            conflict(free_peer, near_peer, peer.bev, tall_ego, np.linalg.inv(T)),
        )

    assert free_ego.sum() > 1000 and free_peer.sum() > 1000  # the road between the buildings is seen through
    assert both(T_true) < 0.05
    assert both(T_true @ se2(np.pi, 0.0, 0.0)) > cfg.max_conflict


def test_a_pose_whose_conflict_exceeds_the_bound_is_refused_and_says_why(monkeypatch):
    """The refusal's wiring: the same right pose stands at the measured conflict and is refused (success false,
    free_space_conflict, a note) when the conflict exceeds max_conflict. The measurement is replaced by a fixed 0.5
    here; the tests above check the measurement itself."""
    T_true = se2(np.radians(8.0), 45.0, 2.0)
    aligner, ego, peer = _street_pair(T_true)
    res = aligner.align(ego, peer)
    assert res.success and res.acquisition.best.conflict <= aligner.config.free_space.max_conflict
    monkeypatch.setattr(free_space, "conflict", lambda *args: 0.5)
    refused = aligner.align(ego, peer)
    assert not refused.success and refused.reason == "free_space_conflict"
    assert any("free-space conflict 0.50" in n for n in refused.notes)
    lenient = Aligner(aligner.config.model_copy(update={"free_space": FreeSpaceConfig(max_conflict=1.0)}))
    assert lenient.align(ego, peer).success


def test_a_best_pose_the_free_space_rules_out_gives_way_to_the_next():
    """Hypotheses, best first: a half turn of the truth (a street's alias, refined; the free space rules it out) and
    the truth 1.5 m / 2 deg off, unrefined (what the coarse stage leaves of a hypothesis it ranked lower). The alias
    is dropped, the next is refined fully, onto the truth, and its conflict measured again there; with the alias
    alone nothing is left."""
    from bb_align.engine.box_poses import BoxSet
    from bb_align.engine.refine import bev_samples, peer_normals

    T_true = se2(np.radians(8.0), 45.0, 2.0)
    aligner, ego, peer = _street_pair(T_true)
    cfg = aligner.config
    rf, fs = cfg.refine, cfg.free_space
    (pts,) = bev_samples(peer.bev, rf.min_pixel_value, [rf.max_peer_points], cfg.seed)
    sample = (pts, peer_normals(peer.bev, pts, rf))
    boxes = (BoxSet.of(ego.boxes), BoxSet.of(peer.boxes))
    args = (ego.cloud(rf), covisible(ego, cfg), sample, boxes, fs.rival_conflict, cfg)

    alias = Hypothesis(T_true @ se2(np.pi, 0.0, 0.0), 10, fitness=0.3, refined=True)
    off = Hypothesis(se2(np.radians(2.0), 1.5, 0.0) @ T_true, 8, fitness=0.1)
    hyps = [alias, off]
    free_space.conflicts(ego, peer, hyps, cfg)
    assert alias.conflict > fs.rival_conflict  # what the half turn's conflict is (measured, not set)
    kept = free_space.without_ruled_out(ego, peer, hyps, *args)
    assert kept == [off] and off.refined and off.conflict <= fs.max_conflict
    assert pose_error(se3_from_se2(off.T), se3_from_se2(T_true))[0] < 0.3
    assert free_space.without_ruled_out(ego, peer, [alias], *args) == []


def test_a_pose_chosen_because_the_best_gave_way_must_be_clear_of_the_free_space(monkeypatch):
    """The wiring, with the measurement replaced: the true pose (the best) is made to conflict (0.5) and every other
    pose, here its half turn, to conflict a little (0.05: no rival is ruled out by that, and a best pose would pass
    max_conflict 0.10). The truth gives way, the half turn is judged, and at 0.05 it is not clear enough for a pose
    chosen that way (gave_way_max_conflict 0.03): refused, saying so. With the rule off the truth itself is refused."""
    T_true = se2(np.radians(8.0), 45.0, 2.0)
    aligner, ego, peer = _street_pair(T_true)

    def fake_conflict(free, near, bev, pts, T):
        errors = [pose_error(se3_from_se2(X), se3_from_se2(T_true)) for X in (T, np.linalg.inv(T))]
        return 0.5 if any(t < 3.0 and r < 3.0 for t, r in errors) else 0.05

    def with_half_turn(*args, **kwargs):  # the street offers one clear hypothesis: add its alias, turned round
        return [*hypotheses_of(*args, **kwargs), Hypothesis(T_true @ se2(np.pi, 0.0, 0.0), 10)]

    hypotheses_of = hypotheses.pose_hypotheses
    monkeypatch.setattr(acquirer, "pose_hypotheses", with_half_turn)
    monkeypatch.setattr(free_space, "conflict", fake_conflict)
    # Every other gate open (the calibration's multi_open): only the free space decides here.
    cfg = with_overrides(aligner.config, ["acquire.min_margin=1.0", "acquire.min_evidence=0.0", "acquire.first_k=0"])
    aligner = Aligner(cfg)
    res = aligner.align(ego, peer)
    assert not res.success and res.reason == "free_space_conflict"
    assert any("the free space rules out" in n for n in res.notes) and any("conflict 0.05" in n for n in res.notes)
    lenient = aligner.config.free_space.model_copy(update={"gave_way_max_conflict": 0.10})
    res_lenient = Aligner(aligner.config.model_copy(update={"free_space": lenient})).align(ego, peer)
    assert res_lenient.reason != "free_space_conflict"  # the bound, not max_conflict, refused the half turn
    off = aligner.config.free_space.model_copy(update={"ruled_out_first": False})
    res_off = Aligner(aligner.config.model_copy(update={"free_space": off})).align(ego, peer)
    assert res_off.reason == "free_space_conflict" and any("conflict 0.50" in n for n in res_off.notes)


def test_a_pose_chosen_after_others_gave_way_needs_the_images_own_evidence(monkeypatch):
    """As above, with the half turn clear enough (gave_way_max_conflict 0.10) but the images' evidence short of
    acquire.min_evidence: a pose the free space chose is not carried by box evidence alone, it is refused."""
    T_true = se2(np.radians(8.0), 45.0, 2.0)
    aligner, ego, peer = _street_pair(T_true)

    def fake_conflict(free, near, bev, pts, T):
        errors = [pose_error(se3_from_se2(X), se3_from_se2(T_true)) for X in (T, np.linalg.inv(T))]
        return 0.5 if any(t < 3.0 and r < 3.0 for t, r in errors) else 0.05

    def with_half_turn(*args, **kwargs):
        return [*hypotheses_of(*args, **kwargs), Hypothesis(T_true @ se2(np.pi, 0.0, 0.0), 10)]

    hypotheses_of = hypotheses.pose_hypotheses
    monkeypatch.setattr(acquirer, "pose_hypotheses", with_half_turn)
    monkeypatch.setattr(free_space, "conflict", fake_conflict)
    overrides = ["acquire.min_margin=1.0", "acquire.first_k=0", "free_space.gave_way_max_conflict=0.10"]
    res = Aligner(with_overrides(aligner.config, [*overrides, "acquire.min_evidence=100.0"])).align(ego, peer)
    assert not res.success and res.reason == "ambiguous_bv"
    assert any("box evidence alone does not carry it" in n for n in res.notes)
    enough = Aligner(with_overrides(aligner.config, [*overrides, "acquire.min_evidence=0.0"])).align(ego, peer)
    assert not any("box evidence alone" in n for n in enough.notes)  # with the evidence there, the rule is silent
