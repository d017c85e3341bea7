"""ROS 2 bags out: a tracked run's answers as a rosbag2 with MCAP storage (``DIR/metadata.yaml`` and
``DIR/<DIR name>.mcap``), written with ``rosbags``, in standard messages only, so Foxglove (or RViz through
``ros2 bag play``) shows it with no plugin:

- ``/tf`` (``tf2_msgs/TFMessage``): ``T_ego_peer`` of every successful answer, parent the ego's cloud frame, child
  the peer's (the frame ids of the clouds in the recording, so the input bag opened beside it places the peer's
  cloud in the ego's);
- ``/bb_align/peer_pose`` (``geometry_msgs/PoseWithCovarianceStamped``): the same pose with the answer's covariance:
  its 3-DoF (yaw, x, y) covariance in the 6x6's (x, y, rot_z) slots (m^2, m rad, rad^2); z, roll and pitch are not
  estimated (the ground plane's constants), their rows and columns are 0;
- ``/bb_align/verdict`` (``std_msgs/String``): every frame's verdict as JSON (success, reason, source, track state
  and event, confidence, 1-sigma, the promise's bounds);
- ``/bb_align/ego/bev/compressed``, ``/bb_align/peer/bev/compressed`` (``sensor_msgs/CompressedImage``, format
  ``png``): each frame's two BV images (row 0 is the car's front, column 0 its left).

Every message is stamped (header and log time) with the frame's time: the peer sweep's header stamp for a bag.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

TOPIC_TF = "/tf"
TOPIC_POSE = "/bb_align/peer_pose"
TOPIC_VERDICT = "/bb_align/verdict"
TOPIC_BEV = {"ego": "/bb_align/ego/bev/compressed", "peer": "/bb_align/peer/bev/compressed"}
# (yaw, tx, ty), the answer's covariance order -> the slots of a ROS 6x6 (x, y, z, rot_x, rot_y, rot_z)
_SLOTS = (5, 0, 1)


def ros_covariance(cov3) -> np.ndarray:
    """The answer's 3x3 covariance of (yaw rad, tx m, ty m) -> a ROS 6x6 (row-major, 36 numbers)."""
    out = np.zeros((6, 6))
    c = np.asarray(cov3, dtype=float)
    for i, a in enumerate(_SLOTS):
        for j, b in enumerate(_SLOTS):
            out[a, b] = c[i, j]
    return out.reshape(36)


def _time_ns(stamp: float) -> int:
    return int(round(stamp * 1e9))


def write_results_bag(
    out: str | Path,
    records: list[dict],
    frame_ids: dict[str, str],
    *,
    max_error_m: float,
    max_error_deg: float,
    confidence: float,
) -> Path:
    """Write one sequence's records (``replay_groups`` with ``bev_images``) as a rosbag2 with MCAP storage at
    ``out`` (a new directory); returns the MCAP file's path. Stamps before 0 (simulated sequences start a few ms
    early) are shifted so that the first is 0."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.LATEST)
    T = ts.types
    shift = max(0.0, -min((r["stamp"] for r in records), default=0.0))
    ego_id, peer_id = frame_ids["ego"], frame_ids["peer"]
    with Writer(Path(out), version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            TOPIC_TF: writer.add_connection(TOPIC_TF, "tf2_msgs/msg/TFMessage", typestore=ts),
            TOPIC_POSE: writer.add_connection(TOPIC_POSE, "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=ts),
            TOPIC_VERDICT: writer.add_connection(TOPIC_VERDICT, "std_msgs/msg/String", typestore=ts),
        }
        for topic in TOPIC_BEV.values():
            conns[topic] = writer.add_connection(topic, "sensor_msgs/msg/CompressedImage", typestore=ts)

        def put(topic: str, msg, t_ns: int) -> None:
            writer.write(conns[topic], t_ns, ts.serialize_cdr(msg, msg.__msgtype__))

        for r in records:
            t_ns = _time_ns(r["stamp"] + shift)
            stamp = T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
            header = T["std_msgs/msg/Header"](stamp=stamp, frame_id=ego_id)
            cov = r.get("covariance")
            sigma = None if cov is None else np.sqrt(np.maximum(np.diag(cov), 0.0))
            verdict = {
                "stamp": r["stamp"],
                "frame": r["frame"],
                "success": r["success"],
                "reason": r["reason"],
                "source": r["source"],
                "track_state": r["state"],
                "track_event": r["event"],
                "confidence": r.get("confidence"),
                "sigma_yaw_deg": None if sigma is None else float(np.degrees(sigma[0])),
                "sigma_x_m": None if sigma is None else float(sigma[1]),
                "sigma_y_m": None if sigma is None else float(sigma[2]),
                "promise": {"max_error_m": max_error_m, "max_error_deg": max_error_deg, "confidence": confidence},
            }
            put(TOPIC_VERDICT, T["std_msgs/msg/String"](data=json.dumps(verdict)), t_ns)
            for car, png in zip(("ego", "peer"), r.get("bev_png") or ()):
                img_header = T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_ids[car])
                data = np.frombuffer(png, dtype=np.uint8)
                put(
                    TOPIC_BEV[car],
                    T["sensor_msgs/msg/CompressedImage"](header=img_header, format="png", data=data),
                    t_ns,
                )
            if not r["success"]:
                continue
            M = np.asarray(r["T_ego_peer"], dtype=float)
            qx, qy, qz, qw = Rotation.from_matrix(M[:3, :3]).as_quat()
            quat = T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
            x, y, z = (float(v) for v in M[:3, 3])
            tf = T["geometry_msgs/msg/TransformStamped"](
                header=header,
                child_frame_id=peer_id,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z), rotation=quat
                ),
            )
            put(TOPIC_TF, T["tf2_msgs/msg/TFMessage"](transforms=[tf]), t_ns)
            pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z), orientation=quat)
            pwc = T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=ros_covariance(cov))
            put(TOPIC_POSE, T["geometry_msgs/msg/PoseWithCovarianceStamped"](header=header, pose=pwc), t_ns)
    return Path(out) / f"{Path(out).name}.mcap"
