"""Two or more cars on a procedural street, each with its own LiDAR, driving for a few frames.

    frames = simulate_sequence(seed=3, n_frames=10, n_agents=2, distance_m=40.0)
    ego, peer = frames[0].agents["0"], frames[0].agents["1"]
    T_ego_peer_true = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor

Deterministic for a seed: the world, the cars' placement, their sensors and every frame draw from generators
seeded by (seed, purpose[, frame, agent]).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .detections import DetectionModel, detect
from .paths import Path
from .raycast import Mount, T_world_sensor_at, cast_sweep, sensor_twist
from .sensors import DEFAULT_FLEET, SENSOR_MODELS, SensorModel, pick_sensors
from .streets import generate_world
from .world import Vehicle, World


class SimConfig(BaseModel):
    """Scenario parameters (defaults: the benchmark's)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    min_distance_m: float = Field(4.0, ge=0, description="closest agent spacing drawn when distance_m is None")
    max_distance_m: float = Field(100.0, gt=0, description="farthest agent spacing drawn when distance_m is None")
    fleet: tuple[str, ...] = Field(DEFAULT_FLEET, description="sensor models the agents draw from (all different)")
    distortion: bool = Field(True, description="self-motion distortion on (points not de-skewed)")
    traffic: float | None = Field(None, ge=0, le=1, description="0 light .. 1 busy; None: drawn per scenario")
    tilt_sigma_deg: float = Field(0.3, ge=0, description="residual sensor roll/pitch (mounting + body), 1 sigma")
    stopped_prob: float = Field(0.15, ge=0, le=1, description="probability that an agent is standing still")
    phase_jitter_s: float = Field(
        0.05,
        ge=0,
        le=0.5,
        description="peers' sweeps are centred up to this far "
        "from the ego's (unsynchronised LiDARs; uniform, fixed per agent)",
    )
    same_road_prob: float = Field(0.7, ge=0, le=1, description="probability that a peer drives on the ego's road")
    family: Literal["mixed", "street", "turn", "crossing"] = Field(
        "mixed",
        description="mixed: the benchmark's streets and placements; street: a straight residential street, every "
        "peer ahead of the ego in its lane (following); turn: every peer on a crossing street it has turned into, "
        "beyond the crossing the ego drives towards; crossing: the turn family's worlds, the ego on the main road "
        "within 30 m of a crossing, every peer on the crossing street (either side, either lane) at the wanted "
        "distance: relative yaw 65-115 deg either way",
    )
    vehicle_range_m: float = Field(120.0, gt=0, description="vehicles listed as ground truth within this range")
    detection: DetectionModel = DetectionModel()


@dataclass
class SimAgent:
    """One car's frame: its cloud and detections in its own sensor frame, and its true pose."""

    points: np.ndarray  # (N, 4) float32 x, y, z, intensity; sensor frame, distorted as measured
    boxes: np.ndarray  # (K, 7) detections [x, y, z, l, w, h, yaw], sensor frame
    T_world_sensor: np.ndarray  # 4x4 true pose at mid-sweep (time_s)
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K,) detection confidences
    sensor: str = ""
    time_s: float = 0.0  # mid-sweep time: the frame's stamp plus this LiDAR's phase offset
    vehicle_id: int = -1  # this car's id among the frame's vehicles
    points_on: dict[int, int] = field(default_factory=dict)  # vehicle id -> LiDAR points on it
    seen_boxes: dict[int, np.ndarray] = field(default_factory=dict)  # vehicle id -> box where the (distorted)
    # sweep shows it, sensor frame: what an annotator labelling this cloud would draw
    # (vx m/s, vy m/s, yaw rate rad/s) of the sensor at mid-sweep, its own frame, and the sweep's period: what
    # the car's odometry gives a sender that de-skews; None when the sweep is rendered frozen (already de-skewed)
    twist: tuple[float, float, float] | None = None
    period_s: float = 0.1


@dataclass
class SimFrame:
    stamp: float
    agents: dict[str, SimAgent]
    vehicles: dict[int, np.ndarray] = field(default_factory=dict)  # id -> world box [x, y, z, l, w, h, yaw]


@dataclass
class _AgentSpec:
    vehicle: int
    sensor: SensorModel
    mount: Mount
    beam_error_deg: np.ndarray
    phase_s: float = 0.0


def _lane_speed(world: World, lane: Path, rng) -> float:
    for v in world.vehicles:
        if v.path is lane:
            return v.speed
    return float(rng.uniform(5, 16))


def _add_agent(world: World, lane: Path, s0: float, rng, stopped_prob: float, agents: list[Vehicle]) -> Vehicle:
    speed = 0.0 if rng.random() < stopped_prob else _lane_speed(world, lane, rng)
    speed = next((a.speed for a in agents if a.path is lane), speed)  # agents sharing a lane never collide
    # clear the lane around the agent (traffic in a lane shares one speed, so nothing drives into it)
    behind = 40.0 + (40.0 if speed == 0 else 0.0)
    world.vehicles = [
        v for v in world.vehicles if any(v is a for a in agents) or not (v.path is lane and -behind < v.s0 - s0 < 14.0)
    ]
    car = Vehicle(
        -1,
        float(rng.uniform(4.4, 4.9)),
        float(rng.uniform(1.8, 1.95)),
        float(rng.uniform(1.45, 1.7)),
        "car",
        path=lane,
        s0=s0,
        speed=speed,
    )
    world.vehicles.append(car)
    return car


def _place(world: World, rng, n_agents: int, distance_m: float | None, cfg: SimConfig) -> list[int]:
    """Ego on the main road; each other agent on any lane of any road at the wanted distance from the ego."""
    main = world.roads[0]
    lane = main.lanes()[int(rng.integers(len(main.lanes())))]
    s_ego = float(rng.uniform(0.35, 0.65) * lane.length)
    agents: list[Vehicle] = []
    agents.append(_add_agent(world, lane, s_ego, rng, cfg.stopped_prob, agents))
    ego_xy = lane.pose_at(s_ego)[:2]
    taken = [(lane, s_ego)]
    for _ in range(n_agents - 1):
        d = distance_m if distance_m is not None else float(rng.uniform(cfg.min_distance_m, cfg.max_distance_m))
        options = []
        for road in world.roads:
            for ln in road.lanes():
                dist = np.hypot(ln.xy[:, 0] - ego_xy[0], ln.xy[:, 1] - ego_xy[1])
                ok = (np.abs(dist - d) < 1.5) & (ln.s > 10) & (ln.s < ln.length - 40)
                for tl, ts in taken:  # keep clear of agents already placed
                    if tl is ln:
                        ok &= np.abs(ln.s - ts) > 8.0
                    else:
                        x, y, _ = tl.pose_at(ts)
                        ok &= np.hypot(ln.xy[:, 0] - x, ln.xy[:, 1] - y) > 3.0
                if ok.any():
                    options.append((ln, ln.s[ok]))
        if not options:  # the wanted distance is impossible here: nearest feasible on the ego's lane
            s_other = float(np.clip(s_ego + d, 10, lane.length - 40))
            if abs(s_other - s_ego) < 8:
                s_other = s_ego - max(d, 8.0)
            options = [(lane, np.array([s_other]))]
        same_road = [o for o in options if any(o[0] is m for m in main.lanes())]
        if same_road and rng.random() < cfg.same_road_prob:  # cooperating cars mostly share a road
            options = same_road
        ln, ss = options[int(rng.integers(len(options)))]
        s_other = float(ss[int(rng.integers(len(ss)))])
        agents.append(_add_agent(world, ln, s_other, rng, cfg.stopped_prob, agents))
        taken.append((ln, s_other))
    return _numbered(world, agents)


def _spacing(rng, distance_m: float | None, cfg: SimConfig) -> float:
    return distance_m if distance_m is not None else float(rng.uniform(cfg.min_distance_m, cfg.max_distance_m))


def _numbered(world: World, agents: list[Vehicle]) -> list[int]:
    for i, v in enumerate(world.vehicles):
        v.vid = i
    return [a.vid for a in agents]


def _place_following(world: World, rng, n_agents: int, distance_m: float | None, cfg: SimConfig) -> list[int]:
    """The street family: the ego in a lane of the main road, every peer ahead of it in the same lane (the real far
    pairs' case: one car following another along a street)."""
    lane = world.roads[0].lanes()[int(rng.integers(len(world.roads[0].lanes())))]
    spacings = [_spacing(rng, distance_m, cfg) for _ in range(n_agents - 1)]
    s_ego = float(rng.uniform(40.0, max(41.0, lane.length - max(spacings, default=0.0) - 60.0)))
    agents = [_add_agent(world, lane, s_ego, rng, cfg.stopped_prob, [])]
    taken = [s_ego]
    for d in spacings:
        s = min(s_ego + d, lane.length - 20.0)
        while any(abs(s - t) < 8.0 for t in taken):  # two peers drawn at about the same spacing
            s += 9.0
        agents.append(_add_agent(world, lane, s, rng, cfg.stopped_prob, agents))
        taken.append(s)
    return _numbered(world, agents)


def _place_turned(world: World, rng, n_agents: int, distance_m: float | None, cfg: SimConfig) -> list[int]:
    """The turn family: the ego drives towards a crossing 5-30 m ahead; every peer has turned into the crossing
    street and drives away from it, at the wanted distance from the ego (nearest feasible when out of reach)."""
    return _on_crossing_street(
        world, rng, n_agents, distance_m, cfg,
        ego_s=lambda s_c: s_c - rng.uniform(5.0, 30.0),
        allowed=lambda ln, s_x: (ln.s > s_x + 8.0) & (ln.s < ln.length - 20.0),  # beyond the crossing: turned off
        either_side=False,
    )  # fmt: skip


def _place_crossing(world: World, rng, n_agents: int, distance_m: float | None, cfg: SimConfig) -> list[int]:
    """The crossing family: the ego on a lane of the main road within 30 m of a crossing (before or past it), every
    peer on a lane of the crossing street, either side of the junction and clear of it (> 10 m from the main
    road's centre line), at the wanted distance from the ego (nearest feasible when out of reach)."""
    return _on_crossing_street(
        world, rng, n_agents, distance_m, cfg,
        ego_s=lambda s_c: s_c + rng.uniform(-30.0, 30.0),
        allowed=lambda ln, s_x: (np.abs(ln.s - s_x) > 10.0) & (ln.s > 10.0) & (ln.s < ln.length - 20.0),
        either_side=True,
    )  # fmt: skip


def _on_crossing_street(world: World, rng, n_agents, distance_m, cfg: SimConfig, ego_s, allowed, either_side: bool):
    """The ego on a lane of the main road at ``ego_s(s of the crossing)``, every peer on a lane of a crossing street
    where ``allowed(lane, s of the crossing)``, at the wanted distance from the ego (nearest feasible when out of
    reach; ``either_side``: any feasible place within 1.5 m of it, drawn)."""
    k = int(rng.integers(1, len(world.roads)))
    cross = world.roads[k]
    centre = np.array(cross.centre.pose_at(cross.centre.length / 2)[:2])  # where the two streets meet
    lane = world.roads[0].lanes()[int(rng.integers(len(world.roads[0].lanes())))]
    s_c, _ = lane.nearest_s(centre)
    s_ego = float(np.clip(ego_s(s_c), 10.0, lane.length - 10.0))
    agents = [_add_agent(world, lane, s_ego, rng, cfg.stopped_prob, [])]
    ego_xy = np.array(lane.pose_at(s_ego)[:2])
    taken: list[tuple[Path, float]] = []
    for _ in range(n_agents - 1):
        d = _spacing(rng, distance_m, cfg)
        ln = cross.lanes()[int(rng.integers(len(cross.lanes())))]
        s_x, _ = ln.nearest_s(centre)
        ok = allowed(ln, s_x)
        for tl, ts in taken:
            ok &= ~((tl is ln) & (np.abs(ln.s - ts) < 8.0))
        miss = np.where(ok, np.abs(np.hypot(*(ln.xy - ego_xy).T) - d), np.inf)
        near = np.flatnonzero(miss < 1.5) if either_side else []
        i = int(near[int(rng.integers(len(near)))]) if len(near) else int(np.argmin(miss))
        s = float(ln.s[i])
        agents.append(_add_agent(world, ln, s, rng, cfg.stopped_prob, agents))
        taken.append((ln, s))
    return _numbered(world, agents)


class Scenario:
    """A world with agents, ready to render frames at any time."""

    def __init__(self, seed: int, n_agents: int = 2, distance_m: float | None = None, config: SimConfig | None = None):
        if n_agents < 1:
            raise ValueError(f"n_agents must be >= 1, got {n_agents}")
        if distance_m is not None and not (0 <= distance_m <= 300):
            raise ValueError(f"distance_m must be within [0, 300] m, got {distance_m}")
        self.seed = int(seed)
        self.config = cfg = config or SimConfig()
        world_family = "turn" if cfg.family == "crossing" else cfg.family  # the crossing family: turn's worlds
        self.world = generate_world(np.random.default_rng([self.seed, 0]), traffic=cfg.traffic, family=world_family)
        rng = np.random.default_rng([self.seed, 1])
        place = {"mixed": _place, "street": _place_following, "turn": _place_turned, "crossing": _place_crossing}
        place = place[cfg.family]
        vids = place(self.world, rng, n_agents, distance_m, cfg)
        sensors = pick_sensors(rng, n_agents, cfg.fleet)
        tilt = np.radians(cfg.tilt_sigma_deg)
        self.agents: list[_AgentSpec] = []
        for vid, sensor in zip(vids, sensors):
            mount = Mount(
                height_m=float(rng.uniform(1.65, 2.15)),
                x_offset_m=float(rng.uniform(-0.5, 0.8)),
                roll=float(rng.normal(0, tilt)),
                pitch=float(rng.normal(0, tilt)),
            )
            err = rng.normal(0, sensor.elevation_jitter_deg, sensor.beams)
            phase = float(rng.uniform(-cfg.phase_jitter_s, cfg.phase_jitter_s)) if self.agents else 0.0
            self.agents.append(_AgentSpec(vid, sensor, mount, err, phase))

    @property
    def agent_ids(self) -> list[str]:
        return [str(i) for i in range(len(self.agents))]

    def frame(self, index: int, dt: float = 0.1, stamp: float | None = None) -> SimFrame:
        """Frame ``index`` (its noise's seed) at simulation time ``stamp`` (s; default index * dt)."""
        stamp = index * dt if stamp is None else float(stamp)
        cfg = self.config
        w = self.world
        agents: dict[str, SimAgent] = {}
        for a_idx, spec in enumerate(self.agents):
            rng = np.random.default_rng([self.seed, 2, index, a_idx])
            t_mid = stamp + spec.phase_s
            sweep = cast_sweep(
                w, spec.vehicle, spec.sensor, spec.mount, t_mid, rng, spec.beam_error_deg, distortion=cfg.distortion
            )
            hit = sweep.owner >= 0
            ids, counts = np.unique(sweep.owner[hit], return_counts=True)
            true_boxes = np.zeros((len(ids), 7))
            for j, vid in enumerate(ids):
                # the box as its points show it: car and sensor where they were when the laser swept it
                t_v = float(sweep.time[sweep.owner == vid].mean())
                T_sw = np.linalg.inv(T_world_sensor_at(w, spec.vehicle, spec.mount, t_v))
                box = w.vehicles[vid].box(t_v)
                true_boxes[j, :3] = T_sw[:3, :3] @ box[:3] + T_sw[:3, 3]
                true_boxes[j, 3:6] = box[3:6]
                true_boxes[j, 6] = box[6] + np.arctan2(T_sw[1, 0], T_sw[0, 0])
            dets = detect(true_boxes, counts, sweep.points, rng, cfg.detection)
            agents[str(a_idx)] = SimAgent(
                points=sweep.points,
                boxes=dets.boxes,
                scores=dets.scores,
                T_world_sensor=sweep.T_world_sensor,
                sensor=spec.sensor.name,
                time_s=t_mid,
                vehicle_id=spec.vehicle,
                points_on={int(i): int(c) for i, c in zip(ids, counts)},
                seen_boxes={int(i): true_boxes[j] for j, i in enumerate(ids)},
                twist=sensor_twist(w, spec.vehicle, spec.mount, t_mid) if cfg.distortion else None,
                period_s=1.0 / spec.sensor.spin_hz,
            )
        ego_xy = agents["0"].T_world_sensor[:2, 3]
        vehicles = {}
        for v in w.vehicles:
            box = v.box(stamp)
            if np.hypot(*(box[:2] - ego_xy)) <= cfg.vehicle_range_m:
                vehicles[v.vid] = box
        return SimFrame(stamp=stamp, agents=agents, vehicles=vehicles)


def simulate_sequence(
    seed: int,
    n_frames: int = 10,
    n_agents: int = 2,
    distance_m: float | None = None,
    dt: float = 0.1,
    config: SimConfig | None = None,
) -> list[SimFrame]:
    """``n_frames`` consecutive frames (``dt`` apart) of ``n_agents`` cars ``distance_m`` apart (None: drawn
    in config's [min_distance_m, max_distance_m]). Agent "0" is the ego. Deterministic for a seed."""
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    if not dt > 0:
        raise ValueError(f"dt must be > 0 s, got {dt}")
    scenario = Scenario(seed, n_agents, distance_m, config)
    return [scenario.frame(i, dt) for i in range(n_frames)]


__all__ = ["SENSOR_MODELS", "Scenario", "SimAgent", "SimConfig", "SimFrame", "simulate_sequence"]
