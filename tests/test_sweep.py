"""Swept sequences for tracking: the spacing sweeps as each kind says, odometry is locally accurate and drifts
slowly, reported (GNSS) poses are metres off."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from bb_align.engine.geometry import pose_error, se2
from bb_align.io.dataset import parse_lidar_pose
from bb_align.lab.sim.sweep import SWEEP_KINDS, PoseSensors, SweepConfig, sweep_scenario, write_sweep


def _spacing(sc, t: float) -> float:
    ego, peer = (sc.world.vehicles[a.vehicle] for a in sc.agents)
    (xe, ye, _), (xp, yp, _) = ego.pose(t), peer.pose(t)
    return float(np.hypot(xe - xp, ye - yp))


@pytest.mark.parametrize("kind", SWEEP_KINDS)
def test_each_kind_sweeps_the_spacing_as_it_says(kind):
    T = 15.0
    sc = sweep_scenario(1234, kind, T, SweepConfig())
    d = np.array([_spacing(sc, t) for t in np.linspace(0, T, 31)])
    assert d.min() < 20 and d.max() > (50 if kind == "overtaking" else 100), (kind, d.round(1))
    expected_end = {
        "receding": (d[-1] > 100),
        "approaching": (d[-1] < 20),
        "overtaking": (d[0] > 40 and d[-1] > 40),
        "oncoming": (d[0] > 100 and d[-1] > 100),
        "crossing": (d[0] > 60 and d[-1] > 60),
    }
    assert expected_end[kind], (kind, d.round(1))
    ego, peer = (sc.world.vehicles[a.vehicle] for a in sc.agents)
    assert ego.speed > 0 and peer.speed > 0  # both drive


def test_odometry_is_locally_accurate_and_gnss_is_metres_off():
    rng = np.random.default_rng(0)
    cfg = SweepConfig()
    sensors = PoseSensors(rng, cfg, dt=0.1)
    W = [np.eye(4) for _ in range(150)]
    for k in range(150):  # a car driving 10 m/s on a gentle curve
        T2 = se2(0.01 * k * 0.1, 10.0 * k * 0.1, 0.02 * (k * 0.1) ** 2)
        W[k][:2, :2], W[k][:2, 3] = T2[:2, :2], T2[:2, 2]
    out = [sensors.step(w) for w in W]
    odo, gnss = [o for o, _ in out], [g for _, g in out]
    # Over 1 s the odometry's motion matches the truth to a few centimetres; over 15 s it drifts, but < 2 % of 150 m.
    t1, r1 = pose_error(np.linalg.inv(odo[40]) @ odo[50], np.linalg.inv(W[40]) @ W[50])
    assert t1 < 0.05 and r1 < 0.05
    t15, _ = pose_error(np.linalg.inv(odo[0]) @ odo[149], np.linalg.inv(W[0]) @ W[149])
    assert 0.0 < t15 < 3.0
    assert pose_error(odo[0], W[0])[0] > 10  # the odometry frame is the car's own, not the world
    g = np.array([pose_error(gi, wi) for gi, wi in zip(gnss, W)])
    assert 0.5 < np.median(g[:, 0]) < 6.0 and np.median(g[:, 1]) > 0.2  # 2 m / 2 deg class


def test_written_sweep_carries_odometry_and_gnss(tmp_path):
    name = write_sweep(tmp_path, seed=2, index=0, frames=3)
    assert name.endswith("receding")
    y = [yaml.safe_load((tmp_path / name / "1" / f"{k:06d}.yaml").read_text()) for k in range(3)]
    true = [parse_lidar_pose(v["lidar_pose"]) for v in y]
    odo = [parse_lidar_pose(v["odometry_pose"]) for v in y]
    assert all(v["sweep"] == "receding" and "gnss_pose" in v for v in y)
    t, r = pose_error(np.linalg.inv(odo[0]) @ odo[2], np.linalg.inv(true[0]) @ true[2])
    assert t < 0.05 and r < 0.05
    moved = np.hypot(*(true[2][:2, 3] - true[0][:2, 3]))
    assert 1.0 < moved < 6.0  # 0.2 s of a peer at 10-30 m/s


def test_crossing_sweeps_only_when_asked(tmp_path):
    """`bb-align sim --sweep --family crossing`: every sequence a crossing; an unknown kind is refused by name."""
    from bb_align.lab.sim.sweep import write_sweeps

    names = write_sweeps(tmp_path, 2, 2, seed=3, workers=1, progress=False, kinds=("crossing",))
    assert [n.rsplit("_", 1)[1] for n in names] == ["crossing", "crossing"]
    y = yaml.safe_load((tmp_path / names[0] / "1" / "000000.yaml").read_text())
    assert y["sweep"] == "crossing"
    with pytest.raises(ValueError, match="kinds must be among"):
        write_sweeps(tmp_path, 1, 2, kinds=("sideways",))
