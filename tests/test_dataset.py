"""OPV2V / V2V4Real layout: x_to_world against hand-worked matrices and an independent rotation library, the
reader on a hand-written tiny dataset, and a writer -> reader round trip."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest
from pypcd4 import PointCloud
from scipy.spatial.transform import Rotation

from bb_align.io.dataset import (
    agent_order,
    iter_frames,
    parse_lidar_pose,
    read_agent_frame,
    world_to_x_pose,
    write_agent_frame,
    x_to_world,
)


def test_x_to_world_hand_worked():
    # yaw 90 deg: x axis -> +y, y axis -> -x; translation as given
    T = x_to_world([1.0, 2.0, 3.0, 0.0, 90.0, 0.0])
    np.testing.assert_allclose(T, [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], atol=1e-12)
    # pitch 30 deg (CARLA sign): the x axis tilts up, (1, 0, 0) -> (cos 30, 0, sin 30)
    c, s = math.cos(math.radians(30)), 0.5
    T = x_to_world([0, 0, 0, 0, 0, 30])
    np.testing.assert_allclose(T[:3, :3], [[c, 0, -s], [0, 1, 0], [s, 0, c]], atol=1e-12)
    # roll 30 deg (CARLA sign): (0, 1, 0) -> (0, cos 30, -sin 30)
    T = x_to_world([0, 0, 0, 30, 0, 0])
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, c, s], [0, -s, c]], atol=1e-12)


def test_x_to_world_matches_an_independent_rotation_library_and_inverts():
    rng = np.random.default_rng(0)
    for _ in range(50):
        x, y, z = rng.uniform(-100, 100, 3)
        roll, yaw, pitch = rng.uniform(-80, 80), rng.uniform(-180, 180), rng.uniform(-80, 80)
        T = x_to_world([x, y, z, roll, yaw, pitch])
        R_ref = Rotation.from_euler("ZYX", [yaw, -pitch, -roll], degrees=True).as_matrix()
        np.testing.assert_allclose(T[:3, :3], R_ref, atol=1e-12)
        np.testing.assert_allclose(x_to_world(world_to_x_pose(T)), T, atol=1e-9)


def test_parse_lidar_pose_forms_and_errors():
    T = x_to_world([5, -3, 1.8, 0.5, 42.0, -1.0])
    np.testing.assert_allclose(parse_lidar_pose(T.tolist()), T)
    np.testing.assert_allclose(parse_lidar_pose(T.reshape(-1).tolist()), T)
    with pytest.raises(ValueError, match="lidar_pose"):
        parse_lidar_pose([1, 2, 3, 4, 5])
    bad = T.copy()
    bad[3] = (0, 0, 1, 1)
    with pytest.raises(ValueError, match="last row"):
        parse_lidar_pose(bad.tolist())


def test_agent_order_is_numeric_when_ids_are_numbers():
    assert agent_order(["1005", "641", "-1"]) == ["-1", "641", "1005"]
    assert agent_order(["b", "a"]) == ["a", "b"]


def _pcd(path, pts):
    PointCloud.from_xyzi_points(np.asarray(pts, dtype=np.float32)).save(path)


def test_reader_on_hand_written_dataset(tmp_path):
    scen = tmp_path / "2021_08_18_19_48_05"
    for agent in ("641", "1005", "77"):
        (scen / agent).mkdir(parents=True)
    # ego 641: OPV2V 6-vector pose, one vehicle, no detections
    (scen / "641" / "000068.yaml").write_text(
        textwrap.dedent("""\
        lidar_pose: [10.0, 20.0, 1.9, 0.0, 90.0, 0.0]
        vehicles:
          1005:
            location: [30.0, 20.0, 0.0]
            center: [0.0, 0.0, 0.8]
            extent: [2.25, 0.9, 0.8]
            angle: [0.0, 180.0, 0.0]
        ego_speed: 12.5
        """)
    )
    _pcd(scen / "641" / "000068.pcd", [[1, 2, 3, 0.5], [4, 5, 6, 0.25]])
    # peer 1005: V2V4Real 4x4 pose, detections with scores
    (scen / "1005" / "000068.yaml").write_text(
        textwrap.dedent("""\
        lidar_pose:
          - [1.0, 0.0, 0.0, 30.0]
          - [0.0, 1.0, 0.0, 20.0]
          - [0.0, 0.0, 1.0, 1.8]
          - [0.0, 0.0, 0.0, 1.0]
        vehicles: {}
        detections:
          - [5.0, 1.0, -1.0, 4.5, 1.8, 1.6, 0.1]
        detection_scores: [0.9]
        """)
    )
    _pcd(scen / "1005" / "000068.pcd", [[7, 8, 9, 1.0]])
    # agent 77 has a yaml without its pcd at 000068 and a lone frame at 000069: neither makes a group with it
    (scen / "77" / "000068.yaml").write_text("lidar_pose: [0, 0, 0, 0, 0, 0]\n")
    (scen / "641" / "000069.yaml").write_text("lidar_pose: [0, 0, 0, 0, 0, 0]\n")
    _pcd(scen / "641" / "000069.pcd", [[0, 0, 0, 0]])

    groups = list(iter_frames(tmp_path))
    assert [(g.scenario, g.timestamp) for g in groups] == [("2021_08_18_19_48_05", "000068")]
    g = groups[0]
    assert list(g.agents) == ["641", "1005"]  # numeric order: 641 is the ego
    ego, peer = g.ego, g.peers[0]
    np.testing.assert_allclose(ego.T_world_sensor[:3, 3], [10, 20, 1.9])
    np.testing.assert_allclose(ego.T_world_sensor[:2, :2], [[0, -1], [1, 0]], atol=1e-12)
    # box centre = location + center, sizes = 2 * extent, yaw = radians(angle[1])
    np.testing.assert_allclose(ego.vehicles["1005"], [30, 20, 0.8, 4.5, 1.8, 1.6, math.pi])
    assert ego.detections is None and ego.extra == {"ego_speed": 12.5}
    np.testing.assert_allclose(peer.T_world_sensor[:3, 3], [30, 20, 1.8])
    np.testing.assert_allclose(peer.detections, [[5, 1, -1, 4.5, 1.8, 1.6, 0.1]])
    np.testing.assert_allclose(peer.detection_scores, [0.9])
    np.testing.assert_allclose(ego.load_points(), [[1, 2, 3, 0.5], [4, 5, 6, 0.25]])
    # true relative pose: the peer sits 20 m ahead of the ego along the ego's x axis (ego faces +y), yawed -90
    T_ego_peer = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
    np.testing.assert_allclose(T_ego_peer[:2, 3], [0, -20], atol=1e-9)
    assert len(list(iter_frames(tmp_path, min_agents=1))) == 2


def test_reader_errors_name_the_field(tmp_path):
    p = tmp_path / "x.yaml"
    p.write_text("vehicles: {}\n")
    with pytest.raises(ValueError, match="lidar_pose"):
        read_agent_frame(p)
    p.write_text("lidar_pose: [0,0,0,0,0,0]\ndetections: [[0,0,0,4,2,1.5,0]]\ndetection_scores: [0.5, 0.2]\n")
    with pytest.raises(ValueError, match="detection_scores"):
        read_agent_frame(p)
    p.write_text("lidar_pose: [0,0,0,0,0,0]\nvehicles: {3: {location: [1, 2]}}\n")
    with pytest.raises(ValueError, match="location"):
        read_agent_frame(p)
    with pytest.raises(FileNotFoundError):
        list(iter_frames(tmp_path / "missing"))


def test_writer_reader_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    pts = rng.normal(0, 10, (500, 4)).astype(np.float32)
    T = x_to_world([3.0, -4.0, 1.7, 0.3, -120.0, 0.7])
    vehicles = {12: np.array([5.0, 6.0, 0.75, 4.6, 1.9, 1.5, 0.4]), 40: np.array([-8, 2, 1.5, 10, 2.5, 3, -2.0])}
    dets = np.array([[1.0, 2.0, -1.0, 4.4, 1.8, 1.5, 3.0]])
    for agent, as_matrix in (("0", False), ("1", True)):
        write_agent_frame(
            tmp_path,
            "s",
            agent,
            "000001",
            pts,
            T,
            vehicles,
            detections=dets,
            detection_scores=[0.7],
            extra={"sensor": "vlp32c"},
            pose_as_matrix=as_matrix,
        )
    g = next(iter_frames(tmp_path))
    for a in g.agents.values():
        np.testing.assert_allclose(a.T_world_sensor, T, atol=1e-9)
        np.testing.assert_allclose(a.load_points(), pts)
        assert set(a.vehicles) == {"12", "40"}
        for k, v in vehicles.items():
            np.testing.assert_allclose(a.vehicles[str(k)], v, atol=1e-9)
        np.testing.assert_allclose(a.detections, dets)
        assert a.extra["sensor"] == "vlp32c"


def test_reader_finds_scenarios_directly_under_root_and_in_split_folders(tmp_path):
    T = x_to_world([1.0, 2.0, 0.0, 0.0, 10.0, 0.0])
    pts = np.array([[1.0, 0.0, 0.0, 0.5]] * 3, dtype=np.float32)
    for root, scen in ((tmp_path / "flat", "s1"), (tmp_path / "split", "train/s1"), (tmp_path / "split", "test/s2")):
        for agent in ("0", "1"):
            write_agent_frame(root, scen, agent, "000001", pts, T, {})
    (tmp_path / "split" / "train" / "notes").mkdir()  # a folder without agents is not a scenario
    assert [(g.scenario, list(g.agents)) for g in iter_frames(tmp_path / "flat")] == [("s1", ["0", "1"])]
    assert [g.scenario for g in iter_frames(tmp_path / "split")] == ["test/s2", "train/s1"]
