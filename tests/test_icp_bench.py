"""The ICP yardstick of benchmarks/icp_from_prior.py: its wrapper recovers a known transform of a real scan from a
prior 2 m / 2 deg off, in the project's frame convention (T_a_b maps points of b into a)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from bb_align.engine.geometry import pose_error, rotation_rpy, se2, se2_params

pytest.importorskip("small_gicp", reason="small_gicp (the `bench` extra) is not installed")

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SCAN = DATA / "kitti_seq08_pair" / "000000.bin"
pytestmark = pytest.mark.skipif(not SCAN.exists(), reason="../shared/data (real KITTI scans) is not present")


def _bench():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "icp_from_prior.py"
    spec = importlib.util.spec_from_file_location("bench_icp_from_prior", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_icp_recovers_a_known_transform_of_a_real_scan_from_a_2m_2deg_prior():
    """Ego: one half of a real KITTI scan's points within 40 m; peer: the other half seen from a sensor 6 m ahead,
    1.5 m left, 0.2 m up and turned 7 deg (so p_ego = T_true @ p_peer). Started 2 m and 2 deg off T_true on the
    ground plane (level, z = 0, as the benchmark's prior), the wrapper returns T_true within 0.1 m and 0.1 deg; its
    inverse, the other convention, lies metres away."""
    bench = _bench()
    pts = np.fromfile(SCAN, np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) < 40.0]  # the scan within 40 m: fast, and still a whole street
    rng = np.random.default_rng(8)
    half = rng.random(len(pts)) < 0.5
    T_true = np.eye(4)
    T_true[:3, :3] = rotation_rpy(0.0, 0.0, np.radians(7.0))
    T_true[:3, 3] = (6.0, 1.5, 0.2)
    ego = pts[half]
    peer = (pts[~half] - T_true[:3, 3]) @ T_true[:3, :3]  # p_peer = R^T (p_ego - t)
    yaw, tx, ty = se2_params(T_true)
    prior = se2(yaw - np.radians(2.0), tx + 2.0 * np.cos(2.4), ty + 2.0 * np.sin(2.4))
    assert pose_error(prior, T_true) == pytest.approx((2.0, 2.0))

    answer = bench.icp(ego, peer, prior, bench.IcpSettings())

    t_err, r_err = pose_error(answer.T, T_true)
    assert t_err < 0.1 and r_err < 0.1, (t_err, r_err)
    assert abs(answer.T[2, 3] - 0.2) < 0.1  # z recovered from the level z = 0 start
    assert answer.fitness > 0.5  # the two halves of one scan overlap almost everywhere
    assert pose_error(np.linalg.inv(answer.T), T_true)[0] > 5.0
