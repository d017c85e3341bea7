"""Write simulated scenarios in the OPV2V / V2V4Real layout (see ``bb_align.io.dataset``).

Each agent's ``vehicles`` are the labels an annotator of its own cloud would give: a car the agent's LiDAR hit
is boxed where the (distorted, not de-skewed) sweep shows it, as in V2V4Real; other cars at their true pose. A
sweep rendered with self-motion distortion also carries ``sweep_twist`` (the sensor's velocity and yaw rate at
mid-sweep, and the sweep's period): what the car's odometry gives a sender to de-skew it with; ``bb-align eval``
de-skews with it as such a sender would.

Scenario i of a benchmark seeded S is ``Scenario(seed=S * 100_003 + i)``; its agents' spacing is stratified
over [min_distance_m, max_distance_m] so every distance bucket gets its share of pairs.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bb_align.io.dataset import write_agent_frame

from .scenario import Scenario, SimAgent, SimConfig


def scenario_seed(seed: int, index: int) -> int:
    return int(seed) * 100_003 + int(index)


def scenario_distance(seed: int, index: int, n: int, config: SimConfig) -> float:
    """Stratified spacing: scenario i of n gets a distance in the i-th of n equal slices of the range."""
    u = np.random.default_rng([int(seed), int(index), 7]).random()
    lo, hi = config.min_distance_m, config.max_distance_m
    return float(lo + (index + u) / n * (hi - lo))


def write_scenario(
    root: str | Path,
    seed: int,
    index: int,
    n_scenarios: int,
    frames: int = 1,
    n_agents: int = 2,
    dt: float = 0.1,
    config: SimConfig | None = None,
) -> str:
    """Simulate and write scenario ``index``; returns its directory name."""
    cfg = config or SimConfig()
    sc = Scenario(scenario_seed(seed, index), n_agents, scenario_distance(seed, index, n_scenarios, cfg), cfg)
    return write_scenario_frames(root, f"sim_{seed}_{index:04d}", sc, frames, dt)


def write_scenario_frames(
    root: str | Path,
    name: str,
    sc: Scenario,
    frames: int,
    dt: float = 0.1,
    extra: Callable[[str, SimAgent], dict] | None = None,
) -> str:
    """Render ``frames`` frames of a scenario and write every agent's cloud and yaml under ``root/name``;
    ``extra(agent_id, agent)`` adds fields to each yaml (called in frame order). Returns ``name``."""
    cfg = sc.config
    for f in range(frames):
        frame = sc.frame(f, dt)
        for agent_id, agent in frame.agents.items():
            T = agent.T_world_sensor
            vehicles = {}
            for v in sc.world.vehicles:
                if v.vid == agent.vehicle_id:
                    continue
                box = v.box(agent.time_s)
                if np.hypot(*(box[:2] - T[:2, 3])) > cfg.vehicle_range_m:
                    continue
                seen = agent.seen_boxes.get(v.vid)
                if seen is not None:  # labelled where this agent's cloud shows it (distortion included)
                    box = seen.copy()
                    box[:3] = T[:3, :3] @ seen[:3] + T[:3, 3]
                    box[6] = seen[6] + np.arctan2(T[1, 0], T[0, 0])
                vehicles[v.vid] = box
            fields = {
                "sensor": agent.sensor,
                "timestamp_s": round(agent.time_s, 6),
                "sim_seed": sc.seed,
                "vehicle_points": {int(k): int(n) for k, n in agent.points_on.items() if k in vehicles},
                **(extra(agent_id, agent) if extra is not None else {}),
            }
            if agent.twist is not None:  # a sweep not de-skewed carries the motion a sender would de-skew it with
                vx, vy, w = agent.twist
                fields["sweep_twist"] = {
                    "vx_mps": round(vx, 6),
                    "vy_mps": round(vy, 6),
                    "yaw_rate_rps": round(w, 6),
                    "period_s": agent.period_s,
                }
            write_agent_frame(
                root,
                name,
                agent_id,
                f"{f:06d}",
                agent.points,
                agent.T_world_sensor,
                vehicles,
                detections=agent.boxes,
                detection_scores=agent.scores,
                extra=fields,
            )
    return name


def write_benchmark(
    root: str | Path,
    n_scenarios: int,
    seed: int = 0,
    frames: int = 1,
    n_agents: int = 2,
    dt: float = 0.1,
    config: SimConfig | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> list[str]:
    """Simulate ``n_scenarios`` scenarios into ``root`` (deterministic for ``seed``); returns their names."""
    if n_scenarios < 1:
        raise ValueError(f"n_scenarios must be >= 1, got {n_scenarios}")
    Path(root).mkdir(parents=True, exist_ok=True)
    args = [(str(root), seed, i, n_scenarios, frames, n_agents, dt, config) for i in range(n_scenarios)]
    return run_pool(_write_star, args, workers, "simulating", "scenario", progress)


def run_pool(fn, args: list, workers: int | None, desc: str, unit: str, progress: bool = True) -> list:
    """``fn`` over ``args`` in order, on ``workers`` processes (default: up to 2), with a progress bar."""
    workers = workers or min(2, os.cpu_count() or 1)
    out = []
    with tqdm(total=len(args), desc=desc, unit=unit, disable=not progress) as bar:
        if workers <= 1:
            for a in args:
                out.append(fn(a))
                bar.update()
        else:
            with ProcessPoolExecutor(workers) as pool:
                for r in pool.map(fn, args):
                    out.append(r)
                    bar.update()
    return out


def _write_star(a):
    return write_scenario(*a)
