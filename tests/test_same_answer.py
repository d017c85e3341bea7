"""Same data, same answer: `recover`, `eval` and `track` share one de-skew default and one option
(--deskew/--no-deskew), and recover and eval give the same poses on the same small simulated set of distorted
sweeps (the simulator's default: each sweep carries its motion, 'sweep_twist')."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.main import get_command
from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.engine.geometry import pose_error
from bb_align.io.dataset import iter_frames
from bb_align.io.defaults import DESKEW_DEFAULT
from bb_align.lab.sim.scenario import SimConfig
from bb_align.lab.sim.writer import write_scenario


def test_recover_eval_and_track_share_one_deskew_option_and_default():
    from bb_align.io.recover import RecoverConfig
    from bb_align.lab.evaluation import EvalConfig
    from bb_align.lab.tracking.replay import ReplayConfig

    group = get_command(app)
    for name in ("recover", "eval", "track"):
        ctx = group.make_context("bb-align", [name, "--help"], resilient_parsing=True)
        (opt,) = [p for p in group.get_command(ctx, name).params if p.name == "deskew"]
        assert opt.opts == ["--deskew"] and opt.secondary_opts == ["--no-deskew"], name
        assert opt.default is DESKEW_DEFAULT, name
    for cfg in (RecoverConfig(), EvalConfig(), ReplayConfig()):
        assert cfg.deskew is DESKEW_DEFAULT


@pytest.fixture(scope="module")
def distorted(tmp_path_factory):
    """A scenario of two cars 8-22 m apart, sweeps rendered with self-motion distortion (without de-skew, recover's
    pose of this pair moved by 0.02 m and 0.03 deg: enough for the comparison below, at 1e-6, to tell)."""
    root = tmp_path_factory.mktemp("same") / "root"
    write_scenario(root, seed=5, index=0, n_scenarios=2, config=SimConfig(min_distance_m=8.0, max_distance_m=22.0))
    groups = list(iter_frames(root))
    assert len(groups) == 1 and all("sweep_twist" in a.extra for g in groups for a in (g.ego, *g.peers))
    return root, groups


def test_recover_and_eval_give_the_same_poses_on_the_same_data(distorted, tmp_path):
    from bb_align.lab.evaluation import EvalConfig
    from bb_align.lab.evaluation.runner import evaluate_dataset

    root, groups = distorted
    records = evaluate_dataset(root, EvalConfig(), workers=1, progress=False)
    assert len(records) == 1 and all(r.deskewed for r in records)
    out = CliRunner().invoke(app, ["recover", str(root), str(tmp_path / "out"), "--quiet"])
    assert out.exit_code == 0, out.output
    rows = {
        (r["scenario"], r["agent"]): r for r in map(json.loads, (tmp_path / "out" / "recovered_poses.jsonl").open())
    }
    truth = {
        (g.scenario, p.agent): np.linalg.inv(g.ego.T_world_sensor) @ p.T_world_sensor for g in groups for p in g.peers
    }
    for rec in records:
        row = rows[(rec.scenario, rec.peer)]
        t_err, r_err = pose_error(np.asarray(row["T_ego_peer"]), truth[(rec.scenario, rec.peer)])
        assert row["success"] == rec.success and row["reason"] == rec.reason
        assert (row["inliers_bv"], row["inliers_box"]) == (rec.inliers_bv, rec.inliers_box)
        assert t_err == pytest.approx(rec.t_err_m, abs=1e-6) and r_err == pytest.approx(rec.r_err_deg, abs=1e-6)
    assert sum(r.success for r in records) >= 1  # the set is not all failures: the poses compared are real answers
