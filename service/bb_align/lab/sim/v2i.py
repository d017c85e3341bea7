"""A vehicle and a roadside LiDAR (V2I), written in DAIR-V2X-C's cooperative layout (``bb_align.io.dair``).

The roadside unit stands beside the main road on a pole (``mount_height_m`` above the ground, 4-5 m), looks
along the road towards the vehicle with a forward field of view (``fov_deg``, 120 deg: the points of a full
sweep outside it are dropped), and does not move; the vehicle drives with a 40-beam LiDAR (DAIR-V2X-C's
vehicle side). The roadside cloud is written in a "virtual LiDAR" frame as DAIR-V2X-C ships it: levelled, with
the same x, y and heading as the sensor, the ground ``virtual_height_m`` below its origin.

Each side's labels are the vehicles its own cloud shows (with ``label_min_points`` points or more), where the
cloud shows them. ``cooperative/calib/lidar_i2v`` holds the truth moved by a known corruption (x, y, yaw), so a
recovery can be scored against ``bb_align_sim_truth.json`` (written beside the cooperative folder).

Scene i of a root seeded S is ``Scenario(seed=S * 100_003 + i)`` with one agent (the vehicle) plus the pole;
the existing V2V scenarios are untouched. Deterministic for a seed.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bb_align.io.dair import COOP_DIR, DairFrameFiles, write_dair_root
from bb_align.io.dataset import world_to_x_pose, x_to_world

from .raycast import Mount, T_world_sensor_at, cast_sweep
from .scenario import Scenario, SimConfig
from .sensors import SensorModel
from .world import Vehicle
from .writer import scenario_seed

TRUTH_NAME = "bb_align_sim_truth.json"

ROADSIDE_LIDAR = SensorModel(
    name="roadside",
    elevations_deg=tuple(float(a) for a in np.round(np.linspace(5.0, -30.0, 80), 3)),
    columns=1800,
    max_range_m=120,
    range_noise_m=0.02,
    dropout=0.04,
)
"""A dense, downward-reaching roadside LiDAR (80 beams, +5..-30 deg; its returns are cropped to the FOV)."""


class V2IConfig(BaseModel):
    """Parameters of the V2I scenes (defaults: DAIR-V2X-C-like)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    mount_height_m: tuple[float, float] = Field((4.0, 5.0), description="roadside LiDAR height range, m")
    fov_deg: float = Field(120.0, gt=0, le=360, description="roadside horizontal field of view, centred forward")
    virtual_height_m: float = Field(1.7, ge=0, description="the written roadside frame's origin above the ground")
    min_distance_m: float = Field(8.0, ge=0, description="closest vehicle-to-pole distance along the road")
    max_distance_m: float = Field(60.0, gt=0, description="farthest vehicle-to-pole distance along the road")
    label_min_points: int = Field(5, ge=1, description="a vehicle is labelled on a side with this many points")
    corrupt_t_m: float = Field(4.0, ge=0, description="lidar_i2v written with x, y this far off (m)")
    corrupt_deg: float = Field(4.0, ge=0, description="lidar_i2v written with yaw this far off (deg, either way)")
    vehicle_lidar: str = Field("pandar40", description="the vehicle's LiDAR model (bb_align.lab.sim.sensors)")


@dataclass
class V2IScene:
    scenario: Scenario
    pole: int  # the roadside unit's index among the world's vehicles
    mount: Mount
    beam_error_deg: np.ndarray
    config: V2IConfig


def _clear_vehicle_path(world, ego: int, horizon_s: float = 2.0, gap_m: float = 3.5) -> None:
    """Move away every other vehicle that comes within ``gap_m`` of the ego's centre during ``horizon_s``
    (crossing traffic can drive through the ego, whose LiDAR then sees only the inside of a van); indices are
    kept, as vehicle indices name the clouds' owners."""
    ts = np.arange(0.0, horizon_s + 0.05, 0.05)  # finer than a car passing through gap_m
    ex, ey, _ = world.vehicles[ego].pose(ts)
    for i, v in enumerate(world.vehicles):
        if i == ego:
            continue
        vx, vy, _ = v.pose(ts)
        if np.min(np.hypot(vx - ex, vy - ey)) < gap_m:
            world.vehicles[i] = Vehicle(v.vid, v.length, v.width, v.height, v.kind, pose0=(1e5, 1e5, 0.0))


def v2i_scene(seed: int, distance_m: float, config: V2IConfig | None = None, horizon_s: float = 2.0) -> V2IScene:
    """A world with the vehicle (agent "0") and a roadside pole ``distance_m`` from it along the main road;
    no other vehicle drives through the vehicle within ``horizon_s``."""
    cfg = config or V2IConfig()
    sc = Scenario(seed, n_agents=1, config=SimConfig(fleet=(cfg.vehicle_lidar,), stopped_prob=0.3))
    w = sc.world
    rng = np.random.default_rng([int(seed), 11])
    ego = w.vehicles[sc.agents[0].vehicle]
    ex, ey, _ = (float(v) for v in ego.pose(0.0))
    road = w.roads[0]
    s_ego, _ = road.centre.nearest_s(np.array([ex, ey]))
    ahead = 1.0 if rng.random() < 0.5 else -1.0
    s_pole = float(np.clip(s_ego + ahead * distance_m, 5.0, road.centre.length - 5.0))
    x, y, h = (float(v) for v in road.centre.pose_at(s_pole))
    side = 1.0 if rng.random() < 0.5 else -1.0
    lateral = road.half_width + 0.5 * road.sidewalk
    px, py = x - side * lateral * math.sin(h), y + side * lateral * math.cos(h)
    yaw = math.atan2(ey - py, ex - px) + math.radians(rng.uniform(-15, 15))  # facing the road towards the car
    _clear_vehicle_path(w, sc.agents[0].vehicle, horizon_s)
    clear = np.hypot(w.static.xy[:, 0] - px, w.static.xy[:, 1] - py) > w.static.radius + 1.0
    w.static = w.static.take(clear)  # nothing stands where the pole does
    z0 = float(w.terrain.height_at(np.array([px, py])))
    height = float(rng.uniform(*cfg.mount_height_m))
    w.vehicles.append(Vehicle(len(w.vehicles), 0.4, 0.4, height, "pole", pose0=(px, py, yaw), z0=z0))
    tilt = math.radians(0.2)
    mount = Mount(height_m=height, roll=float(rng.normal(0, tilt)), pitch=float(rng.normal(0, tilt)))
    err = rng.normal(0, ROADSIDE_LIDAR.elevation_jitter_deg, ROADSIDE_LIDAR.beams)
    return V2IScene(sc, len(w.vehicles) - 1, mount, err, cfg)


def _boxes_seen(world, owner: np.ndarray, times: np.ndarray, T_sensor_at, min_points: int) -> dict[int, np.ndarray]:
    """Vehicle id -> box in the sensor frame where the sweep shows it (vehicles only, enough points)."""
    out = {}
    ids, counts = np.unique(owner[owner >= 0], return_counts=True)
    for vid, n in zip(ids, counts):
        v = world.vehicles[int(vid)]
        if n < min_points or v.kind == "pole":
            continue
        t_v = float(times[owner == vid].mean())
        T_sw = np.linalg.inv(T_sensor_at(t_v))
        box = v.box(t_v)
        b = box.copy()
        b[:3] = T_sw[:3, :3] @ box[:3] + T_sw[:3, 3]
        b[6] = box[6] + math.atan2(T_sw[1, 0], T_sw[0, 0])
        out[int(vid)] = b
    return out


def _to_frame(T_new_old: np.ndarray, pts: np.ndarray) -> np.ndarray:
    out = pts.copy()
    out[:, :3] = pts[:, :3] @ T_new_old[:3, :3].T + T_new_old[:3, 3]
    return out


def _boxes_to_frame(T_new_old: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    out = np.array(boxes, dtype=float).reshape(-1, 7).copy()
    out[:, :3] = out[:, :3] @ T_new_old[:3, :3].T + T_new_old[:3, 3]
    out[:, 6] += math.atan2(T_new_old[1, 0], T_new_old[0, 0])
    return out


@dataclass
class V2IFrame:
    vehicle_points: np.ndarray
    infra_points: np.ndarray  # virtual LiDAR frame
    vehicle_boxes: np.ndarray
    infra_boxes: np.ndarray
    T_vehicle_infra: np.ndarray  # the truth: p_vehicle = T @ p_infra(virtual frame)
    stamp: float


def render_v2i_frame(scene: V2IScene, index: int, dt: float = 0.1) -> V2IFrame:
    """Frame ``index`` of a scene: both clouds, both sides' labels, the true roadside->vehicle transform."""
    sc, cfg = scene.scenario, scene.config
    frame = sc.frame(index, dt)
    car = frame.agents["0"]
    veh_boxes = {
        vid: b
        for vid, b in car.seen_boxes.items()
        if sc.world.vehicles[vid].kind != "pole" and car.points_on.get(vid, 0) >= cfg.label_min_points
    }
    rng = np.random.default_rng([sc.seed, 12, index])
    sweep = cast_sweep(sc.world, scene.pole, ROADSIDE_LIDAR, scene.mount, frame.stamp, rng, scene.beam_error_deg)
    az = np.degrees(np.arctan2(sweep.points[:, 1], sweep.points[:, 0]))
    keep = np.abs(az) <= cfg.fov_deg / 2
    pts, owner, times = sweep.points[keep], sweep.owner[keep], sweep.time[keep]
    inf_boxes = _boxes_seen(
        sc.world,
        owner,
        times,
        lambda t: T_world_sensor_at(sc.world, scene.pole, scene.mount, t),
        cfg.label_min_points,
    )
    T_ws = sweep.T_world_sensor
    T_wv = np.eye(4)  # the virtual LiDAR frame: levelled, ground virtual_height_m below
    yaw = math.atan2(T_ws[1, 0], T_ws[0, 0])
    T_wv[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T_wv[:3, 3] = (T_ws[0, 3], T_ws[1, 3], T_ws[2, 3] - scene.mount.height_m + cfg.virtual_height_m)
    T_vs = np.linalg.inv(T_wv) @ T_ws
    boxes_i = np.array(list(inf_boxes.values())).reshape(-1, 7)
    return V2IFrame(
        vehicle_points=car.points,
        infra_points=_to_frame(T_vs, pts).astype(np.float32),
        vehicle_boxes=np.array(list(veh_boxes.values())).reshape(-1, 7),
        infra_boxes=_boxes_to_frame(T_vs, boxes_i),
        T_vehicle_infra=np.linalg.inv(car.T_world_sensor) @ T_wv,
        stamp=frame.stamp,
    )


def corrupt(T: np.ndarray, rng: np.random.Generator, t_m: float, deg: float) -> np.ndarray:
    """T with x, y moved ``t_m`` in a random direction and yaw turned ``deg`` either way (z, roll, pitch kept)."""
    x = world_to_x_pose(T)
    a = rng.uniform(0, 2 * math.pi)
    x[0] += t_m * math.cos(a)
    x[1] += t_m * math.sin(a)
    x[4] += deg * (1.0 if rng.random() < 0.5 else -1.0)
    return x_to_world(x)


def write_v2i_root(
    root: str | Path,
    n_scenes: int,
    frames: int = 1,
    seed: int = 0,
    config: V2IConfig | None = None,
    dt: float = 0.1,
) -> Path:
    """Simulate ``n_scenes`` V2I scenes of ``frames`` frames each into ``root`` (DAIR-V2X-C layout, in
    ``root/cooperative-vehicle-infrastructure``) with corrupted lidar_i2v files and the truth in
    ``root/bb_align_sim_truth.json`` ({vehicle id: {T_vehicle_infra, T_written, distance_m, ...}}); returns the
    cooperative folder. Vehicle-to-pole distances are stratified over [min_distance_m, max_distance_m]."""
    if n_scenes < 1 or frames < 1:
        raise ValueError(f"n_scenes and frames must be >= 1, got {n_scenes} and {frames}")
    cfg = config or V2IConfig()
    if cfg.max_distance_m <= cfg.min_distance_m:
        raise ValueError("max_distance_m must be larger than min_distance_m")
    files, truth = [], {}
    for i in range(n_scenes):
        u = np.random.default_rng([int(seed), i, 7]).random()
        dist = cfg.min_distance_m + (i + u) / n_scenes * (cfg.max_distance_m - cfg.min_distance_m)
        scene = v2i_scene(scenario_seed(seed, i), dist, cfg, horizon_s=max(2.0, frames * dt))
        for f in range(frames):
            fr = render_v2i_frame(scene, f, dt)
            veh_id, inf_id = f"{i * 1000 + f:06d}", f"{500000 + i * 1000 + f:06d}"
            rng = np.random.default_rng([int(seed), i, f, 13])
            T_written = corrupt(fr.T_vehicle_infra, rng, cfg.corrupt_t_m, cfg.corrupt_deg)
            files.append(
                DairFrameFiles(
                    veh_id,
                    inf_id,
                    fr.vehicle_points,
                    fr.infra_points,
                    fr.vehicle_boxes,
                    fr.infra_boxes,
                    T_written,
                    timestamp_s=fr.stamp,
                )
            )
            truth[veh_id] = {
                "infra_id": inf_id,
                "scene_seed": scene.scenario.seed,
                "frame": f,
                "distance_m": float(np.hypot(*fr.T_vehicle_infra[:2, 3])),
                "T_vehicle_infra": fr.T_vehicle_infra.tolist(),
                "T_written": T_written.tolist(),
            }
    base = write_dair_root(root, files)
    (Path(root) / TRUTH_NAME).write_text(json.dumps(truth, indent=1))
    return base


def read_truth(root: str | Path) -> dict[str, np.ndarray]:
    """Vehicle frame id -> true T_vehicle_infra, from a root :func:`write_v2i_root` wrote."""
    root = Path(root)
    path = root / TRUTH_NAME if (root / TRUTH_NAME).is_file() else root.parent / TRUTH_NAME
    data = json.loads(path.read_text())
    return {k: np.asarray(v["T_vehicle_infra"], dtype=float) for k, v in data.items()}


def score_against_truth(dair_root: str | Path, truth_root: str | Path) -> dict:
    """How far each lidar_i2v under ``dair_root`` (a simulated root, or a recover output of one) is from the
    simulator's truth: per frame (t m, yaw deg, distance m), and the anchors' metrics of the files themselves
    (every file counts as a reported pose)."""
    from bb_align.engine.geometry import pose_error
    from bb_align.io.dair import read_calib, read_pairs

    from ..evaluation.summary import anchor_metrics

    truth = read_truth(truth_root)
    pairs, _ = read_pairs(dair_root)
    rows = []
    for p in pairs:
        T_true = truth[p.vehicle_id]
        t, r = pose_error(read_calib(p.lidar_i2v), T_true)
        rows.append(
            {"vehicle_id": p.vehicle_id, "t_err_m": t, "r_err_deg": r, "distance_m": float(np.hypot(*T_true[:2, 3]))}
        )
    t = np.array([x["t_err_m"] for x in rows])
    r = np.array([x["r_err_deg"] for x in rows])
    return {"frames": len(rows), **anchor_metrics(t, r, np.ones(len(rows), bool)), "per_frame": rows}


__all__ = [
    "COOP_DIR",
    "ROADSIDE_LIDAR",
    "V2IConfig",
    "read_truth",
    "score_against_truth",
    "render_v2i_frame",
    "v2i_scene",
    "write_v2i_root",
]


def _fmt3(d: dict, pct: bool = False) -> str:
    """The three lambdas' values of an anchor metric, as text."""
    cells = []
    for k in ("1", "2", "3"):
        v = d[k]
        cells.append("  -  " if v is None else f"{100 * v:.1f}%" if pct else f"{v:.2f}")
    return " / ".join(cells)


def main(argv: list[str] | None = None) -> None:
    """``python -m bb_align.lab.sim.v2i SIM_ROOT [RECOVERED_ROOT]``: the anchors' metrics of the lidar_i2v files
    against the simulator's truth (before, and after recovery), overall and by distance."""
    import sys

    from ..evaluation.runner import DIST_BUCKETS
    from ..evaluation.summary import anchor_metrics

    args = sys.argv[1:] if argv is None else argv
    if not 1 <= len(args) <= 2:
        raise SystemExit("usage: python -m bb_align.lab.sim.v2i SIM_ROOT [RECOVERED_ROOT]")
    for name in args:
        s = score_against_truth(name, args[0])
        rows = s["per_frame"]
        print(f"{name}: {s['frames']} frames")
        for bucket, (lo, hi) in {"all": (0.0, math.inf), **DIST_BUCKETS}.items():
            sel = [r for r in rows if lo <= r["distance_m"] < hi]
            if not sel:
                continue
            a = anchor_metrics(
                np.array([r["t_err_m"] for r in sel]), np.array([r["r_err_deg"] for r in sel]), np.ones(len(sel), bool)
            )
            print(
                f"  {bucket:>6} ({len(sel):3d}): success@1/2/3 {_fmt3(a['success_at_m'], True)}"
                f"  mRTE {_fmt3(a['mRTE_m'])} m  mRRE {_fmt3(a['mRRE_deg'])} deg"
            )


if __name__ == "__main__":
    main()
