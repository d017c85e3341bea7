"""The maintained benchmarks (benchmarks/README.md) still run against today's code: every script imports, and
sim_vs_real's per-pair measurement, on one simulated pair, agrees with the pair's known truth."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from bb_align import AlignConfig, Aligner
from bb_align.lab.realpairs import RealPair
from bb_align.lab.sim import simulate_sequence

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(f"bench_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)  # the scripts run only under `if __name__ == "__main__"`
    return module


@pytest.mark.parametrize("path", sorted(BENCHMARKS.glob("*.py")), ids=lambda p: p.stem)
def test_benchmark_imports_and_has_a_main(path):
    assert callable(getattr(_load(path), "main", None)), f"{path.name} has no main()"


def test_every_benchmark_is_listed_in_its_readme():
    readme = (BENCHMARKS / "README.md").read_text()
    missing = [p.name for p in BENCHMARKS.glob("*.py") if f"`{p.name}`" not in readme]
    assert not missing, f"benchmarks/README.md does not list {missing}"


def test_sim_vs_real_measures_a_pair_against_its_truth():
    """A simulated pair 25 m apart: the engine answers it right with and without the seeded prior, the overlap at the
    truth is that of a real overlap, and the landscape along the baseline peaks within a cell of the truth."""
    bench = _load(BENCHMARKS / "sim_vs_real.py")
    frame = simulate_sequence(seed=5, n_frames=1, n_agents=2, distance_m=25.0)[0]
    ego, peer = frame.agents["0"], frame.agents["1"]
    T_true = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
    pair = RealPair("sim/5", "sim", Path(), Path(), T_true)
    row = bench.measure(Aligner(AlignConfig()), pair, ego.points, peer.points)
    assert row["no_prior"]["outcome"] == "right" and row["prior"]["outcome"] == "right"
    assert row["no_prior"]["covered"] and row["prior"]["covered"]
    assert row["truth_fitness"] > 0.2
    assert abs(row["peak_offset_cells"]) <= 1 and row["ramp"] <= 0.0
    assert len(row["lit_peer"]) == 4 and sum(row["lit_peer"]) > 500


def test_sim_places_runs_a_place_as_the_real_run_and_ranks_the_real_place():
    """A simulated place is rendered as the real run is: the follower's consecutive sweeps against the leader's, the
    follower moving between them, the cars 73-81 m apart; the real place's standing is worked by hand."""
    bench = _load(BENCHMARKS / "sim_places.py")
    pairs = bench.place_pairs(11 * 100003, ego_sweeps=2, peer_sweeps=1)
    assert [p.name for p, _, _ in pairs] == ["place1100033/0<-0", "place1100033/1<-0"]
    (first, ego0, peer0), (second, ego1, peer1) = pairs
    assert peer0 is peer1 and ego0 is not ego1  # one leader sweep against two follower sweeps
    assert 72.0 < first.distance_m < 83.0  # 73-81 m drawn, the follower one sweep back
    closed_in = first.distance_m - second.distance_m  # one sweep (0.1 s) at the street family's 5-16 m/s
    assert 0.4 < closed_in < 1.7
    rows = [{"place": "real", "no_prior": {"right": 8}, "prior": {"right": 18}}] + [
        {"place": f"sim {k}", "no_prior": {"right": v}, "prior": {"right": 20 - v}} for k, v in enumerate([0, 3, 8, 9])
    ]
    assert bench.standing([0, 3, 8, 9], 8) == 0.5  # places 8 and 9 do at least as well
    assert bench.standing([20, 17, 12, 11], 18) == 0.25
    for row in rows[1:]:
        for path in bench.PATHS:
            row[path].update(wrong=0, refused=20 - row[path]["right"])
    summ = bench.summary(rows)
    assert summ["places"] == 4 and summ["no_prior"]["sim_places_at_least_real"] == 0.5
    assert summ["prior"]["sim_places_none_right"] == 0 and summ["no_prior"]["sim_places_none_right"] == 1


def test_crossings_summary_counts_outcomes_and_noisy_priors_scatter_as_drawn():
    """benchmarks/crossings.py: its summary counts right, wrong and refusals (with the right poses refused as
    degenerate) per slice, and its prior's noise has the 2 m / 2 deg spread it claims (500 seeds)."""
    crossings = _load(BENCHMARKS / "crossings.py")
    row = {"d2": 1.0, "t_err_m": 0.3, "r_err_deg": 0.2, "reason": None}
    rows = [
        {**row, "distance_m": 55.0, "rel_yaw_deg": 80.0, "outcome": "right"},
        {**row, "distance_m": 90.0, "rel_yaw_deg": -100.0, "outcome": "wrong", "t_err_m": 3.0},
        {**row, "distance_m": 90.0, "rel_yaw_deg": 100.0, "outcome": "refused", "reason": "degenerate_pose"},
        {**row, "distance_m": 60.0, "rel_yaw_deg": -70.0, "outcome": "refused", "reason": "no_box_overlap"},
    ]
    s = crossings.summarise(rows)
    assert (s["all"]["right"], s["all"]["wrong"], s["all"]["success_pct"]) == (1, 1, 25.0)
    assert s["all"]["refused"] == {"degenerate_pose": 1, "no_box_overlap": 1}
    assert s["all"]["degenerate_but_within_1m_1deg"] == 1
    assert (s["75-100 m"]["pairs"], s["75-100 m"]["wrong"], s["yaw < 0"]["pairs"]) == (2, 1, 2)
    T = np.eye(4)
    T[:2, 3] = (60.0, 20.0)
    priors = [crossings.noisy_prior(T, seed) for seed in range(500)]
    offsets = np.array([P[:2, 2] - (60.0, 20.0) for P in priors])
    yaws = np.degrees([np.arctan2(P[1, 0], P[0, 0]) for P in priors])
    assert np.allclose(offsets.std(axis=0), 2.0, rtol=0.15) and abs(np.std(yaws) - 2.0) < 0.3
