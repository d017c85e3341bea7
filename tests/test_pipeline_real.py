"""End to end on real scans (../shared/data; skipped with a reason when absent)."""

import numpy as np
import pytest

from bb_align import Aligner
from bb_align.engine.geometry import pose_error
from realdata import av2_scan, kitti_scan, moved_copy, nuscenes_scan


@pytest.fixture(scope="module")
def aligner():
    return Aligner()


def test_kitti_pair_matches_icp_reference(shared_data, aligner):
    T_ref = np.loadtxt(shared_data / "kitti_seq08_pair" / "T_velo0_velo49_icp_refined.txt")
    res = aligner.align(
        aligner.prepare(kitti_scan(shared_data, "000000")), aligner.prepare(kitti_scan(shared_data, "000049"))
    )
    t_err, r_err = pose_error(res.T_ego_peer, T_ref)
    assert res.success, res.reason
    assert t_err < 0.5 and r_err < 0.5, (t_err, r_err)


def test_kitti_without_overlap_fails_explicitly(shared_data, aligner):
    res = aligner.align(
        aligner.prepare(kitti_scan(shared_data, "000000")), aligner.prepare(kitti_scan(shared_data, "000186"))
    )
    assert not res.success
    assert res.reason in {"too_few_inliers_bv", "ambiguous_bv", "too_few_matches"}
    assert res.confidence <= 0.1


@pytest.mark.parametrize("scan", ["av2", "nuscenes"])
def test_moved_copies_of_a_real_scan(shared_data, aligner, scan):
    pts, boxes = av2_scan(shared_data) if scan == "av2" else nuscenes_scan(shared_data)
    ego = aligner.prepare(pts, boxes)
    good, report = 0, []
    for seed in range(20):
        pts_peer, boxes_peer, T_true = moved_copy(pts, boxes, seed)
        res = aligner.align(ego, aligner.prepare(pts_peer, boxes_peer))
        t_err, r_err = pose_error(res.T_ego_peer, T_true)
        ok = res.success and t_err < 1.0 and r_err < 1.0
        good += ok
        report.append((seed, round(t_err, 2), round(r_err, 2), res.inliers_bv, res.inliers_box, res.reason))
        # Never a confident wrong answer.
        assert ok or not res.success or res.confidence < 0.5, report[-1]
    assert good >= 19, report
