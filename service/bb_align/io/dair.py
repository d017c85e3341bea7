"""DAIR-V2X-C (vehicle-infrastructure cooperative) layout: read it, and write it (the simulator's V2I output).

    ROOT/cooperative/data_info.json                   one entry per cooperative frame (below)
    ROOT/cooperative/calib/lidar_i2v/<veh id>.json    {"rotation": 3x3, "translation": 3x1}: p_vehicle = R p_infra + t
    ROOT/vehicle-side/velodyne/<veh id>.pcd           the vehicle LiDAR, its own frame
    ROOT/vehicle-side/label/lidar/<veh id>.json       its 3-D boxes, same frame
    ROOT/infrastructure-side/velodyne/<inf id>.pcd    the roadside LiDAR, already in its "virtual LiDAR" frame
    ROOT/infrastructure-side/label/virtuallidar/<inf id>.json

ROOT is ``cooperative-vehicle-infrastructure`` itself or its parent. A ``cooperative/data_info.json`` entry
names ``vehicle_pointcloud_path`` and ``infrastructure_pointcloud_path`` (relative to ROOT), and usually
``system_error_offset`` ``{"delta_x", "delta_y"}`` (metres); ``calib_lidar_i2v_path`` when present, else the
calibration is ``cooperative/calib/lidar_i2v/<vehicle frame id>.json`` as DAIR-V2X's tools name it.

``system_error_offset``: DAIR-V2X-C's measured systematic error of the roadside unit's world pose for the frame's
batch, a shift of ``virtuallidar_to_world``'s translation in the WORLD frame. DAIR-V2X's ``calib_i2v.py`` adds
it to ``virtuallidar_to_world`` before composing ``lidar_i2v``; so, in the vehicle LiDAR frame, it shifts
``lidar_i2v``'s translation by ``R_vlidar_world @ (delta_x, delta_y, 0)``. Whether a given ``lidar_i2v`` file
already holds it depends on the tool that wrote it; the reader scores against the file as stored unless asked
(``system_error_offset=True``), and then rotates the offset into the vehicle frame with
``vehicle-side/calib/novatel_to_world`` and ``lidar_to_novatel`` (without them: adds it unrotated, and says so).

Labels (DAIR-V2X's single-view format): a list of ``{"type", "3d_location": {x, y, z} (box centre),
"3d_dimensions": {h, w, l}, "rotation": yaw (rad)}``. The engine takes the vehicle classes (Car, Truck, Van,
Bus: the classes of DAIR-V2X-C's cooperative labels).

As frame groups (:class:`bb_align.io.dataset.FrameGroup`): the scenario is ``""``, the timestamp the vehicle
frame id, the agents ``vehicle-side`` (the ego, ``T_world_sensor`` = identity) and ``infrastructure-side`` (the
peer, ``T_world_sensor`` = the lidar_i2v reference). Per-frame detection files then sit at
``DIR/vehicle-side/<veh id>.json`` and ``DIR/infrastructure-side/<inf id>.json``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bb_align.engine.boxes import as_boxes

from .dataset import AgentFrame, FrameGroup

COOP_DIR = "cooperative-vehicle-infrastructure"
DATA_INFO = "cooperative/data_info.json"
EGO, PEER = "vehicle-side", "infrastructure-side"
VEHICLE_CLASSES = ("car", "truck", "van", "bus")


# ---- files -------------------------------------------------------------------------------------------------


def find_dair_root(root: str | Path) -> Path | None:
    """The ``cooperative-vehicle-infrastructure`` folder: ``root`` itself or its child; None when neither holds
    ``cooperative/data_info.json``."""
    root = Path(root)
    for cand in (root, root / COOP_DIR):
        if (cand / DATA_INFO).is_file():
            return cand
    return None


def _load_json(path: Path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not readable JSON ({exc})") from exc


def _calib_block(data, path: Path) -> dict:
    """The dict holding rotation/translation (DAIR nests some calibrations under "transform")."""
    if isinstance(data, dict) and isinstance(data.get("transform"), dict):
        data = data["transform"]
    if not isinstance(data, dict) or "rotation" not in data or "translation" not in data:
        raise ValueError(f"{path}: needs 'rotation' (3x3) and 'translation' (3 numbers)")
    return data


def read_calib(path: str | Path) -> np.ndarray:
    """A DAIR calibration file ({"rotation": 3x3, "translation": 3x1}, optionally under "transform") -> 4x4."""
    path = Path(path)
    block = _calib_block(_load_json(path), path)
    try:
        R = np.asarray(block["rotation"], dtype=float).reshape(3, 3)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: 'rotation' must be 3x3 numbers") from exc
    try:
        t = np.asarray(block["translation"], dtype=float).reshape(3)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: 'translation' must be 3 numbers (3x1)") from exc
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError(f"{path}: 'rotation' and 'translation' must be finite")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise ValueError(f"{path}: 'rotation' is not a rotation matrix (R R^T != I within 1e-3, or det < 0)")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def calib_text(T: np.ndarray, template: dict | None = None) -> str:
    """A 4x4 as a DAIR calibration file: ``template``'s keys and nesting kept, rotation and translation (3x1)
    replaced."""
    T = np.asarray(T, dtype=float)
    block = {"rotation": T[:3, :3].tolist(), "translation": [[float(v)] for v in T[:3, 3]]}
    if template is None:
        return json.dumps(block)
    out = json.loads(json.dumps(template))
    target = out["transform"] if isinstance(out.get("transform"), dict) else out
    target.update(block)
    return json.dumps(out)


def read_labels(path: str | Path, classes: tuple[str, ...] | None = VEHICLE_CLASSES) -> np.ndarray:
    """DAIR-V2X single-view labels -> (K, 7) [x, y, z, l, w, h, yaw] in the file's LiDAR frame; only ``classes``
    (case-insensitive; None: all)."""
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, list):
        raise ValueError(f"{path}: labels must be a JSON list of objects")
    rows = []
    for i, obj in enumerate(data):
        where = f"{path}[{i}]"
        if not isinstance(obj, dict):
            raise ValueError(f"{where}: a label must be an object")
        if classes is not None and str(obj.get("type", "")).lower() not in classes:
            continue
        try:
            loc, dim = obj["3d_location"], obj["3d_dimensions"]
            rows.append(
                [
                    float(loc["x"]),
                    float(loc["y"]),
                    float(loc["z"]),
                    float(dim["l"]),
                    float(dim["w"]),
                    float(dim["h"]),
                    float(obj["rotation"]),
                ]
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(
                f"{where}: needs 3d_location {{x, y, z}}, 3d_dimensions {{h, w, l}} and rotation (yaw, rad): {exc!r}"
            ) from exc
    try:
        return as_boxes(np.array(rows, dtype=float).reshape(-1, 7))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


def label_entries(boxes: np.ndarray, kind: str = "Car") -> list[dict]:
    """(K, 7) boxes -> DAIR-V2X single-view label objects."""
    out = []
    for x, y, z, l, w, h, yaw in as_boxes(boxes):
        out.append(
            {
                "type": kind,
                "truncated_state": 0,
                "occluded_state": 0,
                "alpha": 0.0,
                "3d_dimensions": {"h": float(h), "w": float(w), "l": float(l)},
                "3d_location": {"x": float(x), "y": float(y), "z": float(z)},
                "rotation": float(yaw),
            }
        )
    return out


# ---- pairs ---------------------------------------------------------------------------------------------------


@dataclass
class DairPair:
    """One entry of cooperative/data_info.json, resolved against the root."""

    index: int
    vehicle_id: str
    infra_id: str
    vehicle_pcd: Path
    infra_pcd: Path
    lidar_i2v: Path  # cooperative/calib/lidar_i2v/<veh id>.json
    vehicle_label: Path
    infra_label: Path
    offset_xy: tuple[float, float] | None  # system_error_offset (delta_x, delta_y), world frame; None: absent
    entry: dict = field(default_factory=dict, repr=False)


def _offset(value, where: str) -> tuple[float, float] | None:
    if value in (None, ""):
        return None
    try:
        dx, dy = float(value["delta_x"]), float(value["delta_y"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: 'system_error_offset' needs numbers 'delta_x' and 'delta_y'") from exc
    if not (math.isfinite(dx) and math.isfinite(dy)):
        raise ValueError(f"{where}: 'system_error_offset' must be finite")
    return dx, dy


def inside(base: Path, relative, where: str) -> Path:
    """``base / relative`` for a path read from the dataset, refused (ValueError naming ``where``) when it is
    absolute or leaves ``base``, by ``..`` or through a symbolic link: the dataset names files inside itself."""
    if not isinstance(relative, str) or not relative or Path(relative).is_absolute():
        raise ValueError(f"{where}: {relative!r} is not a path relative to {base} (outside the dataset root)")
    base = Path(os.path.normpath(base))
    path = Path(os.path.normpath(base / relative))
    if not path.is_relative_to(base) or not path.resolve().is_relative_to(base.resolve()):
        raise ValueError(f"{where}: {relative!r} leads outside the dataset root {base}")
    return path


def read_pairs(root: str | Path) -> tuple[list[DairPair], list[str]]:
    """The cooperative frames whose files are all present, and a note for each entry left out (missing files,
    a vehicle frame listed twice). ``root``: the cooperative folder or its parent."""
    base = find_dair_root(root)
    if base is None:
        raise FileNotFoundError(f"{root}: no {DATA_INFO} here or under {COOP_DIR}/ (not a DAIR-V2X-C root)")
    info_path = base / DATA_INFO
    info = _load_json(info_path)
    if not isinstance(info, list):
        raise ValueError(f"{info_path}: must be a JSON list of cooperative frames")
    pairs, skipped, seen = [], [], set()
    for i, e in enumerate(info):
        where = f"{info_path}[{i}]"
        if not isinstance(e, dict):
            raise ValueError(f"{where}: an entry must be an object")
        missing = [k for k in ("vehicle_pointcloud_path", "infrastructure_pointcloud_path") if not e.get(k)]
        if missing:
            raise ValueError(f"{where}: missing {', '.join(missing)}")
        veh = Path(e["vehicle_pointcloud_path"]).stem
        inf = Path(e["infrastructure_pointcloud_path"]).stem
        calib = e.get("calib_lidar_i2v_path") or f"cooperative/calib/lidar_i2v/{veh}.json"
        pair = DairPair(
            i,
            veh,
            inf,
            inside(base, e["vehicle_pointcloud_path"], f"{where}.vehicle_pointcloud_path"),
            inside(base, e["infrastructure_pointcloud_path"], f"{where}.infrastructure_pointcloud_path"),
            inside(base, calib, f"{where}.calib_lidar_i2v_path"),
            base / EGO / "label" / "lidar" / f"{veh}.json",
            base / PEER / "label" / "virtuallidar" / f"{inf}.json",
            _offset(e.get("system_error_offset"), where),
            e,
        )
        absent = [p for p in (pair.vehicle_pcd, pair.infra_pcd, pair.lidar_i2v) if not p.is_file()]
        if absent:
            skipped.append(f"vehicle frame {veh}: missing {', '.join(str(p.relative_to(base)) for p in absent)}")
        elif veh in seen:
            skipped.append(f"vehicle frame {veh}: listed twice (entry {i} left out; lidar_i2v is per vehicle frame)")
        else:
            seen.add(veh)
            pairs.append(pair)
    return pairs, skipped


def world_rotation_of_vehicle(base: Path, vehicle_id: str) -> np.ndarray | None:
    """R_world_vlidar from vehicle-side/calib/novatel_to_world and lidar_to_novatel (None when absent)."""
    calib = base / EGO / "calib"
    n2w, l2n = calib / "novatel_to_world" / f"{vehicle_id}.json", calib / "lidar_to_novatel" / f"{vehicle_id}.json"
    if not (n2w.is_file() and l2n.is_file()):
        return None
    return (read_calib(n2w) @ read_calib(l2n))[:3, :3]


def with_system_error_offset(
    T_i2v: np.ndarray, offset_xy: tuple[float, float], R_world_vlidar: np.ndarray | None
) -> np.ndarray:
    """lidar_i2v with the roadside unit's world position shifted by (delta_x, delta_y): the translation moves by
    R_vlidar_world @ (dx, dy, 0) (unrotated when the vehicle's world rotation is unknown)."""
    d = np.array([offset_xy[0], offset_xy[1], 0.0])
    T = np.array(T_i2v, dtype=float)
    T[:3, 3] += d if R_world_vlidar is None else np.asarray(R_world_vlidar).T @ d
    return T


def reference(base: Path, pair: DairPair, system_error_offset: bool = False) -> tuple[np.ndarray, str]:
    """The pair's reference T_vehicle_infra and what it is ("lidar_i2v", "lidar_i2v+offset(world)",
    "lidar_i2v+offset(unrotated)")."""
    T = read_calib(pair.lidar_i2v)
    if not system_error_offset or pair.offset_xy is None or pair.offset_xy == (0.0, 0.0):
        return T, "lidar_i2v"
    R = world_rotation_of_vehicle(base, pair.vehicle_id)
    return with_system_error_offset(T, pair.offset_xy, R), (
        "lidar_i2v+offset(world)" if R is not None else "lidar_i2v+offset(unrotated)"
    )


def _labels_or_none(path: Path) -> np.ndarray | None:
    return read_labels(path) if path.is_file() else None


def _world_boxes(prefix: str, boxes: np.ndarray | None, T_world_sensor: np.ndarray) -> dict[str, np.ndarray]:
    """Sensor-frame labels as the 'world' boxes an AgentFrame holds (ids per side: DAIR-V2X-C's single-view
    labels share no ids between the two sides)."""
    if boxes is None or not len(boxes):
        return {}
    out = boxes.copy()
    out[:, :3] = boxes[:, :3] @ T_world_sensor[:3, :3].T + T_world_sensor[:3, 3]
    out[:, 6] = boxes[:, 6] + math.atan2(T_world_sensor[1, 0], T_world_sensor[0, 0])
    return {f"{prefix}{i}": b for i, b in enumerate(out)}


def frame_group(base: Path, pair: DairPair, system_error_offset: bool = False) -> FrameGroup:
    """One cooperative frame as a FrameGroup: the vehicle (ego, identity pose) and the roadside unit (peer, at
    the reference transform); each side's labels as its detections."""
    T_ref, kind = reference(base, pair, system_error_offset)
    ego_boxes, peer_boxes = _labels_or_none(pair.vehicle_label), _labels_or_none(pair.infra_label)
    extra = {"detections_from": "labels", "reference": kind, "infrastructure_frame": pair.infra_id}
    ego = AgentFrame(
        "",
        EGO,
        pair.vehicle_id,
        pair.vehicle_pcd,
        np.eye(4),
        _world_boxes("v", ego_boxes, np.eye(4)),
        ego_boxes,
        None,
        {**extra, "sensor": "vehicle"},
    )
    peer = AgentFrame(
        "",
        PEER,
        pair.infra_id,
        pair.infra_pcd,
        T_ref,
        _world_boxes("i", peer_boxes, T_ref),
        peer_boxes,
        None,
        {**extra, "sensor": "infrastructure"},
    )
    return FrameGroup("", pair.vehicle_id, {EGO: ego, PEER: peer})


def iter_dair_frames(root: str | Path, system_error_offset: bool = False) -> Iterator[FrameGroup]:
    """Every complete cooperative frame of a DAIR-V2X-C root, in data_info.json order."""
    base = find_dair_root(root)
    pairs, _ = read_pairs(root)
    for p in pairs:
        yield frame_group(base, p, system_error_offset)


# ---- writing -----------------------------------------------------------------------------------------------


def write_dair_pcd(path: str | Path, points: np.ndarray, side: str, timestamp_s: float = 0.0) -> None:
    """A cloud as DAIR-V2X-C ships it (binary_compressed): the vehicle side x y z intensity(uint8 0-255)
    timestamp(float64 s), the infrastructure side x y z intensity(float32 0-1)."""
    from pypcd4 import Encoding, PointCloud

    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, 3+), got {pts.shape}")
    inten = pts[:, 3] if pts.shape[1] > 3 else np.zeros(len(pts), np.float32)
    xyz = [pts[:, 0], pts[:, 1], pts[:, 2]]
    if side == EGO:
        cols = [*xyz, np.clip(np.round(inten * 255), 0, 255).astype(np.uint8), np.full(len(pts), timestamp_s)]
        pc = PointCloud.from_points(
            cols, ("x", "y", "z", "intensity", "timestamp"), (np.float32,) * 3 + (np.uint8, np.float64)
        )
    elif side == PEER:
        pc = PointCloud.from_points([*xyz, inten], ("x", "y", "z", "intensity"), (np.float32,) * 4)
    else:
        raise ValueError(f"side must be {EGO!r} or {PEER!r}, got {side!r}")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    pc.save(Path(path), encoding=Encoding.BINARY_COMPRESSED)


@dataclass
class DairFrameFiles:
    """What the writer needs for one cooperative frame."""

    vehicle_id: str
    infra_id: str
    vehicle_points: np.ndarray  # vehicle LiDAR frame
    infra_points: np.ndarray  # virtual LiDAR frame
    vehicle_boxes: np.ndarray  # (K, 7) vehicle LiDAR frame
    infra_boxes: np.ndarray  # (K, 7) virtual LiDAR frame
    T_i2v: np.ndarray  # what to write as lidar_i2v
    offset_xy: tuple[float, float] = (0.0, 0.0)
    timestamp_s: float = 0.0


def write_dair_root(root: str | Path, frames: list[DairFrameFiles]) -> Path:
    """Write a DAIR-V2X-C root (``root/cooperative-vehicle-infrastructure``) holding ``frames``; returns the
    cooperative folder."""
    base = Path(root) / COOP_DIR
    info = []
    for f in frames:
        write_dair_pcd(base / EGO / "velodyne" / f"{f.vehicle_id}.pcd", f.vehicle_points, EGO, f.timestamp_s)
        write_dair_pcd(base / PEER / "velodyne" / f"{f.infra_id}.pcd", f.infra_points, PEER)
        for side, sub, fid, boxes in (
            (EGO, "lidar", f.vehicle_id, f.vehicle_boxes),
            (PEER, "virtuallidar", f.infra_id, f.infra_boxes),
        ):
            p = base / side / "label" / sub / f"{fid}.json"
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(json.dumps(label_entries(boxes)))
        calib = base / "cooperative" / "calib" / "lidar_i2v" / f"{f.vehicle_id}.json"
        calib.parent.mkdir(parents=True, exist_ok=True)
        calib.write_text(calib_text(f.T_i2v))
        info.append(
            {
                "infrastructure_image_path": f"{PEER}/image/{f.infra_id}.jpg",
                "infrastructure_pointcloud_path": f"{PEER}/velodyne/{f.infra_id}.pcd",
                "vehicle_image_path": f"{EGO}/image/{f.vehicle_id}.jpg",
                "vehicle_pointcloud_path": f"{EGO}/velodyne/{f.vehicle_id}.pcd",
                "cooperative_label_path": f"cooperative/label_world/{f.vehicle_id}.json",
                "system_error_offset": {"delta_x": float(f.offset_xy[0]), "delta_y": float(f.offset_xy[1])},
            }
        )
    (base / DATA_INFO).parent.mkdir(parents=True, exist_ok=True)
    (base / DATA_INFO).write_text(json.dumps(info, indent=1))
    return base
