"""DAIR-V2X-C layout: the reader on hand-written files, system_error_offset on a hand-worked case, and
recover / eval end to end on a simulated V2I root checked against the simulator's truth."""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bb_align.engine.geometry import pose_error
from bb_align.io.dair import (
    COOP_DIR,
    DairFrameFiles,
    calib_text,
    find_dair_root,
    read_calib,
    read_labels,
    read_pairs,
    reference,
    with_system_error_offset,
    write_dair_root,
)
from bb_align.io.dataset import iter_frames, world_to_x_pose, x_to_world


def _rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _tree_digest(root: Path) -> dict[str, str]:
    out = {}
    for dirpath, _, files in os.walk(root):
        for f in files:
            p = Path(dirpath) / f
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def test_calibration_and_labels_read_as_dair_writes_them(tmp_path):
    T = x_to_world([3.0, -4.0, 0.5, 1.0, 30.0, -2.0])
    p = tmp_path / "lidar_i2v.json"
    p.write_text(calib_text(T))
    assert np.allclose(read_calib(p), T)
    # DAIR's lidar_to_novatel nests the transform: the nesting and other keys are kept when rewritten
    nested = tmp_path / "nested.json"
    nested.write_text(json.dumps({"transform": json.loads(calib_text(np.eye(4))), "note": "x"}))
    text = calib_text(T, json.loads(nested.read_text()))
    assert json.loads(text)["note"] == "x" and json.loads(text)["transform"]["translation"][2] == [0.5]
    nested.write_text(text)
    assert np.allclose(read_calib(nested), T)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "translation": [[0], [0], [0]]}))
    with pytest.raises(ValueError, match="'rotation' is not a rotation"):
        read_calib(bad)
    bad.write_text(json.dumps({"rotation": np.eye(3).tolist()}))
    with pytest.raises(ValueError, match="'translation'"):
        read_calib(bad)

    labels = tmp_path / "labels.json"
    labels.write_text(
        json.dumps(
            [
                {
                    "type": "Car",
                    "3d_location": {"x": 1, "y": 2, "z": -1},
                    "3d_dimensions": {"h": 1.5, "w": 1.8, "l": 4.2},
                    "rotation": 0.3,
                },  # fmt: skip
                {
                    "type": "Pedestrian",
                    "3d_location": {"x": 5, "y": 5, "z": -1},
                    "3d_dimensions": {"h": 1.7, "w": 0.5, "l": 0.5},
                    "rotation": 0.0,
                },  # fmt: skip
                {
                    "type": "truck",
                    "3d_location": {"x": -9, "y": 0, "z": -0.5},
                    "3d_dimensions": {"h": 3.0, "w": 2.5, "l": 9.0},
                    "rotation": -1.0,
                },  # fmt: skip
            ]
        )
    )
    boxes = read_labels(labels)  # vehicle classes only, any case; [x, y, z, l, w, h, yaw]
    assert np.allclose(boxes, [[1, 2, -1, 4.2, 1.8, 1.5, 0.3], [-9, 0, -0.5, 9.0, 2.5, 3.0, -1.0]])
    assert len(read_labels(labels, classes=None)) == 3
    labels.write_text(json.dumps([{"type": "Car", "3d_location": {"x": 1}}]))
    with pytest.raises(ValueError, match=r"labels.json\[0\]: needs 3d_location"):
        read_labels(labels)


def test_system_error_offset_is_a_world_shift_rotated_into_the_vehicle_frame(tmp_path):
    # The vehicle LiDAR faces world +y (yaw 90 deg): a world shift of the roadside unit by (+1, 0) is, seen from
    # the vehicle, a shift to its right: (0, -1) in the vehicle frame.
    T = with_system_error_offset(np.eye(4), (1.0, 0.0), _rz(90.0))
    assert np.allclose(T[:3, 3], [0.0, -1.0, 0.0]) and np.allclose(T[:3, :3], np.eye(3))
    assert np.allclose(with_system_error_offset(np.eye(4), (1.0, 0.0), None)[:3, 3], [1.0, 0.0, 0.0])

    # Through the reader: novatel_to_world turns 90 deg, lidar_to_novatel (nested, as DAIR ships it) is identity.
    base = _tiny_root(tmp_path / "r", offset=(1.0, 0.0))
    calib = base / "vehicle-side" / "calib"
    for sub, R in (("novatel_to_world", _rz(90.0)), ("lidar_to_novatel", np.eye(3))):
        (calib / sub).mkdir(parents=True)
        T4 = np.eye(4)
        T4[:3, :3] = R
        text = calib_text(T4) if sub == "novatel_to_world" else json.dumps({"transform": json.loads(calib_text(T4))})
        (calib / sub / "000001.json").write_text(text)
    (pair,), _ = read_pairs(base)
    T_file, kind = reference(base, pair)
    T_off, kind_off = reference(base, pair, system_error_offset=True)
    assert kind == "lidar_i2v" and kind_off == "lidar_i2v+offset(world)"
    assert np.allclose(T_off[:3, 3] - T_file[:3, 3], [0.0, -1.0, 0.0])
    g = next(iter_frames(base, system_error_offset=True))
    assert np.allclose(g.peers[0].T_world_sensor, T_off)


def _tiny_root(root: Path, offset=(0.0, 0.0), n: int = 1) -> Path:
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        pts = np.column_stack([rng.uniform(-20, 20, (500, 3)), rng.uniform(0, 1, 500)]).astype(np.float32)
        boxes = np.array([[5.0, 1.0, -1.0, 4.5, 1.9, 1.6, 0.2]])
        T = x_to_world([10.0 + i, 2.0, -0.4, 0.5, 20.0, -0.5])
        frames.append(DairFrameFiles(f"{i + 1:06d}", f"{i + 7:06d}", pts, pts[:300], boxes, boxes, T, offset))
    return write_dair_root(root, frames)


def test_reader_takes_the_root_or_its_parent_and_reads_dair_pcds(tmp_path):
    base = _tiny_root(tmp_path, n=3)
    assert base == tmp_path / COOP_DIR and find_dair_root(tmp_path) == base == find_dair_root(base)
    # the clouds as DAIR ships them: binary_compressed, vehicle intensity uint8 with a float64 timestamp
    head = (base / "vehicle-side" / "velodyne" / "000001.pcd").read_bytes()[:400].decode("latin-1")
    assert "FIELDS x y z intensity timestamp" in head and "TYPE F F F U F" in head and "binary_compressed" in head
    head = (base / "infrastructure-side" / "velodyne" / "000007.pcd").read_bytes()[:400].decode("latin-1")
    assert "FIELDS x y z intensity" in head and "TYPE F F F F" in head
    for root in (tmp_path, base):
        groups = list(iter_frames(root))
        assert [g.timestamp for g in groups] == ["000001", "000002", "000003"]
    g = groups[1]
    assert list(g.agents) == ["vehicle-side", "infrastructure-side"] and g.peers[0].timestamp == "000008"
    assert np.allclose(g.ego.T_world_sensor, np.eye(4))
    assert np.allclose(g.peers[0].T_world_sensor, x_to_world([11.0, 2.0, -0.4, 0.5, 20.0, -0.5]))
    assert g.ego.load_points().shape == (500, 4) and g.peers[0].load_points().shape == (300, 4)
    assert len(g.ego.detections) == 1 and g.ego.extra["detections_from"] == "labels"
    # a frame with a missing cloud is left out, and said so
    (base / "infrastructure-side" / "velodyne" / "000008.pcd").unlink()
    pairs, skipped = read_pairs(tmp_path)
    assert [p.vehicle_id for p in pairs] == ["000001", "000003"] and "000008.pcd" in skipped[0]
    info = json.loads((base / "cooperative" / "data_info.json").read_text())
    info[0]["system_error_offset"] = {"delta_x": "a", "delta_y": 0}
    (base / "cooperative" / "data_info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"data_info.json\[0\]: 'system_error_offset'"):
        read_pairs(tmp_path)


@pytest.fixture(scope="module")
def v2i_root(tmp_path_factory) -> Path:
    from bb_align.cli import app

    root = tmp_path_factory.mktemp("v2i") / "dair"
    r = CliRunner().invoke(app, ["sim", str(root), "--dair", "--scenarios", "2", "--frames", "2", "--seed", "4"])
    assert r.exit_code == 0 and "DAIR-V2X-C layout" in r.output, r.output
    return root


def test_simulated_v2i_root_recovered_against_the_truth(v2i_root, tmp_path):
    from bb_align.cli import app
    from bb_align.lab.sim.v2i import read_truth, score_against_truth

    truth = read_truth(v2i_root)
    before = _tree_digest(v2i_root)
    out = tmp_path / "out"
    runner = CliRunner()
    r1 = runner.invoke(app, ["recover", str(v2i_root), str(out), "--limit", "1", "--quiet"])
    assert r1.exit_code == 0, r1.output
    assert "detections: labels" in r1.output and "run the same command again" in r1.output
    r2 = runner.invoke(app, ["recover", str(v2i_root), str(out), "--quiet"])  # resumes
    assert r2.exit_code == 0, r2.output
    assert _tree_digest(v2i_root) == before  # ROOT untouched

    rows = [json.loads(line) for line in (out / "recovered_poses.jsonl").read_text().splitlines()]
    assert sorted(r["timestamp"] for r in rows) == sorted(truth) and len(rows) == 4
    pairs, _ = read_pairs(out)  # the written copy, through the project's reader
    recovered = 0
    for p in pairs:
        T_true, T_out = truth[p.vehicle_id], read_calib(p.lidar_i2v)
        T_in = read_calib(v2i_root / COOP_DIR / "cooperative" / "calib" / "lidar_i2v" / f"{p.vehicle_id}.json")
        t_in, r_in = pose_error(T_in, T_true)
        assert t_in == pytest.approx(4.0, abs=1e-6) and r_in == pytest.approx(4.0, abs=1e-6)  # the corruption
        row = next(r for r in rows if r["timestamp"] == p.vehicle_id)
        if row["success"]:
            recovered += 1
            t_err, r_err = pose_error(T_out, T_true)
            assert t_err < 0.5 and r_err < 0.5, (p.vehicle_id, t_err, r_err)
            x_out, x_in = world_to_x_pose(T_out), world_to_x_pose(T_in)
            assert x_out[2] == pytest.approx(x_in[2]) and x_out[3] == pytest.approx(x_in[3], abs=1e-9)
            assert x_out[5] == pytest.approx(x_in[5], abs=1e-9)  # z, roll and pitch kept
        else:
            assert np.allclose(T_out, T_in)  # a refused frame keeps the file
    assert recovered >= 3, rows
    s = json.loads((out / "recover_summary.json").read_text())
    assert s["layout"] == "dair-v2x-c" and s["frames"] == 4 and s["recovered"] == recovered
    # the before/after scoring used in docs/dair.md: every corrupted file is 4 m / 4 deg off (no success at any
    # lambda), the recovered ones are successes at lambda 1
    before, after = score_against_truth(v2i_root, v2i_root), score_against_truth(out, v2i_root)
    assert before["frames"] == after["frames"] == 4 and before["success_at_m"]["3"] == 0.0
    assert after["success_at_m"]["1"] == pytest.approx(recovered / 4)


def test_recover_refuses_tracking_on_a_dair_root(v2i_root, tmp_path):
    from bb_align.cli import app

    r = CliRunner().invoke(app, ["recover", str(v2i_root), str(tmp_path / "o"), "--track", "--quiet"])
    assert r.exit_code == 2 and "--track" in r.output and "DAIR-V2X-C" in r.output


def test_cli_names_the_bad_file_and_field(tmp_path):
    from bb_align.cli import app

    base = _tiny_root(tmp_path / "r")
    calib = base / "cooperative" / "calib" / "lidar_i2v" / "000001.json"
    calib.write_text(json.dumps({"rotation": [[1, 0, 0], [0, 1, 0]], "translation": [[0], [0], [0]]}))
    runner = CliRunner()
    for args in (["eval", str(tmp_path / "r"), "--workers", "1"], ["recover", str(base), str(tmp_path / "o")]):
        r = runner.invoke(app, args)
        assert r.exit_code == 2, r.output
        flat = "".join(c for c in r.output if c not in "│ \n")  # the message, unwrapped from the error box
        assert "000001.json" in flat and "'rotation'mustbe3x3" in flat and "Traceback" not in r.output
