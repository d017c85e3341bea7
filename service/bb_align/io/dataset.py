"""OPV2V / V2V4Real dataset layout: read it, and write it (the simulator's output).

    ROOT/<scenario>/<agent_id>/<timestamp>.pcd    x y z [intensity], the agent's sensor frame
    ROOT/<scenario>/<agent_id>/<timestamp>.yaml   lidar_pose, vehicles, optional detections
    (or the same one level down in split folders: ROOT/train|validate|test/<scenario>/...)

- ``lidar_pose``: ``[x, y, z, roll, yaw, pitch]`` (metres, degrees) turned into T_world_sensor by OpenCOOD's
  ``x_to_world`` formula, or a 4x4 matrix (V2V4Real), nested or flat.
- ``vehicles``: ``{id: {location, center, extent, angle}}`` in the world frame; the box centre is
  ``location + center``, ``extent`` holds HALF sizes, ``angle`` is ``[roll, yaw, pitch]`` in degrees.
- ``detections`` (optional, this project's extension): ``[[x, y, z, l, w, h, yaw], ...]`` in the agent's sensor
  frame (yaw in radians); ``detection_scores`` (optional) one confidence per detection.

Agents of a scenario with the same timestamp were captured together; the lowest agent id is the ego.

A DAIR-V2X-C root (``cooperative/data_info.json``; see ``bb_align.io.dair``) is read by the same
:func:`iter_frames`: the vehicle is the ego, the roadside unit the peer.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from bb_align.engine.boxes import as_boxes

# ---- poses -------------------------------------------------------------------------------------------------


def x_to_world(pose) -> np.ndarray:
    """OpenCOOD's formula: ``[x, y, z, roll, yaw, pitch]`` (degrees) -> 4x4 T_world_x.

    Equals Rz(yaw) @ Ry(-pitch) @ Rx(-roll) with this project's right-handed rotations (CARLA's sign
    convention for roll and pitch)."""
    p = np.asarray(pose, dtype=float).reshape(-1)
    if p.shape != (6,) or not np.all(np.isfinite(p)):
        raise ValueError(f"lidar_pose must be 6 finite numbers [x, y, z, roll, yaw, pitch], got {pose!r}")
    x, y, z, roll, yaw, pitch = p
    cy, sy = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    cr, sr = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    cp, sp = math.cos(math.radians(pitch)), math.sin(math.radians(pitch))
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    T[0, :3] = (cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr)
    T[1, :3] = (sy * cp, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr)
    T[2, :3] = (sp, -cp * sr, cp * cr)
    return T


def world_to_x_pose(T_world_x: np.ndarray) -> list[float]:
    """Inverse of :func:`x_to_world`: 4x4 -> ``[x, y, z, roll, yaw, pitch]`` (degrees)."""
    T = np.asarray(T_world_x, dtype=float)
    pitch = math.degrees(math.asin(float(np.clip(T[2, 0], -1.0, 1.0))))
    yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]))
    roll = math.degrees(math.atan2(-T[2, 1], T[2, 2]))
    return [float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), roll, yaw, pitch]


def parse_lidar_pose(value) -> np.ndarray:
    """A yaml ``lidar_pose`` (6-vector, 4x4 nested or 16 flat numbers) -> 4x4 T_world_sensor."""
    arr = np.asarray(value, dtype=float)
    if arr.size == 6:
        return x_to_world(arr)
    if arr.size == 16:
        T = arr.reshape(4, 4)
        if not np.all(np.isfinite(T)) or not np.allclose(T[3], (0, 0, 0, 1), atol=1e-6):
            raise ValueError("lidar_pose as a 4x4 matrix must be finite with last row [0, 0, 0, 1]")
        return T
    raise ValueError(f"lidar_pose must have 6 numbers [x, y, z, roll, yaw, pitch] or 16 (4x4), got {arr.size}")


def parse_vehicle(obj: dict) -> np.ndarray:
    """One yaml vehicle {location, center, extent, angle} -> world box [x, y, z, l, w, h, yaw(rad)]."""
    try:
        loc = np.asarray(obj["location"], dtype=float).reshape(3)
        ext = np.asarray(obj["extent"], dtype=float).reshape(3)
        ang = np.asarray(obj.get("angle", [0.0, 0.0, 0.0]), dtype=float).reshape(3)
        ctr = np.asarray(obj.get("center", [0.0, 0.0, 0.0]), dtype=float).reshape(3)
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"vehicle needs location[3], extent[3] (half sizes), angle[3], center[3]: {exc}") from exc
    c = loc + ctr
    return np.array([c[0], c[1], c[2], 2 * ext[0], 2 * ext[1], 2 * ext[2], math.radians(ang[1])])


def vehicle_entry(box_world: np.ndarray) -> dict:
    """World box [x, y, z, l, w, h, yaw] -> yaml vehicle entry (z is the box centre; location on the ground)."""
    x, y, z, l, w, h, yaw = (float(v) for v in box_world)
    return {
        "location": [x, y, z - h / 2],
        "center": [0.0, 0.0, h / 2],
        "extent": [l / 2, w / 2, h / 2],
        "angle": [0.0, math.degrees(yaw), 0.0],
    }


# ---- reading -----------------------------------------------------------------------------------------------


@dataclass
class AgentFrame:
    """One agent's files at one timestamp."""

    scenario: str
    agent: str
    timestamp: str
    pcd_path: Path  # (a bag's frames: the bag, their points held in ``points``)
    T_world_sensor: np.ndarray | None  # the reference pose (None: a recording without one, e.g. a bag)
    vehicles: dict[str, np.ndarray]  # id -> world box [x, y, z, l, w, h, yaw]
    detections: np.ndarray | None = None  # (K, 7) sensor frame, or None when the yaml has none
    detection_scores: np.ndarray | None = None
    extra: dict = field(default_factory=dict)  # other yaml keys (e.g. the simulator's sensor name)
    points: np.ndarray | None = field(default=None, repr=False)  # in memory (a bag's sweep), else read from pcd_path

    def load_points(self) -> np.ndarray:
        """(N, 3+) float32 points in the sensor frame."""
        from .clouds import load_cloud

        if self.points is not None:
            return self.points

        return load_cloud(self.pcd_path)


@dataclass
class FrameGroup:
    """All agents of one scenario at one timestamp; ``agents`` is ordered with the ego first."""

    scenario: str
    timestamp: str
    agents: dict[str, AgentFrame]

    @property
    def ego(self) -> AgentFrame:
        return next(iter(self.agents.values()))

    @property
    def peers(self) -> list[AgentFrame]:
        return list(self.agents.values())[1:]


def agent_order(ids) -> list[str]:
    """Agent ids lowest first: numerically when all are integers (OPV2V's '641' < '1005'), else as text."""
    ids = [str(i) for i in ids]
    try:
        return sorted(ids, key=lambda a: (int(a), a))
    except ValueError:
        return sorted(ids)


def read_agent_frame(yaml_path: Path, scenario: str = "", agent: str = "") -> AgentFrame:
    yaml_path = Path(yaml_path)
    with open(yaml_path) as fh:
        meta = yaml.safe_load(fh) or {}
    if not isinstance(meta, dict) or "lidar_pose" not in meta:
        raise ValueError(f"{yaml_path}: missing 'lidar_pose'")
    try:
        T = parse_lidar_pose(meta["lidar_pose"])
        vehicles = {str(k): parse_vehicle(v) for k, v in (meta.get("vehicles") or {}).items()}
        dets = meta.get("detections")
        dets = None if dets is None else as_boxes(np.asarray(dets, dtype=float).reshape(-1, 7) if len(dets) else None)
        scores = meta.get("detection_scores")
        if scores is not None:
            scores = np.asarray(scores, dtype=float).reshape(-1)
            if dets is None or len(scores) != len(dets):
                raise ValueError("detection_scores needs one score per entry of 'detections'")
    except ValueError as exc:
        raise ValueError(f"{yaml_path}: {exc}") from exc
    pcd = yaml_path.with_suffix(".pcd")
    known = {"lidar_pose", "vehicles", "detections", "detection_scores"}
    return AgentFrame(
        scenario,
        agent,
        yaml_path.stem,
        pcd,
        T,
        vehicles,
        dets,
        scores,
        {k: v for k, v in meta.items() if k not in known},
    )


def _is_scenario(path: Path) -> bool:
    """A scenario folder holds agent folders with ``<timestamp>.yaml`` files."""
    return any(a.is_dir() and next(a.glob("*.yaml"), None) is not None for a in path.iterdir())


def find_scenarios(root: str | Path) -> list[tuple[str, Path]]:
    """The scenario folders under ``root``, as (name, path), sorted by name.

    Scenarios sit directly under ``root`` (``ROOT/<scenario>/<agent>/``) or one level down in split folders
    (``ROOT/train|validate|test/<scenario>/<agent>/``, OPV2V's and V2V4Real's download layout); a scenario
    found one level down is named ``<split>/<scenario>``."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root {root} is not a directory")
    found = []
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        if _is_scenario(d):
            found.append((d.name, d))
        else:
            found += [
                (f"{d.name}/{s.name}", s) for s in sorted(p for p in d.iterdir() if p.is_dir()) if _is_scenario(s)
            ]
    return found


def is_dair_root(root: str | Path) -> bool:
    """True when ``root`` is a DAIR-V2X-C root (``cooperative-vehicle-infrastructure`` or its parent)."""
    from .dair import find_dair_root

    return find_dair_root(root) is not None


def iter_frames(root: str | Path, min_agents: int = 2, *, system_error_offset: bool = False) -> Iterator[FrameGroup]:
    """Every (scenario, timestamp) with at least ``min_agents`` agents having both .yaml and .pcd, sorted.

    Scenarios are found by :func:`find_scenarios` (directly under ``root`` or in split folders). A DAIR-V2X-C
    root gives its cooperative frames instead (``system_error_offset``: the reference pose includes it; see
    ``bb_align.io.dair``)."""
    if is_dair_root(root):
        from .dair import iter_dair_frames

        yield from iter_dair_frames(root, system_error_offset=system_error_offset)
        return
    for name, scen in find_scenarios(root):
        yield from iter_scenario_frames(name, scen, min_agents)


def iter_scenario_frames(name: str, scen: str | Path, min_agents: int = 2) -> Iterator[FrameGroup]:
    """One scenario folder's frames in time order (as :func:`iter_frames`)."""
    agent_dirs = {p.name: p for p in Path(scen).iterdir() if p.is_dir()}
    stamps: dict[str, list[str]] = {}
    for a in agent_order(agent_dirs):
        for y in agent_dirs[a].glob("*.yaml"):
            if y.with_suffix(".pcd").exists():
                stamps.setdefault(y.stem, []).append(a)
    for ts in sorted(stamps):
        agents = stamps[ts]
        if len(agents) < min_agents:
            continue
        yield FrameGroup(name, ts, {a: read_agent_frame(agent_dirs[a] / f"{ts}.yaml", name, a) for a in agents})


# ---- writing -----------------------------------------------------------------------------------------------


def write_pcd(path: str | Path, points: np.ndarray) -> None:
    """(N, 3) or (N, 4: x, y, z, intensity) -> binary PCD via pypcd4."""
    from pypcd4 import PointCloud

    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise ValueError(f"points must be (N, 3) or (N, 4), got {pts.shape}")
    pc = PointCloud.from_xyzi_points(pts) if pts.shape[1] == 4 else PointCloud.from_xyz_points(pts)
    pc.save(Path(path))


def write_agent_frame(
    root: str | Path,
    scenario: str,
    agent: str,
    timestamp: str,
    points: np.ndarray,
    T_world_sensor: np.ndarray,
    vehicles: dict,
    detections: np.ndarray | None = None,
    detection_scores: np.ndarray | None = None,
    extra: dict | None = None,
    pose_as_matrix: bool = False,
) -> Path:
    """Write ``<timestamp>.pcd`` and ``<timestamp>.yaml`` for one agent; returns the yaml path.

    ``vehicles`` maps id -> world box [x, y, z, l, w, h, yaw]. ``pose_as_matrix`` writes lidar_pose as a 4x4
    (V2V4Real style) instead of the 6-vector."""
    d = Path(root) / scenario / str(agent)
    d.mkdir(parents=True, exist_ok=True)
    write_pcd(d / f"{timestamp}.pcd", points)
    T = np.asarray(T_world_sensor, dtype=float)
    meta: dict = {"lidar_pose": T.tolist() if pose_as_matrix else world_to_x_pose(T)}
    meta["vehicles"] = {
        int(k) if str(k).lstrip("-").isdigit() else str(k): vehicle_entry(np.asarray(v)) for k, v in vehicles.items()
    }
    if detections is not None:
        meta["detections"] = [[float(v) for v in row] for row in as_boxes(detections)]
        if detection_scores is not None:
            meta["detection_scores"] = [float(v) for v in detection_scores]
    meta.update(extra or {})
    path = d / f"{timestamp}.yaml"
    with open(path, "w") as fh:
        yaml.safe_dump(meta, fh, sort_keys=False, default_flow_style=None)
    return path
