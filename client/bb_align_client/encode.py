"""Build a wire Frame from a LiDAR sweep, and read a Result."""

from __future__ import annotations

from typing import Any

import numpy as np

from bb_align.engine.bev import BevImage, make_bev
from bb_align.engine.boxes import as_boxes
from bb_align.engine.config import BevConfig
from bb_align.protocol import (
    FLEET_KEY_ID,
    JSON,
    MSGPACK,
    BevMeta,
    Credential,
    Frame,
    Pose,
    Result,
    is_signed,
    load_result,
    pack,
    sign,
    to_json,
    wrap_yaw,
)

from .deskew import deskew_sweep


def as_pose(pose: Any) -> Pose | None:
    """A Pose, a 4x4 T_world_sensor, a dict, or (x, y, z, roll, pitch, yaw) in metres and radians -> Pose."""
    if pose is None or isinstance(pose, Pose):
        return pose
    if isinstance(pose, dict):
        return Pose(**pose)
    arr = np.asarray(pose, dtype=float)
    if arr.shape == (4, 4):
        return Pose.from_matrix(arr)
    if arr.shape == (6,):
        return Pose(**dict(zip(("x", "y", "z", "roll", "pitch", "yaw"), arr.tolist())))
    raise ValueError(f"pose must be a 4x4 matrix or (x, y, z, roll, pitch, yaw), got shape {arr.shape}")


def make_frame(
    points,
    boxes=None,
    *,
    vehicle_id: str,
    stamp: float,
    seq: int = 0,
    pose: Any = None,
    odometry: Any = None,
    scores=None,
    png_compression: int = 6,
    velocity=None,
    yaw_rate: float = 0.0,
    **bev_options,
) -> Frame:
    """A sweep (N, 3+) in the sensor frame, or a ready BevImage, and its boxes [x, y, z, l, w, h, yaw] -> Frame.
    Any finite yaw is taken (a dataset's [0, 2 pi) or degrees-turned-radians beyond it) and wrapped into
    [-pi, pi); a non-finite box number is a ValueError naming the box and the component.
    ``pose``: the reported (GNSS-grade) T_world_sensor; ``odometry``: the car's odometry pose T_odom_sensor (as
    :func:`as_pose` reads either), which lets the service track the peer through time. ``velocity`` (vx, vy in
    the sensor frame, m/s) and ``yaw_rate`` (rad/s): the car's motion during the sweep; when given, the sweep is
    de-skewed to mid-sweep before it is encoded (:func:`bb_align_client.deskew.deskew_sweep`, firing times from
    the azimuth of a clockwise sweep; call it yourself for per-point times). Leave it out for a sweep the driver
    already de-skewed."""
    if isinstance(points, BevImage):
        if velocity is not None:
            raise ValueError("velocity: a ready BevImage cannot be de-skewed; pass the sweep's points")
        bev, num_points = points, None
    else:
        pts = np.asarray(points)
        if velocity is not None:
            pts = deskew_sweep(pts, velocity, yaw_rate)
        bev, num_points = make_bev(pts, BevConfig(**bev_options)), int(len(pts))
    rows = [[*row[:6], wrap_yaw(row[6])] for row in as_boxes(boxes).tolist()]
    return Frame(
        vehicle_id=vehicle_id,
        seq=seq,
        stamp=float(stamp),
        png=bev.to_png(png_compression),
        bev=BevMeta(**bev.meta()),
        boxes=rows,
        scores=None if scores is None else [float(s) for s in scores],
        pose=as_pose(pose),
        odometry=as_pose(odometry),
        num_points=num_points,
    )


def encode_frame(
    points,
    boxes=None,
    *,
    vehicle_id: str,
    stamp: float,
    seq: int = 0,
    pose: Any = None,
    odometry: Any = None,
    encoding: str = MSGPACK,
    key: bytes | str | Credential | None = None,
    key_id: str = FLEET_KEY_ID,
    **bev_options,
) -> bytes:
    """The bytes a car sends for one sweep: msgpack (default) or JSON (``encoding="application/json"``).
    ``key``: sign the frame: a vehicle Credential (Ed25519, the recommended way), or HMAC-SHA256 with the fleet
    key (``key_id="fleet"``) or the car's own key (``key_id=vehicle_id``). ``bev_options`` are BevConfig fields
    (range_m, resolution_m, ...) plus ``scores``, ``png_compression`` and the
    de-skewing motion ``velocity`` / ``yaw_rate`` (:func:`make_frame`)."""
    frame = make_frame(
        points, boxes, vehicle_id=vehicle_id, stamp=stamp, seq=seq, pose=pose, odometry=odometry, **bev_options
    )
    if encoding == JSON:
        data = to_json(frame)
    elif encoding == MSGPACK:
        data = pack(frame)
    else:
        raise ValueError(f"encoding must be {MSGPACK!r} or {JSON!r}")
    return data if key is None else sign(data, key, key_id, encoding)


def sign_frame(data: bytes, key: bytes | str | Credential, key_id: str = FLEET_KEY_ID) -> bytes:
    """Sign already encoded frame bytes (msgpack or JSON); bytes already signed are returned unchanged."""
    return data if is_signed(data) else sign(data, key, key_id)


def decode_result(data: bytes) -> Result:
    """msgpack (Zenoh, REST with Accept: application/msgpack) or JSON bytes -> Result."""
    return load_result(data)
