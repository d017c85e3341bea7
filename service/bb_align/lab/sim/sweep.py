"""Swept two-car sequences for tracking: the peer-ego distance sweeps across ~5-120 m while both cars drive, each
frame carrying the cars' odometry (locally accurate, slowly drifting) and GNSS-grade reported poses.

Kinds, one per scenario in turn: ``receding`` (the peer pulls away on the ego's road), ``approaching`` (the ego
catches up with a slower peer), ``overtaking`` (the peer comes from behind and passes), ``oncoming`` (the peer
meets the ego on the other carriageway and drives on) and ``crossing`` (the two cars reach an intersection from
different roads).

Written in the OPV2V / V2V4Real layout (``bb_align.io.dataset``): ``lidar_pose`` is the true pose; each yaml also
holds ``odometry_pose`` (the car's odometry, same 6-vector format, in its own odometry frame) and ``gnss_pose``
(the reported pose, 2 m / 2 deg class, time-correlated).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bb_align.engine.geometry import se2, se2_params
from bb_align.io.dataset import world_to_x_pose

from .scenario import Scenario, SimConfig
from .writer import run_pool, scenario_seed, write_scenario_frames

SWEEP_KINDS = ("receding", "approaching", "overtaking", "oncoming", "crossing")


class SweepConfig(BaseModel):
    """How the swept sequences move and what their odometry and GNSS poses get wrong."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    duration_s: float = Field(
        15.0,
        gt=0,
        description="the sweep's motion is planned over this long (150 frames at "
        "10 Hz); a shorter sequence is its beginning",
    )
    near_m: float = Field(5.0, gt=0, description="closest spacing of the sweep")
    far_m: float = Field(120.0, gt=0, description="farthest spacing of the sweep")
    ego_speed_m_s: tuple[float, float] = Field((8.0, 12.0), description="the ego's speed is drawn in this range")
    odometry_scale_sigma: float = Field(0.005, ge=0, description="odometry distance scale error, 1 sigma (0.5 %)")
    odometry_yaw_bias_deg_s: float = Field(0.02, ge=0, description="odometry yaw-rate bias, 1 sigma, deg/s")
    odometry_step_sigma_m: float = Field(0.005, ge=0, description="odometry white noise per frame, metres")
    odometry_step_sigma_deg: float = Field(0.005, ge=0, description="odometry white noise per frame, degrees")
    gnss_sigma_m: float = Field(2.0, ge=0, description="reported-pose position error, 1 sigma per axis")
    gnss_sigma_deg: float = Field(2.0, ge=0, description="reported-pose heading error, 1 sigma")
    gnss_correlation_s: float = Field(5.0, gt=0, description="time constant of the reported-pose error")


def _drive(vehicle, lane, s0: float, speed: float) -> None:
    vehicle.path, vehicle.s0, vehicle.speed = lane, float(s0), float(max(0.0, speed))


def _intersection(main_lane, road) -> tuple[float, float] | None:
    """(s on main_lane, s on the road's first forward lane) where the two come closest, if they cross."""
    other = road.lane(0, True)
    best = None
    for s_o, xy in zip(other.s[::4], other.xy[::4]):
        s_m, d = main_lane.nearest_s(xy)
        if best is None or d < best[2]:
            best = (s_m, float(s_o), d)
    return (best[0], best[1]) if best is not None and best[2] < 3.0 else None


def sweep_scenario(seed: int, kind: str, duration_s: float, cfg: SweepConfig) -> Scenario:
    """A two-car Scenario whose peer drives so the spacing sweeps near..far (or far..near..far) in duration_s."""
    sc = Scenario(seed, 2, 30.0, SimConfig(stopped_prob=0.0))
    world = sc.world
    rng = np.random.default_rng([seed, 17])
    ego, peer = (world.vehicles[a.vehicle] for a in sc.agents)
    main = world.roads[0]
    lane_e = main.lane(0, True)
    v_e = float(rng.uniform(*cfg.ego_speed_m_s))
    span, T = cfg.far_m - cfg.near_m, duration_s
    s_e0 = float(rng.uniform(cfg.far_m, max(cfg.far_m + 1, lane_e.length - v_e * T - cfg.far_m - 20)))
    lanes_same = [main.lane(k, True) for k in range(main.lanes_per_dir)]
    lane_p = lanes_same[-1]
    if kind == "receding":
        _drive(peer, lane_p, s_e0 + cfg.near_m, v_e + span / T)
    elif kind == "approaching":
        _drive(peer, lane_p, s_e0 + cfg.far_m, v_e - span / T)
    elif kind == "overtaking":
        _drive(peer, lane_p, s_e0 - cfg.far_m / 2, v_e + cfg.far_m / T)
    elif kind == "oncoming":
        lane_p = main.lane(0, False)
        start_xy = np.array(lane_e.pose_at(s_e0 + cfg.far_m)[:2])
        _drive(peer, lane_p, lane_p.nearest_s(start_xy)[0], max(1.0, 2 * cfg.far_m / T - v_e))
    elif kind == "crossing":
        found = ((r, _intersection(lane_e, r)) for r in world.roads[1:])
        road, crossing = next(((r, c) for r, c in found if c is not None), (None, None))
        if crossing is None:  # no crossing street in this world: the oncoming case instead
            return sweep_scenario(seed, "oncoming", duration_s, cfg)
        s_m, s_o = crossing
        lane_p = road.lane(0, True)
        v_p = float(rng.uniform(*cfg.ego_speed_m_s))
        s_e0 = s_m - v_e * T / 2  # both reach the intersection around mid-sequence, the peer 1.5 s later
        _drive(peer, lane_p, s_o - v_p * (T / 2 + 1.5), v_p)
    else:
        raise ValueError(f"kind must be one of {SWEEP_KINDS}, got {kind!r}")
    _drive(ego, lane_e, s_e0, v_e)
    # Other moving traffic on the agents' lanes would drive through them at a different speed: removed.
    agents = (ego, peer)
    world.vehicles = [
        v for v in world.vehicles if any(v is a for a in agents) or not (v.path is lane_e or v.path is lane_p)
    ]
    for i, v in enumerate(world.vehicles):
        v.vid = i
    for spec, v in zip(sc.agents, agents):
        spec.vehicle = v.vid
    return sc


def _lift(T2: np.ndarray, T_like: np.ndarray) -> np.ndarray:
    """A 4x4 pose with T2's x, y, yaw and T_like's z, roll and pitch."""
    yaw_like = np.arctan2(T_like[1, 0], T_like[0, 0])
    yaw, x, y = se2_params(T2)
    Rz = np.array(
        [
            [np.cos(yaw - yaw_like), -np.sin(yaw - yaw_like), 0],
            [np.sin(yaw - yaw_like), np.cos(yaw - yaw_like), 0],
            [0, 0, 1],
        ]
    )
    out = np.array(T_like, dtype=float)
    out[:3, :3] = Rz @ out[:3, :3]
    out[0, 3], out[1, 3] = x, y
    return out


class PoseSensors:
    """One car's odometry (integrated noisy increments, biased) and GNSS (Gauss-Markov error) over a sequence."""

    def __init__(self, rng: np.random.Generator, cfg: SweepConfig, dt: float):
        self.rng, self.cfg, self.dt = rng, cfg, dt
        self.scale = 1.0 + rng.normal(0, cfg.odometry_scale_sigma)
        self.yaw_bias = np.radians(rng.normal(0, cfg.odometry_yaw_bias_deg_s))
        self.O = se2(rng.uniform(-np.pi, np.pi), *rng.uniform(-500, 500, 2))  # the odometry frame is its own
        self.prev: np.ndarray | None = None
        self.gnss_err = rng.normal(0, 1, 3) * [np.radians(cfg.gnss_sigma_deg), cfg.gnss_sigma_m, cfg.gnss_sigma_m]

    def step(self, W4: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(odometry pose, GNSS pose), 4x4, for the true pose W4."""
        c, W = self.cfg, se2(*se2_params(W4))
        if self.prev is not None:
            d_yaw, dx, dy = se2_params(np.linalg.inv(self.prev) @ W)
            n = self.rng.normal(0, 1, 3)
            self.O = self.O @ se2(
                d_yaw + self.yaw_bias * self.dt + np.radians(c.odometry_step_sigma_deg) * n[0],
                dx * self.scale + c.odometry_step_sigma_m * n[1],
                dy * self.scale + c.odometry_step_sigma_m * n[2],
            )
        self.prev = W
        a = np.exp(-self.dt / c.gnss_correlation_s)
        sig = np.array([np.radians(c.gnss_sigma_deg), c.gnss_sigma_m, c.gnss_sigma_m])
        self.gnss_err = a * self.gnss_err + np.sqrt(1 - a * a) * sig * self.rng.normal(0, 1, 3)
        G = W.copy()
        G[0, 2] += self.gnss_err[1]
        G[1, 2] += self.gnss_err[2]
        G = G @ se2(self.gnss_err[0], 0.0, 0.0)
        return _lift(self.O, W4), _lift(G, W4)


def write_sweep(
    root: str | Path,
    seed: int,
    index: int,
    frames: int,
    dt: float = 0.1,
    cfg: SweepConfig | None = None,
    kinds: tuple[str, ...] = SWEEP_KINDS,
) -> str:
    """Simulate and write swept scenario ``index`` (its kind ``kinds[index]``, in turn); returns its directory name."""
    cfg = cfg or SweepConfig()
    kind = kinds[index % len(kinds)]
    sc = sweep_scenario(scenario_seed(seed, index), kind, cfg.duration_s, cfg)
    sensors = {a: PoseSensors(np.random.default_rng([seed, index, 23, i]), cfg, dt) for i, a in enumerate(sc.agent_ids)}

    def extra(agent_id: str, agent) -> dict:
        odo, gnss = sensors[agent_id].step(agent.T_world_sensor)
        return {"sweep": kind, "odometry_pose": world_to_x_pose(odo), "gnss_pose": world_to_x_pose(gnss)}

    return write_scenario_frames(root, f"sweep_{seed}_{index:04d}_{kind}", sc, frames, dt, extra)


def write_sweeps(
    root: str | Path,
    n_scenarios: int,
    frames: int,
    seed: int = 0,
    dt: float = 0.1,
    cfg: SweepConfig | None = None,
    workers: int | None = None,
    progress: bool = True,
    kinds: tuple[str, ...] = SWEEP_KINDS,
) -> list[str]:
    """``n_scenarios`` swept sequences of ``frames`` frames into ``root`` (deterministic for ``seed``), of
    ``kinds`` in turn."""
    if n_scenarios < 1 or frames < 2:
        raise ValueError(f"need n_scenarios >= 1 and frames >= 2, got {n_scenarios}, {frames}")
    unknown = [k for k in kinds if k not in SWEEP_KINDS]
    if unknown or not kinds:
        raise ValueError(f"kinds must be among {SWEEP_KINDS}, got {kinds!r}")
    Path(root).mkdir(parents=True, exist_ok=True)
    args = [(str(root), seed, i, frames, dt, cfg, tuple(kinds)) for i in range(n_scenarios)]
    return run_pool(_write_sweep_star, args, workers, "simulating sweeps", "sequence", progress)


def _write_sweep_star(a):
    return write_sweep(*a)
