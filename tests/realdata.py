"""Loaders for the real scans in ../shared/data (tests only) and the moved-copy experiment of issue 2."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from bb_align.engine.boxes import transform_boxes
from bb_align.engine.geometry import se2, se3_from_se2, transform_points_3d


def kitti_scan(data: Path, frame: str) -> np.ndarray:
    return np.fromfile(data / "kitti_seq08_pair" / f"{frame}.bin", np.float32).reshape(-1, 4)


def av2_scan(data: Path) -> tuple[np.ndarray, np.ndarray]:
    """AV2 sweep (ego-vehicle frame) and its annotated boxes [x, y, z, l, w, h, yaw]."""
    folder = data / "av2_sensor_7fab2350"
    ts = "315966265259836000"
    pts = np.fromfile(folder / f"lidar_{ts}.bin", np.float32).reshape(-1, 5)
    boxes = []
    with open(folder / f"annotations_{ts}.csv", newline="") as f:
        for r in csv.DictReader(f):
            yaw = 2.0 * np.arctan2(float(r["qz"]), float(r["qw"]))  # rotation about z only
            boxes.append(
                [
                    float(r["tx_m"]),
                    float(r["ty_m"]),
                    float(r["tz_m"]),
                    float(r["length_m"]),
                    float(r["width_m"]),
                    float(r["height_m"]),
                    yaw,
                ]
            )
    return pts, np.array(boxes)


def nuscenes_scan(data: Path) -> tuple[np.ndarray, np.ndarray]:
    folder = data / "mmdet3d_single_scans"
    pts = np.fromfile(folder / "nuscenes_LIDAR_TOP_1532402927647951.pcd.bin", np.float32).reshape(-1, 5)
    info = json.loads((folder / "nuscenes_sample_info_mmdet3d.json").read_text())
    boxes = np.array([inst["bbox_3d"] for inst in info["data_list"][0]["instances"]], dtype=float)
    return pts, boxes


def moved_copy(
    pts_ego: np.ndarray,
    boxes_ego: np.ndarray,
    seed: int,
    *,
    max_shift: float = 40.0,
    drop: float = 0.3,
    max_range: float = 80.0,
):
    """The scan seen from a random pose: any yaw in (-180, 180], a shift up to max_shift, a random fraction of
    points dropped, cropped to max_range around the new sensor. Returns (pts_peer, boxes_peer, T_ego_peer)."""
    rng = np.random.default_rng(seed)
    yaw = np.pi - rng.uniform(0, 2 * np.pi)
    r, a = max_shift * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
    T2_ego_peer = se2(yaw, r * np.cos(a), r * np.sin(a))
    T_peer_ego = np.linalg.inv(se3_from_se2(T2_ego_peer))
    keep = rng.random(len(pts_ego)) >= drop
    pts_peer = transform_points_3d(T_peer_ego, pts_ego[keep])
    pts_peer = pts_peer[np.hypot(pts_peer[:, 0], pts_peer[:, 1]) < max_range]
    boxes_peer = transform_boxes(np.linalg.inv(T2_ego_peer), boxes_ego)
    boxes_peer = boxes_peer[np.hypot(boxes_peer[:, 0], boxes_peer[:, 1]) < max_range]
    return pts_peer.astype(np.float32), boxes_peer, se3_from_se2(T2_ego_peer)
