"""A real run of ``../shared/data`` as two cars record it: the same steps as ``real_runs.track_run`` (the ego
driving the run's sweeps, the peer another sweep of it, each with its odometry and a GNSS-grade pose, the run's
reference poses as the truth), written either in the sequence layout (``bb-align track ROOT``) or as a ROS 2 bag
(``bb-align track BAG``), so both replays can be compared on the same data.

    frames = run_frames(Path("../shared/data"), "kitti08_run", steps=10)
    write_layout(frames, Path("out/kitti08_layout"))       # out/kitti08_layout/kitti08_run/{ego,peer}/*.yaml|pcd
    write_bag(frames, Path("out/kitti08.bag"))              # rosbag2, MCAP storage (the default topics)

The GNSS pose: the ego's is its reference pose, the peer's is placed so that the pair's relative pose carries the
seeded error of ``real_runs.gnss_errors`` (2 m / 2 deg), the prior ``track_run(gnss=True)`` gives.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bb_align.engine.geometry import se2, se3_from_se2
from bb_align.io.clouds import load_cloud
from bb_align.io.rosbag import BagTopics

from .real_runs import STEP_S, gnss_errors, run_poses, schedule

T0_NS = 1_700_000_000 * 10**9  # the recording's start (a stamp as a car's clock gives it)


@dataclass
class CarFrame:
    points: np.ndarray  # (N, 4) float32 x, y, z, reflectance
    T_world_sensor: np.ndarray  # the reference pose (the run's first sweep's frame is the world)
    odometry: np.ndarray
    gnss: np.ndarray


@dataclass
class StepFrames:
    stamp_ns: int
    ego: CarFrame | None  # None: nothing recorded by this car at this stamp (write_bag only)
    peer: CarFrame | None

    @property
    def stamp_s(self) -> float:
        """The stamp as a bag's reader gives it (sec + nanosec)."""
        return self.stamp_ns // 10**9 + (self.stamp_ns % 10**9) * 1e-9


def run_frames(data: Path, run: str, steps: int = 10, seed: int = 0) -> list[StepFrames]:
    """The first ``steps`` steps of ``real_runs.schedule(run)`` as two cars' frames."""
    folder = data / run
    poses = run_poses(folder)
    plan = schedule(run, laps=max(1, -(-steps // 10)))[:steps]
    errors = gnss_errors(len(plan), seed)
    out = []
    for i, (e, p) in enumerate(plan):
        T_true = np.linalg.inv(poses[e]) @ poses[p]
        gnss_peer = poses[e] @ se3_from_se2(se2(*errors[i])) @ T_true
        out.append(
            StepFrames(
                T0_NS + i * int(STEP_S * 1e9),
                CarFrame(load_cloud(folder / f"{e:06d}.bin"), poses[e], poses[e], poses[e]),
                CarFrame(load_cloud(folder / f"{p:06d}.bin"), poses[p], poses[p], gnss_peer),
            )
        )
    return out


def write_layout(frames: list[StepFrames], root: Path, name: str = "run") -> Path:
    """The sequence layout: ``root/name/{ego,peer}/<step>.pcd|yaml`` with lidar_pose (the truth),
    odometry_pose, gnss_pose (4x4) and timestamp_s. Returns ``root``."""
    from bb_align.io.dataset import write_agent_frame

    for k, f in enumerate(frames):
        for agent, car in (("0_ego", f.ego), ("1_peer", f.peer)):
            extra = {
                "odometry_pose": car.odometry.tolist(),
                "gnss_pose": car.gnss.tolist(),
                "timestamp_s": f.stamp_s,
            }
            write_agent_frame(root, name, agent, f"{k:06d}", car.points, car.T_world_sensor, {}, extra=extra,
                              pose_as_matrix=True)  # fmt: skip
    return root


def write_bag(frames: list[StepFrames], out: Path, topics: BagTopics | None = None, storage: str = "mcap") -> Path:
    """A rosbag2 (``storage``: mcap or sqlite3) with each car's PointCloud2, Odometry, GNSS pose
    (PoseWithCovarianceStamped) and reference pose (PoseStamped) on ``topics`` (the reader's defaults)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    topics = topics or BagTopics()
    ts = get_typestore(Stores.LATEST)
    T = ts.types
    kinds = {
        "points": "sensor_msgs/msg/PointCloud2",
        "odometry": "nav_msgs/msg/Odometry",
        "gnss": "geometry_msgs/msg/PoseWithCovarianceStamped",
        "reference": "geometry_msgs/msg/PoseStamped",
    }
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]

    def pose_msg(M: np.ndarray):
        from scipy.spatial.transform import Rotation

        qx, qy, qz, qw = Rotation.from_matrix(M[:3, :3]).as_quat()
        x, y, z = (float(v) for v in M[:3, 3])
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z),
            orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )

    def cloud_msg(header, pts: np.ndarray):
        fields = [
            T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
            for i, n in enumerate(("x", "y", "z", "intensity"))
        ]
        data = np.ascontiguousarray(pts[:, :4], dtype="<f4").view(np.uint8).reshape(-1)
        return T["sensor_msgs/msg/PointCloud2"](
            header=header, height=1, width=len(pts), fields=fields, is_bigendian=False, point_step=16,
            row_step=16 * len(pts), data=data, is_dense=True,
        )  # fmt: skip

    with Writer(out, version=9, storage_plugin=plugin) as writer:
        conns = {
            (car, kind): writer.add_connection(topics.topic(car, kind), msgtype, typestore=ts)
            for car in ("ego", "peer")
            for kind, msgtype in kinds.items()
        }
        zero_cov = np.zeros(36)
        for f in frames:
            stamp = T["builtin_interfaces/msg/Time"](sec=f.stamp_ns // 10**9, nanosec=f.stamp_ns % 10**9)
            for car_name, car in (("ego", f.ego), ("peer", f.peer)):
                if car is None:  # this car recorded nothing at this stamp
                    continue
                hdr = lambda frame_id: T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)  # noqa: B023
                msgs = {
                    "points": cloud_msg(hdr(f"{car_name}/velodyne"), car.points),
                    "odometry": T["nav_msgs/msg/Odometry"](
                        header=hdr(f"{car_name}/odom"),
                        child_frame_id=f"{car_name}/velodyne",
                        pose=T["geometry_msgs/msg/PoseWithCovariance"](
                            pose=pose_msg(car.odometry), covariance=zero_cov
                        ),
                        twist=T["geometry_msgs/msg/TwistWithCovariance"](
                            twist=T["geometry_msgs/msg/Twist"](
                                linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                            ),
                            covariance=zero_cov,
                        ),
                    ),
                    "gnss": T["geometry_msgs/msg/PoseWithCovarianceStamped"](
                        header=hdr("map"),
                        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(car.gnss), covariance=zero_cov),
                    ),
                    "reference": T["geometry_msgs/msg/PoseStamped"](
                        header=hdr("map"), pose=pose_msg(car.T_world_sensor)
                    ),
                }
                for kind, msg in msgs.items():
                    writer.write(conns[(car_name, kind)], f.stamp_ns, ts.serialize_cdr(msg, msg.__msgtype__))
    return out
