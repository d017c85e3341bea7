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
    assert row["ramp"] > -0.01
    assert len(row["lit_peer"]) == 4 and sum(row["lit_peer"]) > 500
