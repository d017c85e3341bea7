"""Real drives' poses in ``../shared/data`` as a car's 10 Hz odometry would give them: (3x3 ground poses, stamps s).

- KITTI 08's official poses: 4071 frames, 6.8 minutes of a residential drive (turns, stops, starts), in the first
  scan's LiDAR frame (z up);
- an Argoverse 2 log's ~100 Hz poses, taken at 10 Hz.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bb_align.engine.geometry import ground_se2

AV2_LOGS = ("av2_sensor_7fab2350", "av2_sensor_adcf7d18")


def kitti08_drive(data: Path) -> tuple[list[np.ndarray], np.ndarray]:
    folder = Path(data) / "kitti_seq08_pair"
    poses = np.loadtxt(folder / "poses_08_kitti_gt_cam0.txt").reshape(-1, 3, 4)
    cam = np.tile(np.eye(4), (len(poses), 1, 1))
    cam[:, :3, :4] = poses
    velo = cam @ np.loadtxt(folder / "Tr_velo_to_cam0_seq04-12.txt")
    velo = np.linalg.inv(velo[0]) @ velo
    return [ground_se2(T) for T in velo], np.loadtxt(folder / "times_08.txt")


def av2_drive(data: Path, log: str, dt: float = 0.1) -> tuple[list[np.ndarray], np.ndarray]:
    poses = np.load(Path(data) / log / "ego_to_city_poses.npy")
    stamps = np.load(Path(data) / log / "ego_poses_timestamps_ns.npy") * 1e-9
    idx = np.unique(np.searchsorted(stamps, np.arange(stamps[0], stamps[-1], dt)))
    return [ground_se2(poses[i]) for i in idx], stamps[idx]


def real_drives(data: Path) -> dict[str, tuple[list[np.ndarray], np.ndarray]]:
    """Every real drive above, by name."""
    out = {"KITTI 08": kitti08_drive(data)}
    out.update({f"AV2 {log.removeprefix('av2_sensor_')}": av2_drive(data, log) for log in AV2_LOGS})
    return out
