"""End to end on a synthetic street (no external data): known transforms, explicit failures."""

import numpy as np
import pytest

from bb_align import AlignConfig, Aligner, SuccessRule, make_bev
from bb_align.engine.boxes import transform_boxes
from bb_align.engine.geometry import pose_error, se2, se3_from_se2
from synthetic import synthetic_world, view_from


@pytest.fixture(scope="module")
def world():
    return synthetic_world(seed=0)


def _pair(world, yaw_deg, t_xy, seed=0):
    pts_w, boxes_w = world
    T_world_ego = se3_from_se2(se2(0.0, 0.0, 0.0))
    T_world_peer = se3_from_se2(se2(np.radians(yaw_deg), *t_xy))
    pts_ego = view_from(pts_w, T_world_ego, seed=seed)
    pts_peer = view_from(pts_w, T_world_peer, seed=seed + 1, sensor_height=1.5)
    boxes_ego = transform_boxes(np.eye(3), boxes_w)
    boxes_peer = transform_boxes(np.linalg.inv(se2(np.radians(yaw_deg), *t_xy)), boxes_w)
    T_ego_peer = np.linalg.inv(T_world_ego) @ T_world_peer
    return pts_ego, boxes_ego, pts_peer, boxes_peer, T_ego_peer


@pytest.mark.parametrize("yaw_deg,t_xy", [(0.0, (15.0, 0.0)), (-172.0, (-25.0, 3.0)), (63.0, (8.0, -30.0))])
def test_recovers_known_relative_pose(world, yaw_deg, t_xy):
    pts_ego, boxes_ego, pts_peer, boxes_peer, T_true = _pair(world, yaw_deg, t_xy)
    aligner = Aligner()
    res = aligner.align(aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, boxes_peer))
    t_err, r_err = pose_error(res.T_ego_peer, T_true)
    assert res.success, res.reason
    assert t_err < 0.3 and r_err < 0.3
    assert res.inliers_bv > 25 and res.inliers_box > 6 and res.box_pairs >= 2
    assert 0.5 < res.confidence <= 1.0
    assert res.T_ego_peer.shape == (4, 4)
    assert res.yaw_deg == pytest.approx(yaw_deg, abs=0.3)
    assert {"mim", "descriptors"} <= set(aligner.prepare(pts_ego).timings_ms)


def test_prepared_ego_is_reusable_and_results_are_deterministic(world):
    pts_ego, _, pts_peer, _, T_true = _pair(world, 40.0, (10.0, 10.0))
    aligner = Aligner()
    ego = aligner.prepare(make_bev(pts_ego))
    peer = aligner.prepare(make_bev(pts_peer))
    a, b = aligner.align(ego, peer), aligner.align(ego, peer)
    np.testing.assert_array_equal(a.T_ego_peer, b.T_ego_peer)
    assert a.success and "stage 2 skipped: no boxes from ego and peer" in a.notes
    assert pose_error(a.T_ego_peer, T_true)[0] < 0.3


@pytest.mark.parametrize("waiver", [None, 1.0, 1e6])
def test_stage2_failure_keeps_stage1_pose(world, waiver):
    """Boxes that pair nowhere: stage 2 vetoes the pose (whatever the waiver: no box supports it) and keeps it."""
    pts_ego, boxes_ego, pts_peer, boxes_peer, T_true = _pair(world, 10.0, (12.0, 0.0))
    aligner = Aligner(AlignConfig.model_validate({"acquire": {"stage2_waiver_evidence": waiver}}))
    far_boxes = boxes_peer.copy()
    far_boxes[:, :2] += 500.0  # nothing overlaps
    res = aligner.align(aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, far_boxes))
    assert not res.success and res.reason == "no_box_overlap"
    assert not res.stage2_applied and res.inliers_bv > 25
    assert pose_error(res.T_ego_peer, T_true)[0] < 0.5, "stage-1 pose is kept when only stage 2 fails"
    assert res.confidence <= 0.5


def test_strong_dense_evidence_stands_with_too_few_box_corners(world):
    """One box of the peer's pairs where it should, the rest were moved away: too few corners for stage 2's bar,
    but the search everywhere found the pose with evidence far above the default waiver, so it stands. Without a
    waiver, or with one above its evidence, stage 2 vetoes it. With a prior the search everywhere still runs
    first, and its waiver stands too (only a pose found inside the prior's window alone gets no waiver)."""
    pts_ego, boxes_ego, pts_peer, boxes_peer, T_true = _pair(world, 10.0, (12.0, 0.0))
    aligner = Aligner()
    one_box = boxes_peer.copy()  # row i is the same car as the ego's row i
    one_box[1:, :2] += 500.0  # only the first pairs: its four corners are below min_inliers_box (6)
    ego, peer = aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, one_box)
    res = aligner.align(ego, peer)
    evidence = res.acquisition.margin * res.acquisition.best.relative_fitness
    assert evidence >= AlignConfig().acquire.stage2_waiver_evidence
    assert res.success and any(
        n.startswith("stage 2 could not verify (too_few_inliers_box); accepted") for n in res.notes
    )
    assert pose_error(res.T_ego_peer, T_true)[0] < 0.3 and not res.stage2_applied
    with_prior = aligner.align(ego, peer, T_prior=T_true)
    assert with_prior.success, "the search everywhere runs first with a prior too: its waiver stands"
    for waiver in (None, 2.0 * evidence):
        strict = Aligner(AlignConfig.model_validate({"acquire": {"stage2_waiver_evidence": waiver}}))
        vetoed = strict.align(strict.prepare(pts_ego, boxes_ego), strict.prepare(pts_peer, one_box))
        assert not vetoed.success and vetoed.reason == "too_few_inliers_box"


def test_requiring_boxes_fails_without_them(world):
    pts_ego, _, pts_peer, _, _ = _pair(world, 0.0, (10.0, 0.0))
    aligner = Aligner(AlignConfig(success=SuccessRule(require_boxes=True)))
    res = aligner.align(aligner.prepare(pts_ego), aligner.prepare(pts_peer))
    assert not res.success and res.reason == "no_boxes"


def test_explicit_failures():
    aligner = Aligner()
    empty = aligner.prepare(np.zeros((0, 3), np.float32))
    some = aligner.prepare(np.random.default_rng(0).uniform(-5, 5, (50, 3)).astype(np.float32))
    res = aligner.align(empty, some)
    assert not res.success and res.reason == "too_few_points" and res.confidence == 0.0
    flat = np.column_stack([np.random.default_rng(1).uniform(-50, 50, (20000, 2)), np.zeros(20000)])
    a = aligner.prepare(flat)
    assert aligner.align(a, a).reason == "empty_image"


def test_unrelated_scenes_are_not_a_confident_pose():
    aligner = Aligner()
    a = aligner.prepare(view_from(synthetic_world(seed=1)[0], np.eye(4)))
    b = aligner.prepare(view_from(synthetic_world(seed=2)[0], np.eye(4)))
    res = aligner.align(a, b)
    assert not res.success and res.confidence <= 0.1


def test_paper_mode_applies_the_box_correction(world):
    from bb_align.engine.config import BoxConfig

    pts_ego, boxes_ego, pts_peer, boxes_peer, T_true = _pair(world, 25.0, (14.0, -6.0))
    aligner = Aligner(AlignConfig(box=BoxConfig(apply="always")))
    res = aligner.align(aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, boxes_peer))
    assert res.success and res.stage2_applied
    np.testing.assert_allclose(res.T_ego_peer[:2, :2], (res.T_box @ res.T_bv)[:2, :2], atol=1e-12)
    assert pose_error(res.T_ego_peer, T_true)[0] < 0.3


def test_prior_pose_gates_matches_in_paper_mode(world):
    """Paper mode: the prior gates the descriptor matches (multi mode's window: tests/test_acquire.py)."""
    from bb_align.engine.config import AcquireConfig
    from bb_align.engine.geometry import se2_params

    pts_ego, _, pts_peer, _, T_true = _pair(world, 120.0, (30.0, -12.0))
    aligner = Aligner(AlignConfig(acquire=AcquireConfig(mode="paper")))
    ego, peer = aligner.prepare(pts_ego), aligner.prepare(pts_peer)
    yaw, tx, ty = se2_params(T_true)
    noisy = se2(yaw + np.radians(3.0), tx + 2.5, ty - 2.0)  # GPS-grade prior: metres and degrees off
    res = aligner.align(ego, peer, T_prior=noisy)
    assert res.success and "matches gated by the prior pose" in res.notes
    assert pose_error(res.T_ego_peer, T_true)[0] < 0.3
    wrong = se2(yaw + np.pi / 2, tx + 40.0, ty)  # a prior far from the truth leaves no consistent evidence
    res = aligner.align(ego, peer, T_prior=wrong)
    assert not res.success


def test_warm_reference_gives_the_same_result(world):
    pts_ego, boxes_ego, pts_peer, boxes_peer, _ = _pair(world, 70.0, (20.0, 4.0))
    aligner = Aligner()
    cold = aligner.align(aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, boxes_peer))
    ego = aligner.warm(aligner.prepare(pts_ego, boxes_ego))
    assert ego._reference is not None and ego._cloud is not None
    warm = aligner.align(ego, aligner.prepare(pts_peer, boxes_peer))
    np.testing.assert_array_equal(cold.T_ego_peer, warm.T_ego_peer)
    assert warm.timings_ms["matching"] < cold.timings_ms["matching"] + 1000  # sanity: no rebuild error


def test_boxes_that_contradict_the_refined_pose_refuse_it(world):
    """The peer's boxes all 1.5 m off (a mis-calibrated detector): stage 2 still pairs them, but as a measurement they
    disagree with the densely refined pose beyond chi2(3) 99 %. Two independent measurements contradict each other,
    so the alignment fails, keeping the refined pose; with box.fuse_disagreement_fails off the boxes are left out
    and the refined pose stands. The same boxes unshifted are fused. (2 m off, at the pairing gate, they pair fewer
    under the true pose than under a half-turn alias: the acquisition refuses first, test_acquire's rule.)"""
    pts_ego, boxes_ego, pts_peer, boxes_peer, T_true = _pair(world, 10.0, (12.0, 0.0))
    shifted = boxes_peer.copy()
    shifted[:, 0] += 1.5
    aligner = Aligner()
    ego, peer = aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, shifted)
    res = aligner.align(ego, peer)
    assert not res.success and res.reason == "box_correction_too_large", (res.reason, res.notes)
    assert "box measurement disagrees with the refined pose: refused" in res.notes
    assert pose_error(res.T_ego_peer, T_true)[0] < 0.5

    lenient = Aligner(AlignConfig.model_validate({"box": {"fuse_disagreement_fails": False}}))
    kept = lenient.align(ego, peer)
    assert kept.success and "box measurement left out: disagrees" in kept.notes
    assert pose_error(kept.T_ego_peer, T_true)[0] < 0.3

    fused = aligner.align(ego, aligner.prepare(pts_peer, boxes_peer))
    assert fused.success and "box measurement fused with the refined pose" in fused.notes
