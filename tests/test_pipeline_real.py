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


def test_apollo_southbay_pair_matches_the_reference(shared_data, aligner):
    """A second city and sensor, two passes minutes apart (parked and moving objects differ), 28.5 m apart."""
    from bb_align.io.clouds import load_cloud

    d = shared_data / "apollo_southbay_pair"
    T_ref = np.loadtxt(d / "T_38908_36822.txt")  # maps points of scan 36822 into scan 38908: ego 38908
    res = aligner.align(
        aligner.prepare(load_cloud(d / "apollo_21_38908.pcd")), aligner.prepare(load_cloud(d / "apollo_21_36822.pcd"))
    )
    t_err, r_err = pose_error(res.T_ego_peer, T_ref)
    assert res.success, res.reason
    assert t_err < 0.5 and r_err < 0.5, (t_err, r_err)
    # The covariance of (yaw, tx, ty) is there and honest about this pose: the true error within chi2(3) 99 %.
    from bb_align.engine.geometry import se2_params, wrap_angle

    e = np.subtract(se2_params(T_ref), se2_params(res.T_ego_peer))
    e[0] = wrap_angle(e[0])
    assert res.covariance is not None and float(e @ np.linalg.solve(res.covariance, e)) < 11.34


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
