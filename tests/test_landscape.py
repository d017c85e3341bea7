"""The pose landscape (engine.landscape) against hand-built images: a known transform, a corridor with no cross
structure, a street repeating every 6 m, and the score kernel against a plain numpy computation."""

from __future__ import annotations

import numpy as np
import pytest

from bb_align.engine.bev import BevImage
from bb_align.engine.config import LandscapeConfig, RefineConfig
from bb_align.engine.geometry import se2, se2_params
from bb_align.engine.landscape import Fields, landscape, likelihood_field, score_grid, with_refinement, with_rivals
from bb_align.engine.refine import bev_cloud, bev_points

RES, RANGE = 0.4, 40.0  # 200 x 200 pixels, the sensor at the centre
CFG = LandscapeConfig()


def _image(points_xy: np.ndarray) -> BevImage:
    bev = BevImage(image=np.zeros((200, 200), np.uint8), resolution_m=RES, range_m=RANGE)
    rc = np.floor(bev.metre_to_pixel(points_xy) + 0.5).astype(int)
    ok = (rc >= 0).all(axis=1) & (rc < 200).all(axis=1)
    bev.image[rc[ok, 0], rc[ok, 1]] = 200
    return bev


def _segment(p0, p1, step: float = 0.1) -> np.ndarray:
    n = max(2, int(np.hypot(p1[0] - p0[0], p1[1] - p0[1]) / step))
    return np.linspace(p0, p1, n)


def _street(posts_every_m: float | None, rng_seed: int = 0) -> np.ndarray:
    """Two facades along x at y = +-8 m; posts (small squares) along the kerbs: irregularly spaced, or every
    ``posts_every_m`` metres (a street that repeats)."""
    parts = [_segment((-90, 8), (90, 8)), _segment((-90, -8), (90, -8))]
    rng = np.random.default_rng(rng_seed)
    xs = np.arange(-90, 90, posts_every_m) if posts_every_m else np.sort(rng.uniform(-90, 90, 36))
    for i, x in enumerate(xs):
        y = 5.5 if i % 2 else -5.5
        parts.append(np.array([[x + dx, y + dy] for dx in (-0.2, 0.2) for dy in (-0.2, 0.2)]))
    return np.concatenate(parts)


def _pair(world_xy: np.ndarray, T_ego_peer: np.ndarray):
    """The ego sees the world as is; the peer sees it from T_ego_peer (its points in its own frame)."""
    ego = _image(world_xy)
    T_peer_ego = np.linalg.inv(T_ego_peer)
    peer = _image(world_xy @ T_peer_ego[:2, :2].T + T_peer_ego[:2, 2])
    return bev_cloud(ego, RefineConfig()), bev_points(peer)


def test_score_kernel_matches_plain_numpy():
    walls_at_edges = [_segment((-90, y), (90, y)) for y in (-39.5, 39.5)] + [
        _segment((x, -90), (x, 90)) for x in (-39.5, 39.5)
    ]
    ego, pts = _pair(np.concatenate([_street(None), *walls_at_edges]), se2(np.radians(3.0), 4.0, 1.0))
    T = se2(np.radians(2.5), 3.6, 1.2)
    # and points whose grid of offsets runs partly off the fields, at every edge and corner (each point's block of
    # offsets is clipped to the fields)
    edge = np.linspace(RANGE - 0.7, RANGE + 0.7, 15) + 0.037  # off the cell boundaries: no ties in floor()
    across = np.linspace(-30.0, 30.0, 15) + 0.013
    at_edges_ego = np.concatenate(
        [np.column_stack([across, edge]), np.column_stack([across, -edge]), np.column_stack([edge, across])]
        + [np.column_stack([-edge, across]), np.column_stack([edge, edge]), np.column_stack([-edge, edge[::-1]])]
    )
    T_peer_ego = np.linalg.inv(T)
    pts = np.vstack([pts, at_edges_ego @ T_peer_ego[:2, :2].T + T_peer_ego[:2, 2]])
    field = likelihood_field(ego, CFG.sigma_m, CFG.step_m)
    wide = likelihood_field(ego, CFG.wide_sigma_m, CFG.step_m)
    yaws = np.radians([-0.3, 0.0, 0.4])
    scores = score_grid((field, wide), ego, pts, T, yaws, 2, CFG.step_m)
    yaw0, tx, ty = se2_params(T)
    for k, dyaw in enumerate(yaws):
        for a in range(5):
            for b in range(5):
                c, s = np.cos(yaw0 + dyaw), np.sin(yaw0 + dyaw)
                x = c * pts[:, 0] - s * pts[:, 1] + tx + (a - 2) * CFG.step_m
                y = s * pts[:, 0] + c * pts[:, 1] + ty + (b - 2) * CFG.step_m
                r = np.floor((RANGE - x) / CFG.step_m).astype(int)
                q = np.floor((RANGE - y) / CFG.step_m).astype(int)
                ok = (r >= 0) & (q >= 0) & (r < field.shape[0]) & (q < field.shape[1])
                expected = field[r[ok], q[ok]].astype(np.float64).sum() / wide[r[ok], q[ok]].astype(np.float64).sum()
                assert scores[k, a, b] == pytest.approx(expected, abs=1e-7)


def test_the_fields_built_per_ego_frame_are_the_plain_fields_to_the_bit():
    # Fields.of builds both grids' layouts in place (fewer multi-MB temporaries); the plain construction, each
    # field on its own then laid out, must give the same floats: the landscape's answers do not move.
    ego, _ = _pair(_street(None), se2(np.radians(3.0), 4.0, 1.0))
    fields = Fields.of(ego, CFG)
    for step, built in ((2 * CFG.step_m, fields.coarse), (CFG.step_m, fields.fine)):
        narrow, wide = likelihood_field(ego, CFG.sigma_m, step), likelihood_field(ego, CFG.wide_sigma_m, step)
        plain = np.stack([narrow[:, ::-1], wide[:, ::-1]], axis=2).reshape(narrow.shape[0], -1)
        assert built.dtype == np.float32 and np.array_equal(built, plain)


def test_the_peak_is_the_known_transform_and_its_covariance_covers_the_start():
    T_true = se2(np.radians(2.0), 12.0, 0.5)
    ego, pts = _pair(_street(None), T_true)
    fields = Fields.of(ego, CFG)
    T_start = se2(np.radians(2.8), 13.3, -0.3)  # 1.5 m and 0.8 deg off
    land = landscape(ego, fields, pts, T_start, CFG)
    err = np.array(se2_params(land.T)) - np.array(se2_params(T_true))
    assert not land.at_edge
    assert np.hypot(err[1], err[2]) < 0.25 and abs(np.degrees(err[0])) < 0.2, err
    sig = np.sqrt(np.diag(land.covariance))
    assert np.all(np.abs(err) <= 3 * sig), (err, sig)  # the answer's uncertainty covers its error
    assert sig[1] < 0.5 and sig[2] < 0.5


def test_a_window_whose_peak_lies_at_its_edge_moves_onto_the_peak():
    T_true = se2(np.radians(2.0), 12.0, 0.5)
    ego, pts = _pair(_street(None), T_true)
    fields = Fields.of(ego, CFG)
    T_start = se2(np.radians(2.0), 9.0, 0.5)  # 3 m short along the street: the peak lies 0.2 m inside the window
    fixed = landscape(ego, fields, pts, T_start, CFG.model_copy(update={"follow_peak": False}))
    assert fixed.at_edge  # the window that stays put sees no bounded peak
    land = landscape(ego, fields, pts, T_start, CFG)
    assert not land.at_edge
    err = np.array(se2_params(land.T)) - np.array(se2_params(T_true))
    assert np.hypot(err[1], err[2]) < 0.25 and abs(np.degrees(err[0])) < 0.2, err
    assert np.all(np.abs(err) <= 3 * np.sqrt(np.diag(land.covariance)))


def test_a_peak_beyond_the_first_window_is_not_climbed_to():
    T_true = se2(np.radians(2.0), 12.0, 0.5)
    ego, pts = _pair(_street(None), T_true)
    T_start = se2(np.radians(2.0), 7.0, 0.5)  # 5 m short: the truth lies beyond the 3.2 m window
    land = landscape(ego, Fields.of(ego, CFG), pts, T_start, CFG)
    assert land.at_edge and np.sqrt(land.covariance[1, 1]) > 100.0  # no answer from a window that had to climb
    assert np.allclose(land.T, T_start)


def test_a_peak_at_the_yaw_edge_is_a_disagreement_not_followed():
    T_true = se2(np.radians(2.0), 12.0, 0.5)
    ego, pts = _pair(_street(None), T_true)
    T_start = se2(np.radians(3.4), 12.0, 0.5)  # 1.4 deg off, at the yaw window's edge (1.5 deg)
    land = landscape(ego, Fields.of(ego, CFG), pts, T_start, CFG)
    # The refinement's known failure is to stop short along a street, not a turn: the window does not move in yaw,
    # and a peak it cannot bound leaves the pose unanswered (a yaw-following window answered two simulated poses
    # 1.1 deg off whose refined yaw was right).
    assert land.at_edge and np.allclose(land.T, T_start)


def test_a_corridor_without_cross_structure_is_unbounded_along_it():
    walls = np.concatenate([_segment((-35, 8), (35, 8)), _segment((-35, -8), (35, -8))])
    T_true = se2(0.0, 10.0, 0.0)
    ego, pts = _pair(walls, T_true)
    T_start = se2(0.0, 10.5, 0.2)
    land = landscape(ego, Fields.of(ego, CFG), pts, T_start, CFG)
    assert land.at_edge
    assert np.sqrt(land.covariance[1, 1]) > 100.0  # unbounded along the walls: never a confident answer
    assert np.allclose(land.T, T_start)  # following the corridor's peak led nowhere: the pose stays put


def test_a_street_repeating_every_6_m_counts_its_repeats_as_modes():
    T_true = se2(0.0, 10.0, 0.0)
    ego, pts = _pair(_street(6.0), T_true)
    fields = Fields.of(ego, CFG)
    main = landscape(ego, fields, pts, T_true, CFG)
    # Alone, the grid (3.2 m each way) sees one post pattern; the same pattern 6 m on (two posts' period, 12 m,
    # on one kerb) is a rival as good as the answer.
    rivals = [se2(0.0, 10.0 + 12.0, 0.0), se2(0.0, 10.0 - 12.0, 0.0)]
    cov, weights = with_rivals(main, ego, fields, pts, rivals, CFG)
    assert max(weights) > 0.3  # as good as the answer, up to the pattern's ends
    assert np.sqrt(cov[1, 1]) > 3.0  # the answer could be 12 m either way: far beyond any success bound
    assert np.sqrt(cov[2, 2]) < 0.5  # across the street it is still pinned


def test_a_distinct_worse_rival_leaves_the_covariance_alone():
    T_true = se2(np.radians(2.0), 12.0, 0.5)
    ego, pts = _pair(_street(None), T_true)
    fields = Fields.of(ego, CFG)
    main = landscape(ego, fields, pts, T_true, CFG)
    cov, weights = with_rivals(main, ego, fields, pts, [se2(np.radians(180.0), -12.0, 0.0)], CFG)
    assert weights[0] < 1e-6
    assert np.allclose(cov, main.covariance, atol=1e-6)


def test_a_refined_pose_the_landscape_rules_out_widens_the_covariance_to_span_both():
    T_true = se2(np.radians(2.0), 12.0, 0.5)
    ego, pts = _pair(_street(None), T_true)
    main = landscape(ego, Fields.of(ego, CFG), pts, T_true, CFG)
    near = np.array(main.T) @ se2(0.0, 0.05, 0.0)  # within the landscape's 1 sigma: the refined pose stands
    T, cov = with_refinement(main, near, 11.345)
    assert np.allclose(T, near) and np.allclose(cov, main.covariance)
    far = se2(np.radians(2.0), 14.5, 0.5)  # 2.5 m along x: two estimators disagree
    T, cov = with_refinement(main, far, 11.345)
    assert np.allclose(T, main.T)
    d = np.array(se2_params(far)) - np.array(se2_params(main.T))
    np.testing.assert_allclose(cov, main.covariance + 0.5 * np.outer(d, d), atol=1e-12)  # two modes, equal weight
    assert np.sqrt(cov[1, 1]) > 1.5  # the answer may be either pose: never within a 1 m bound
