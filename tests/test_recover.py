"""`bb-align recover`: a corrected copy of a dataset. Small simulated datasets (split folders, 6-vector and 4x4
poses) with noisy reported poses, checked against the simulator's true poses; interrupt and resume; ROOT
untouched; detection files; eval on split folders; recover_frame on an OpenCOOD-style dict."""

from __future__ import annotations

import hashlib
import json
import math
import shutil

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.engine.config import AlignConfig
from bb_align.engine.geometry import pose_error
from bb_align.engine.pipeline import Aligner
from bb_align.io.dataset import iter_frames, parse_lidar_pose, world_to_x_pose
from bb_align.io.detections import boxes_from_array, corners_to_boxes, load_detection_file
from bb_align.io.recover import (
    JSONL_NAME,
    SUMMARY_NAME,
    RecoverConfig,
    YamlDetections,
    recover_dataset,
    recover_frame,
    recovered_pose_value,
)
from bb_align.lab.sim import Scenario
from bb_align.lab.sim.scenario import SimConfig
from bb_align.lab.sim.writer import write_scenario

NEAR = SimConfig(min_distance_m=8.0, max_distance_m=22.0)
OFFSET = (1.6, -1.3, 1.7)  # the "GNSS" error put on every non-ego pose: dx, dy (m), dyaw (deg)


def _noisy_value(value, as_matrix: bool):
    x = world_to_x_pose(parse_lidar_pose(value))
    x[0] += OFFSET[0]
    x[1] += OFFSET[1]
    x[4] += OFFSET[2]
    return parse_lidar_pose(x).tolist() if as_matrix else x


def _make_noisy(root, as_matrix: bool = False) -> dict:
    """Put OFFSET on every non-ego lidar_pose under root (4x4 for every agent when as_matrix); returns the true
    T_ego_peer per (scenario, timestamp, agent)."""
    truth = {}
    for g in iter_frames(root):
        scen_dir = g.ego.pcd_path.parent.parent
        for a in g.agents.values():
            truth[(g.scenario, g.timestamp, a.agent)] = np.linalg.inv(g.ego.T_world_sensor) @ a.T_world_sensor
            path = scen_dir / a.agent / f"{g.timestamp}.yaml"
            meta = yaml.safe_load(path.read_text())
            if a.agent == g.ego.agent:
                meta["lidar_pose"] = a.T_world_sensor.tolist() if as_matrix else meta["lidar_pose"]
            else:
                meta["lidar_pose"] = _noisy_value(meta["lidar_pose"], as_matrix)
            path.write_text(yaml.safe_dump(meta, sort_keys=False, default_flow_style=None))
    return truth


def _hashes(root) -> dict:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*") if p.is_file()
    }


def _plain(text: str) -> str:
    """CLI output without rich's box and line wrapping."""
    return " ".join(text.replace("│", " ").split())


def _rows(out) -> list[dict]:
    return [json.loads(line) for line in (out / JSONL_NAME).read_text().splitlines()]


@pytest.fixture(scope="module")
def split_dataset(tmp_path_factory):
    """ROOT/train (3 agents, one frame), ROOT/test (2 agents) and ROOT/validate (a peer whose cloud is 5
    points: its alignment must fail), with noisy non-ego poses; and one uninterrupted recovery of it."""
    base = tmp_path_factory.mktemp("split")
    root = base / "root"
    write_scenario(root / "train", seed=21, index=0, n_scenarios=2, n_agents=3, config=NEAR)
    write_scenario(root / "test", seed=21, index=1, n_scenarios=2, n_agents=2, config=NEAR)
    shutil.copytree(root / "test", root / "validate")
    (broken,) = [p for p in (root / "validate").glob("*/1/000000.pcd")]
    from bb_align.io.dataset import write_pcd

    write_pcd(broken, np.array([[1, 0, 0], [2, 0, 0], [3, 1, 0], [4, 1, 0], [5, 2, 0]], dtype=np.float32))
    truth = _make_noisy(root)
    before = _hashes(root)
    out = base / "out"
    res = CliRunner().invoke(app, ["recover", str(root), str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    return root, out, truth, before, res.output


def test_recover_split_layout_against_the_truth(split_dataset):
    root, out, truth, before, output = split_dataset
    assert "detections: yaml" in output and "recovered 3" in output
    rows = _rows(out)
    assert [(r["scenario"].split("/")[0], r["agent"]) for r in rows] == [
        ("test", "1"),
        ("train", "1"),
        ("train", "2"),
        ("validate", "1"),
    ]
    written = {(g.scenario, g.timestamp): g for g in iter_frames(out)}
    reported = {(g.scenario, g.timestamp): g for g in iter_frames(root)}
    for r in rows:
        key = (r["scenario"], r["timestamp"])
        g = written[key]
        assert r["ego"] == g.ego.agent == "0"
        T_written = np.linalg.inv(g.ego.T_world_sensor) @ g.agents[r["agent"]].T_world_sensor
        T_true = truth[(*key, r["agent"])]
        assert set(r) >= {"T_ego_peer", "success", "reason", "confidence", "inliers_bv", "inliers_box", "covariance"}
        if r["success"]:
            t_err, r_err = pose_error(T_written, T_true)
            assert t_err < 1.0 and r_err < 1.0, r
            assert r["pose_written"] == "recovered" and r["boxes_ego"] > 0 and r["boxes_peer"] > 0
            # z, roll and pitch are the reported ones
            np.testing.assert_allclose(
                world_to_x_pose(g.agents[r["agent"]].T_world_sensor)[2:4],
                world_to_x_pose(reported[key].agents[r["agent"]].T_world_sensor)[2:4],
                atol=1e-9,
            )
        else:  # a failure keeps the reported (noisy) pose, byte for byte in the yaml
            assert r["pose_written"] == "reported" and r["reason"]
            rel = g.agents[r["agent"]].pcd_path.with_suffix(".yaml").relative_to(out)
            assert (
                yaml.safe_load((out / rel).read_text())["lidar_pose"]
                == yaml.safe_load((root / rel).read_text())["lidar_pose"]
            )
    assert [r["success"] for r in rows] == [True, True, True, False]
    assert rows[-1]["reason"] == "too_few_points"
    # everything else copied: clouds hard-linked, ego yaml identical, ROOT untouched
    assert _hashes(root) == before
    for rel, h in before.items():
        if rel.endswith(".pcd") or "/0/" in rel:
            assert _hashes(out)[rel] == h
    pcd = next(root.rglob("*.pcd"))
    assert (out / pcd.relative_to(root)).stat().st_ino == pcd.stat().st_ino
    summary = json.loads((out / SUMMARY_NAME).read_text())
    assert summary["recovered"] == 3 and summary["kept_reported"] == 1 and summary["detections"] == "yaml"


def test_interrupted_run_resumes_to_the_same_output(split_dataset, tmp_path):
    root, full, _, before, _ = split_dataset
    out = tmp_path / "out"

    class Crash(YamlDetections):
        calls = 0

        def __call__(self, agent, points):
            Crash.calls += 1
            if Crash.calls == 5:  # ego + peer of the first frame, ego + first peer of the second
                raise KeyboardInterrupt
            return super().__call__(agent, points)

    with pytest.raises(KeyboardInterrupt):
        recover_dataset(root, out, RecoverConfig(), Crash(), progress=False)
    assert len(_rows(out)) == 1
    with open(out / JSONL_NAME, "a") as fh:  # a torn append, as if killed mid-write
        fh.write('{"scenario": "train/')
    partial = recover_dataset(root, out, RecoverConfig(), limit=1, progress=False)
    assert partial["frames_done"] == 2 and not partial["complete"]
    res = CliRunner().invoke(app, ["recover", str(root), str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    assert _hashes(out) == _hashes(full)
    assert _hashes(root) == before
    # a rerun of a finished OUT changes nothing; other settings are refused
    assert recover_dataset(root, out, RecoverConfig(), progress=False)["complete"]
    assert _hashes(out) == _hashes(full)
    res = CliRunner().invoke(app, ["recover", str(root), str(out), "--prior", "--quiet"])
    assert res.exit_code == 2 and "config.use_prior" in _plain(res.output)


def test_recover_refuses_out_inside_root_and_foreign_folders(split_dataset, tmp_path):
    root = split_dataset[0]
    for out in (root, root / "train" / "copy"):
        res = CliRunner().invoke(app, ["recover", str(root), str(out)])
        assert res.exit_code == 2 and "inside" in _plain(res.output)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    res = CliRunner().invoke(app, ["recover", str(root), str(tmp_path / "other")])
    assert res.exit_code == 2 and "not empty" in _plain(res.output)
    assert not (root / "train" / "copy").exists()


def test_recover_4x4_poses_with_corner_detection_files(tmp_path):
    """V2V4Real-style 4x4 lidar_pose, flat layout, detections as OpenCOOD (K, 8, 3) corner files."""
    root, dets = tmp_path / "root", tmp_path / "dets"
    name = write_scenario(root, seed=34, index=0, n_scenarios=1, n_agents=2, config=NEAR)
    truth = _make_noisy(root, as_matrix=True)
    for g in iter_frames(root):
        for a in g.agents.values():
            (dets / g.scenario / a.agent).mkdir(parents=True)
            np.save(dets / g.scenario / a.agent / f"{g.timestamp}.npy", _corners(a.detections))
            meta = yaml.safe_load(a.pcd_path.with_suffix(".yaml").read_text())
            del meta["detections"], meta["detection_scores"]  # only the files have boxes
            a.pcd_path.with_suffix(".yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["recover", str(root), str(out), "--detections", str(dets), "--quiet"])
    assert res.exit_code == 0, res.output
    (row,) = _rows(out)
    assert row["success"], row
    assert row["boxes_ego"] > 0 and row["boxes_peer"] > 0
    meta = yaml.safe_load((out / name / "1" / "000000.yaml").read_text())
    assert np.asarray(meta["lidar_pose"]).shape == (4, 4)  # written as read
    (g,) = list(iter_frames(out))
    t_err, r_err = pose_error(
        np.linalg.inv(g.ego.T_world_sensor) @ g.agents["1"].T_world_sensor, truth[(name, "000000", "1")]
    )
    assert t_err < 1.0 and r_err < 1.0
    # without any detections the run says so and stage 2 is skipped
    res = CliRunner().invoke(app, ["recover", str(root), str(tmp_path / "out2"), "--quiet"])
    assert res.exit_code == 0 and "stage 2 is skipped" in _plain(res.output)
    assert _rows(tmp_path / "out2")[0]["boxes_ego"] is None
    # simulated from the labels only when asked, and said so
    res = CliRunner().invoke(app, ["recover", str(root), str(tmp_path / "out3"), "--simulate-detections", "--quiet"])
    assert res.exit_code == 0 and "detections: simulated from ground truth" in _plain(res.output)
    assert _rows(tmp_path / "out3")[0]["boxes_peer"] > 0
    assert "simulated" in json.loads((tmp_path / "out3" / SUMMARY_NAME).read_text())["detections"]


def _corners(boxes: np.ndarray) -> np.ndarray:
    """OpenCOOD's boxes_to_corners_3d order: 0 front-right-bottom, 1 front-left, 2 rear-left, 3 rear-right."""
    out = []
    for x, y, z, l, w, h, yaw in boxes:
        local = np.array([[l / 2, -w / 2], [l / 2, w / 2], [-l / 2, w / 2], [-l / 2, -w / 2]])
        c, s = math.cos(yaw), math.sin(yaw)
        xy = local @ np.array([[c, s], [-s, c]]) + (x, y)
        bottom = np.column_stack([xy, np.full(4, z - h / 2)])
        out.append(np.vstack([bottom, bottom + (0, 0, h)]))
    return np.array(out).reshape(-1, 8, 3)


def test_detection_files_corners_json_and_errors(tmp_path):
    boxes = np.array([[10.0, -3.0, -0.8, 4.5, 1.9, 1.6, 0.4], [-20.0, 5.0, -1.0, 4.0, 1.8, 1.5, -2.9]])
    np.testing.assert_allclose(corners_to_boxes(_corners(boxes)), boxes, atol=1e-9)
    p = tmp_path / "a.json"
    p.write_text(json.dumps({"boxes": [dict(zip("x y z l w h yaw".split(), b)) for b in boxes], "scores": [0.9, 0.5]}))
    got, scores = load_detection_file(p)
    np.testing.assert_allclose(got, boxes)
    np.testing.assert_allclose(scores, [0.9, 0.5])
    p.write_text(json.dumps({"boxes": boxes.tolist(), "scores": [0.9]}))
    with pytest.raises(ValueError, match="scores"):
        load_detection_file(p)
    np.save(tmp_path / "b.npy", np.zeros((3, 5)))
    with pytest.raises(ValueError, match=r"b\.npy.*\(K, 7\)"):
        load_detection_file(tmp_path / "b.npy")
    assert boxes_from_array([]).shape == (0, 7)


def test_eval_on_split_folders_and_detections_only_on_request(split_dataset, tmp_path):
    root = split_dataset[0]
    summary = tmp_path / "s.json"
    res = CliRunner().invoke(app, ["eval", str(root), "--workers", "1", "--json", str(summary), "--limit", "2"])
    assert res.exit_code == 0, res.output
    s = json.loads(summary.read_text())
    assert s["pairs"] == 2 and s["detections_used"] == {"yaml": 4}
    assert set(s["detection_ap"]["true"]) == {"0-20", "20-40", "40-70", "70+", "all"}
    # a dataset without detections: none unless asked for
    bare = tmp_path / "bare"
    shutil.copytree(root / "test", bare / "test")
    for y in bare.rglob("*.yaml"):
        meta = yaml.safe_load(y.read_text())
        meta.pop("detections", None), meta.pop("detection_scores", None)
        y.write_text(yaml.safe_dump(meta, sort_keys=False))
    res = CliRunner().invoke(app, ["eval", str(bare), "--workers", "1", "--json", str(summary)])
    assert res.exit_code == 0, res.output
    assert "2 agent frames had no detections" in _plain(res.output)
    s = json.loads(summary.read_text())
    assert s["detections_used"] == {"none": 2} and s["meta"]["detections"] == "yaml"
    res = CliRunner().invoke(
        app, ["eval", str(bare), "--workers", "1", "--json", str(summary), "--simulate-detections"]
    )
    assert res.exit_code == 0, res.output
    s = json.loads(summary.read_text())
    assert s["detections_used"] == {"simulated": 2} and "simulated" in s["meta"]["detections"]


def test_recover_frame_on_an_opencood_style_dict():
    sc = Scenario(8, n_agents=3, distance_m=14.0, config=NEAR)
    sim = sc.frame(0)
    T_true = {a: np.linalg.inv(sim.agents["0"].T_world_sensor) @ s.T_world_sensor for a, s in sim.agents.items()}
    frame = {}
    for aid, s in sim.agents.items():
        pose = world_to_x_pose(s.T_world_sensor)
        if aid != "0":
            pose = _noisy_value(pose, as_matrix=aid == "2")  # agent 2 reports a 4x4
        frame[int(aid)] = {"lidar_np": s.points, "params": {"lidar_pose": pose, "detections": s.boxes}}
    out = recover_frame(frame, Aligner(AlignConfig()))
    assert out[0]["params"]["lidar_pose"] == frame[0]["params"]["lidar_pose"] and "bb_align" not in out[0]
    assert np.asarray(out[1]["params"]["lidar_pose"]).shape == (6,)
    assert np.asarray(out[2]["params"]["lidar_pose"]).shape == (4, 4)
    T_world_ego = parse_lidar_pose(out[0]["params"]["lidar_pose"])
    for aid in (1, 2):
        assert out[aid]["bb_align"]["success"], out[aid]["bb_align"]
        T = np.linalg.inv(T_world_ego) @ parse_lidar_pose(out[aid]["params"]["lidar_pose"])
        t_err, r_err = pose_error(T, T_true[str(aid)])
        assert t_err < 1.0 and r_err < 1.0
    assert frame[1]["params"]["lidar_pose"] != out[1]["params"]["lidar_pose"]  # the input is not modified
    with pytest.raises(ValueError, match=r"frame\[1\]\['params'\] needs 'lidar_pose'"):
        recover_frame({0: frame[0], 1: {"lidar_np": sim.agents["1"].points, "params": {}}}, Aligner(AlignConfig()))


def test_recovered_pose_value_keeps_format_height_and_yaw_branch():
    ego = [0.0, 0.0, 1.8, 0.0, 170.0, 0.0]
    T_world_ego = parse_lidar_pose(ego)
    reported = [5.0, 5.0, 2.1, 0.5, 350.0, -0.4]
    T_ego_peer = np.linalg.inv(T_world_ego) @ parse_lidar_pose([6.0, 4.0, 0.0, 0.0, -9.0, 0.0])
    v = recovered_pose_value(reported, T_world_ego, T_ego_peer)
    np.testing.assert_allclose(v, [6.0, 4.0, 2.1, 0.5, 351.0, -0.4], atol=1e-9)
    m = recovered_pose_value(parse_lidar_pose(reported).reshape(-1).tolist(), T_world_ego, T_ego_peer)
    assert len(m) == 16
    np.testing.assert_allclose(np.asarray(m).reshape(4, 4), parse_lidar_pose(v), atol=1e-9)


def test_recover_with_tracking_follows_each_peer_through_the_sequence(tmp_path):
    """--track: one acquisition per peer, then the refinement from the track's prediction, frame after frame;
    the written poses against the simulator's truth."""
    from bb_align.lab.sim.sweep import write_sweep

    root, out = tmp_path / "root", tmp_path / "out"
    write_sweep(root, seed=9, index=0, frames=8)  # receding from ~5 m
    truth = _make_noisy(root)
    res = CliRunner().invoke(app, ["recover", str(root), str(out), "--track", "--prior", "--quiet"])
    assert res.exit_code == 0, res.output
    rows = _rows(out)
    assert len(rows) == 8 and rows[0]["source"] == "acquisition"
    assert [r["source"] for r in rows[1:]].count("tracking") >= 6, [r["source"] for r in rows]
    written = {(g.scenario, g.timestamp): g for g in iter_frames(out)}
    for r in rows:
        assert r["success"], r
        g = written[(r["scenario"], r["timestamp"])]
        T_written = np.linalg.inv(g.ego.T_world_sensor) @ g.agents[r["agent"]].T_world_sensor
        t_err, r_err = pose_error(T_written, truth[(r["scenario"], r["timestamp"], r["agent"])])
        assert t_err < 0.5 and r_err < 0.5, (r["timestamp"], t_err, r_err)
