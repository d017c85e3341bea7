"""Evaluation: AP and BV IoU on hand-checked cases, the graph-matching baseline on a known transform, and a
small simulated end-to-end run through the CLI (sim -> eval --json --plots)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bb_align.engine.boxes import transform_boxes
from bb_align.engine.geometry import pose_error, se2
from bb_align.lab.evaluation.ap import ApAccumulator, bev_iou, match_frame, nms_bev, voc_ap
from bb_align.lab.evaluation.baseline import graph_match
from bb_align.lab.evaluation.summary import accuracy, anchor_metrics


def test_bev_iou_hand_checked():
    a = np.array([[0, 0, 0, 4, 2, 1.5, 0.0]])
    # same box turned 90 deg: overlap 2 x 2 = 4, union 8 + 8 - 4 = 12
    assert bev_iou(a, [[0, 0, 5, 4, 2, 1, np.pi / 2]])[0, 0] == pytest.approx(1 / 3, abs=1e-4)
    # shifted 1 m along its length: overlap 3 x 2 = 6, union 10 (heights do not matter)
    assert bev_iou(a, [[1, 0, 0, 4, 2, 9, 0.0]])[0, 0] == pytest.approx(0.6, abs=1e-4)
    # heading flipped by 180 deg: the same rectangle
    assert bev_iou(a, [[0, 0, 0, 4, 2, 1.5, np.pi]])[0, 0] == pytest.approx(1.0, abs=1e-4)
    assert bev_iou(a, [[10, 0, 0, 4, 2, 1.5, 0.0]])[0, 0] == 0.0


def test_voc_ap_hand_checked():
    # scores 0.9 (TP), 0.8 (FP), 0.7 (TP), 4 ground-truth boxes:
    # recall 0.25, 0.25, 0.5; precision 1, 0.5, 2/3; envelope 1, 2/3, 2/3
    # AP = 0.25 * 1 + (0.5 - 0.25) * 2/3 = 0.41667
    assert voc_ap(np.array([0.9, 0.8, 0.7]), np.array([1, 0, 1]), 4) == pytest.approx(0.25 + 0.25 * 2 / 3)
    assert voc_ap(np.array([0.5, 0.9]), np.array([1, 1]), 2) == pytest.approx(1.0)
    acc = ApAccumulator()  # pooled over frames, sorted by score across them: same numbers
    acc.add([0.9], [True], 1)
    acc.add([0.8, 0.7], [False, True], 3)
    assert acc.ap() == pytest.approx(0.25 + 0.25 * 2 / 3)


def test_match_frame_uses_each_ground_truth_once_and_nms_removes_duplicates():
    gt = np.array([[0, 0, 0, 4, 2, 1.5, 0.0], [10, 0, 0, 4, 2, 1.5, 0.0]])
    pred = np.array([[0.2, 0, 0, 4, 2, 1.5, 0.0], [0.0, 0, 0, 4, 2, 1.5, 0.0], [10.5, 0.5, 0, 4, 2, 1.5, 0.0]])
    scores = np.array([0.6, 0.9, 0.8])
    # 0.9 takes gt 0; 0.8: IoU with gt 1 = (3.5*1.5)/(16-5.25) = 0.49 -> FP at 0.5; 0.6 duplicate -> FP
    np.testing.assert_array_equal(match_frame(pred, scores, gt, 0.5), [False, True, False])
    np.testing.assert_array_equal(match_frame(pred, scores, gt, 0.45), [False, True, True])
    np.testing.assert_array_equal(np.sort(nms_bev(pred, scores, 0.15)), [1, 2])


def test_graph_matching_baseline_recovers_a_known_transform():
    rng = np.random.default_rng(4)
    n = 9
    boxes_ego = np.column_stack(
        [
            rng.uniform(-40, 40, (n, 2)),
            np.zeros(n),
            rng.uniform(4, 5, n),
            rng.uniform(1.7, 2.0, n),
            np.full(n, 1.5),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )
    T_ego_peer = se2(np.radians(35.0), 12.0, -7.0)
    boxes_peer = transform_boxes(np.linalg.inv(T_ego_peer), boxes_ego)
    boxes_peer[:, :2] += rng.normal(0, 0.1, (n, 2))
    boxes_peer = boxes_peer[rng.permutation(n)]
    res = graph_match(boxes_ego, boxes_peer)
    assert res.success and res.matches >= 7
    t_err, r_err = pose_error(res.T_ego_peer, T_ego_peer)
    assert t_err < 0.3 and r_err < 0.5
    assert not graph_match(boxes_ego[:1], boxes_peer[:1]).success


def test_accuracy_counts_failures_as_failures():
    s = accuracy(np.array([0.2, 0.3, 5.0, 0.1]), np.array([0.1, 0.2, 3.0, 0.1]), np.array([1, 1, 1, 0], bool))
    assert s["pairs"] == 4 and s["success_rate"] == 0.75
    assert s["frac_under_1m_1deg"] == 0.5  # the failed pair's small error does not count
    assert s["frac_under_1m_1deg_raw"] == 0.75
    assert s["median_t_err_m"] == pytest.approx((0.3 + 5.0) / 2)  # errors 0.2, 0.3, 5.0, inf
    assert accuracy(np.ones(3), np.ones(3), np.zeros(3, bool))["median_t_err_m"] is None


def test_anchor_metrics_hand_worked():
    # pairs (t m, r deg, success): a (0.5, 0.2, ok) b (1.5, 0.5, ok) c (0.8, 2.5, ok) d (2.9, 2.9, ok)
    # e (0.1, 0.1, refused) f (9, 9, ok)
    t = np.array([0.5, 1.5, 0.8, 2.9, 0.1, 9.0])
    r = np.array([0.2, 0.5, 2.5, 2.9, 0.1, 9.0])
    ok = np.array([1, 1, 1, 1, 0, 1], bool)
    a = anchor_metrics(t, r, ok)
    # lambda 1: a only; 2: a, b (c fails on rotation); 3: a, b, c, d; e is refused, never a success
    assert a["success_at_m"] == {"1": pytest.approx(1 / 6), "2": pytest.approx(2 / 6), "3": pytest.approx(4 / 6)}
    assert a["mRTE_m"]["1"] == pytest.approx(0.5) and a["mRRE_deg"]["1"] == pytest.approx(0.2)
    assert a["mRTE_m"]["2"] == pytest.approx(1.0) and a["mRRE_deg"]["2"] == pytest.approx(0.35)
    assert a["mRTE_m"]["3"] == pytest.approx((0.5 + 1.5 + 0.8 + 2.9) / 4)
    assert a["mRRE_deg"]["3"] == pytest.approx((0.2 + 0.5 + 2.5 + 2.9) / 4)
    none = anchor_metrics(np.array([5.0]), np.array([5.0]), np.array([True]))
    assert none["success_at_m"]["3"] == 0.0 and none["mRTE_m"]["3"] is None and none["mRRE_deg"]["1"] is None
    assert accuracy(t, r, ok)["success_at_m"] == a["success_at_m"]  # every accuracy block carries them


def test_simulated_end_to_end_through_the_cli(tmp_path):
    from bb_align.cli import app

    runner = CliRunner()
    data = tmp_path / "sim"
    out = runner.invoke(
        app,
        [
            "sim",
            str(data),
            "--scenarios",
            "3",
            "--seed",
            "5",
            "--min-distance",
            "5",
            "--max-distance",
            "25",
            "--workers",
            "1",
        ],
    )
    assert out.exit_code == 0, out.output
    summary_path, plots = tmp_path / "summary.json", tmp_path / "plots"
    out = runner.invoke(
        app,
        [
            "eval",
            str(data),
            "--json",
            str(summary_path),
            "--plots",
            str(plots),
            "--workers",
            "1",
            "--pose-noise",
            "2,2",
            "--records",
            str(tmp_path / "pairs.jsonl"),
        ],
    )
    assert out.exit_code == 0, out.output
    s = json.loads(summary_path.read_text())
    # Each record carries its covariance and its true error in the same parameters: the error's translation part
    # is the translation error measured independently (pose_error), and the summary counts what it covers.
    rows = [json.loads(line) for line in (tmp_path / "pairs.jsonl").read_text().splitlines()]
    for r in rows:
        assert np.hypot(*r["error_params"][1:]) == pytest.approx(r["t_err_m"], abs=1e-6)
        assert abs(np.degrees(r["error_params"][0])) == pytest.approx(r["r_err_deg"], abs=1e-6)
    cov = s["covariance_coverage"]
    assert cov["pairs"] == sum(r["success"] and r["covariance"] is not None for r in rows) >= 2
    assert 0.0 <= cov["frac_d2_within_chi2_99"] <= 1.0 and (plots / "fig15_covariance_vs_true_error.png").exists()
    for key in (
        "pairs",
        "success_rate",
        "frac_under_1m_1deg",
        "median_t_err_m",
        "median_r_err_deg",
        "by_distance",
        "stage1_only",
        "baseline_graph_matching",
        "detection_ap",
        "by_common_cars",
        "by_inliers_bv",
    ):
        assert key in s
    assert s["pairs"] == 3
    assert set(s["by_distance"]) == {"0-20", "20-40", "40-70", "70+"}
    # the anchors' metrics, recomputed from the records by hand, overall and in every distance bucket
    for lam in (1, 2, 3):
        hits = [r for r in rows if r["success"] and r["t_err_m"] < lam and r["r_err_deg"] < lam]
        assert s["success_at_m"][str(lam)] == pytest.approx(len(hits) / len(rows))
        assert s["mRTE_m"][str(lam)] == pytest.approx(np.mean([r["t_err_m"] for r in hits]))
        assert s["mRRE_deg"][str(lam)] == pytest.approx(np.mean([r["r_err_deg"] for r in hits]))
        for name, b in s["by_distance"].items():
            if b["pairs"]:
                lo, hi = {"0-20": (0, 20), "20-40": (20, 40), "40-70": (40, 70), "70+": (70, 1e9)}[name]
                sel = [r for r in rows if lo <= r["distance_m"] < hi]
                n_hit = sum(r["success"] and r["t_err_m"] < lam and r["r_err_deg"] < lam for r in sel)
                assert b["success_at_m"][str(lam)] == pytest.approx(n_hit / len(sel))
    # short range, heterogeneous sensors, distortion on: the engine recovers these pairs
    assert s["frac_under_1m_1deg"] >= 2 / 3
    assert s["frac_under_1m_1deg"] <= s["success_rate"]
    ap = s["detection_ap"]
    assert ap["true"]["all"]["ap@0.5"] > ap["noisy"]["all"]["ap@0.5"]
    assert len(list(plots.glob("*.png"))) >= 10
    bad = runner.invoke(app, ["eval", str(data), "--pose-noise", "2"])
    assert bad.exit_code != 0 and "pose-noise" in bad.output


def test_eval_simulates_detections_only_when_asked(tmp_path):
    """An OPV2V-style dataset without 'detections': no boxes (stage 2 skipped) unless simulate_detections, then
    boxes come from the detector model on the labels."""
    from bb_align.io.dataset import write_agent_frame
    from bb_align.lab.evaluation import EvalConfig, evaluate_dataset
    from bb_align.lab.sim import Scenario

    sc = Scenario(11, n_agents=2, distance_m=12.0)
    frame = sc.frame(0)
    for aid, agent in frame.agents.items():
        vehicles = {v.vid: v.box(frame.stamp) for v in sc.world.vehicles if v.vid != agent.vehicle_id}
        write_agent_frame(tmp_path, "opv2v_like", aid, "000000", agent.points, agent.T_world_sensor, vehicles)
    (bare,) = evaluate_dataset(tmp_path, EvalConfig(), workers=1, progress=False)
    assert bare.ego_boxes == 0 and bare.peer_boxes == 0
    assert bare.ego_detections == bare.peer_detections == "none"
    (rec,) = evaluate_dataset(tmp_path, EvalConfig(simulate_detections=True), workers=1, progress=False)
    assert rec.ego_detections == rec.peer_detections == "simulated"
    assert rec.ego_boxes > 0 and rec.peer_boxes > 0 and rec.common_cars > 0
    assert rec.distance_m == pytest.approx(12.0, abs=2.0)
    assert set(rec.ap) == {"noisy", "recovered", "true"}
    assert rec.ap["true"]["all"]["n_gt"] > 0


def test_deskew_boxes_moves_a_box_as_its_centre_was_fired():
    """Hand-worked: a car driving straight at 10 m/s sees a box on its left (azimuth +90 deg) a quarter sweep
    before mid-sweep (t = -0.025 s, clockwise), so the box is reported 0.25 m ahead of where it is at mid-sweep;
    turning at 1 rad/s the box also turns by -0.025 rad with the frame. Centre and heading follow deskew_sweep."""
    from bb_align.io.sweeps import deskew_boxes
    from bb_align_client.deskew import deskew_sweep

    box = np.array([[0.0, 10.0, -1.0, 4.5, 1.9, 1.6, 0.3]])
    straight = deskew_boxes(box, (10.0, 0.0), 0.0, 0.1)
    np.testing.assert_allclose(straight[0], [-0.25, 10.0, -1.0, 4.5, 1.9, 1.6, 0.3], atol=1e-12)
    turning = deskew_boxes(box, (10.0, 0.0), 1.0, 0.1)
    centre = deskew_sweep(box[:, :3], (10.0, 0.0), 1.0, times_s=np.array([-0.025]))
    np.testing.assert_allclose(turning[0, :3], centre[0], atol=1e-12)
    assert turning[0, 6] == pytest.approx(0.3 - 0.025, abs=1e-12)
    assert deskew_boxes(np.zeros((0, 7)), (10.0, 0.0), 0.0, 0.1).shape == (0, 7)


def test_eval_de_skews_a_distorted_simulated_sweep_with_the_motion_its_yaml_carries(tmp_path):
    """The simulator writes each distorted sweep's twist; it matches the car's motion between two frames (an
    independent finite difference of the written poses), and eval de-skews the cloud with it: each static point
    lands where the simulator's own kinematics put it at mid-sweep (the sensor's pose at the point's firing time,
    moved into the mid-sweep frame), which the raw sweep misses by a good part of the car's travel."""
    from bb_align.engine.pipeline import Aligner
    from bb_align.io.dataset import iter_frames
    from bb_align.lab.evaluation import EvalConfig
    from bb_align.lab.evaluation.runner import _load_agent
    from bb_align.lab.sim import Scenario
    from bb_align.lab.sim.raycast import cast_sweep, sensor_pose
    from bb_align.lab.sim.scenario import SimConfig
    from bb_align.lab.sim.writer import write_scenario_frames

    sc = Scenario(30, n_agents=2, distance_m=15.0)  # the ego drives at 14 m/s and turns
    write_scenario_frames(tmp_path, "moving", sc, frames=2)
    f0, f1 = (g.ego for g in iter_frames(tmp_path))
    twist = f0.extra["sweep_twist"]
    T01 = np.linalg.inv(f0.T_world_sensor) @ f1.T_world_sensor
    speed = np.hypot(*T01[:2, 3]) / 0.1
    assert speed > 10.0
    assert twist["vx_mps"] == pytest.approx(T01[0, 3] / 0.1, rel=0.05)
    assert twist["vy_mps"] == pytest.approx(T01[1, 3] / 0.1, abs=0.05 * speed)
    assert twist["period_s"] == pytest.approx(0.1)

    aligner = Aligner()
    raw = _load_agent(f0, aligner, EvalConfig(deskew=False), "moving", f0.timestamp)
    mended = _load_agent(f0, aligner, EvalConfig(), "moving", f0.timestamp)
    assert mended.deskewed and not raw.deskewed
    # the same sweep again, with each point's firing time and owner (frame() draws its noise from this rng)
    spec, t_mid = sc.agents[0], f0.extra["timestamp_s"]
    sweep = cast_sweep(
        sc.world,
        spec.vehicle,
        spec.sensor,
        spec.mount,
        t_mid,
        np.random.default_rng([sc.seed, 2, 0, 0]),
        spec.beam_error_deg,
        distortion=True,
    )
    np.testing.assert_allclose(sweep.points[:, :3], raw.points[:, :3], atol=1e-4)
    x, y, yaw = sensor_pose(sc.world, spec.vehicle, spec.mount, sweep.time)
    xm, ym, yawm = (float(np.ravel(v)[0]) for v in sensor_pose(sc.world, spec.vehicle, spec.mount, np.array([t_mid])))
    p = sweep.points
    wx = np.cos(yaw) * p[:, 0] - np.sin(yaw) * p[:, 1] + x - xm
    wy = np.sin(yaw) * p[:, 0] + np.cos(yaw) * p[:, 1] + y - ym
    exact = np.stack([np.cos(yawm) * wx + np.sin(yawm) * wy, -np.sin(yawm) * wx + np.cos(yawm) * wy], axis=1)
    static = sweep.owner < 0
    off_raw = np.linalg.norm(raw.points[static, :2] - exact[static], axis=1)
    off_mended = np.linalg.norm(mended.points[static, :2] - exact[static], axis=1)
    travel = speed * 0.1
    assert np.percentile(off_raw, 90) > 0.3 * travel  # the tear: up to half the travel either side of the seam
    assert np.percentile(off_mended, 90) < 0.02 * travel
    # a frozen sweep is already de-skewed: nothing written, nothing undone
    assert (
        Scenario(30, n_agents=2, distance_m=15.0, config=SimConfig(distortion=False)).frame(0).agents["0"].twist is None
    )


@pytest.mark.parametrize(
    "twist", [{"vx_mps": 1.0}, "fast", {"vx_mps": "a", "vy_mps": 0, "yaw_rate_rps": 0, "period_s": 0.1}]
)
def test_a_malformed_sweep_twist_is_refused_by_name(twist):
    """A yaml whose sweep_twist is not the four numbers is refused naming the frame and the field, never guessed."""
    from pathlib import Path

    from bb_align.io.dataset import AgentFrame
    from bb_align.io.sweeps import sweep_twist as _sweep_twist

    frame = AgentFrame("sc", "1", "000000", Path("x.pcd"), np.eye(4), {}, extra={"sweep_twist": twist})
    with pytest.raises(ValueError, match="sc/1/000000: sweep_twist"):
        _sweep_twist(frame)
    assert _sweep_twist(AgentFrame("sc", "1", "000000", Path("x.pcd"), np.eye(4), {})) is None
