"""ROS 2 bags in: a rosbag2 recording (a bag directory with MCAP or sqlite3 storage, or a bare ``.mcap`` / ``.db3``
file) of two cars, read with ``rosbags`` (pure Python, no ROS runtime) into the frames the yaml layout gives.

Per car (topics named by :class:`BagTopics`; the defaults are ``/ego/...`` and ``/peer/...``):

- ``sensor_msgs/PointCloud2``: the LiDAR sweep (fields ``x``, ``y``, ``z``, optional ``intensity``; any numeric
  types, either byte order, padded rows), in the cloud's own frame (x forward, y left, z up);
- ``nav_msgs/Odometry`` (optional): the car's odometry, ``odometry_pose``;
- a GNSS pose (optional): ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped`` or ``Odometry`` in a shared
  map frame, or a ``sensor_msgs/NavSatFix`` with a heading (``sensor_msgs/Imu`` or ``QuaternionStamped``, in
  east-north-up), placed in metres east, north and up of the bag's first fix: ``gnss_pose`` (the acquisitions'
  prior);
- a reference pose (optional, same types): the truth, when the recording has one (an RTK/INS solution), used
  only to score the answers.

Every pose is taken as the pose of the car's LiDAR unless ``*_base_to_lidar`` gives the LiDAR's mount on the
car (4x4 ``T_base_lidar``: pose of the LiDAR = pose of the car @ T_base_lidar). Each peer sweep is one frame:
the ego sweep nearest in header time (within ``max_skew_s``), and each car's poses nearest its own sweep (within
``max_skew_s``; a frame lacking one has none, as a yaml without the key). A frame's time is the peer sweep's
header stamp, in seconds.

    run = read_bag("drive.mcap", BagTopics(peer_points="/car2/points"))
    for group in run.groups():  # each sweep read from the bag when its frame is reached
        group.ego.load_points()  # (N, 4) float32 x, y, z, intensity
"""

from __future__ import annotations

import bisect
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from .dataset import AgentFrame, FrameGroup
from .errors import InputFileError
from .navsat import enu

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
HEADING_TYPES = ("sensor_msgs/msg/Imu", "geometry_msgs/msg/QuaternionStamped")
KINDS = ("points", "odometry", "gnss", "heading", "reference")
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"
# sensor_msgs/PointField datatypes -> numpy
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
CARS = ("ego", "peer")


class BagTopics(BaseModel):
    """Which topic holds what. A topic left at its default may be missing from the bag (the frames then have no
    such pose); a topic named explicitly must be there."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    ego_points: str = Field("/ego/points", description="the ego's sensor_msgs/PointCloud2")
    peer_points: str = Field("/peer/points", description="the peer's sensor_msgs/PointCloud2")
    ego_odometry: str | None = Field("/ego/odom", description="the ego's nav_msgs/Odometry (None: not used)")
    peer_odometry: str | None = Field("/peer/odom", description="the peer's nav_msgs/Odometry")
    ego_gnss: str | None = Field(
        "/ego/gnss_pose",
        description="the ego's GNSS pose (PoseStamped, PoseWithCovarianceStamped, Odometry) or fix "
        "(NavSatFix, with a heading topic)",
    )
    peer_gnss: str | None = Field("/peer/gnss_pose", description="the peer's GNSS pose or fix")
    ego_heading: str | None = Field(
        "/ego/heading", description="with a NavSatFix: the ego's orientation in east-north-up (Imu, QuaternionStamped)"
    )
    peer_heading: str | None = Field("/peer/heading", description="with a NavSatFix: the peer's orientation")
    ego_reference: str | None = Field("/ego/reference", description="the ego's true pose, to score answers only")
    peer_reference: str | None = Field("/peer/reference", description="the peer's true pose")
    ego_base_to_lidar: list[list[float]] | None = Field(None, description="4x4 T_base_lidar of the ego's LiDAR")
    peer_base_to_lidar: list[list[float]] | None = Field(None, description="4x4 T_base_lidar of the peer's LiDAR")
    max_skew_s: float = Field(0.05, gt=0, le=1.0, description="largest time between a peer sweep and what it pairs")

    @field_validator("ego_base_to_lidar", "peer_base_to_lidar")
    @classmethod
    def _rigid(cls, v):
        if v is not None:
            T = np.asarray(v, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[3], (0, 0, 0, 1)):
                raise ValueError("must be a finite 4x4 matrix with last row [0, 0, 0, 1]")
            if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
                raise ValueError("its 3x3 part must be a rotation")
        return v

    def topic(self, car: str, kind: str) -> str | None:
        return getattr(self, f"{car}_{kind}")

    def required(self, car: str, kind: str) -> bool:
        return kind == "points" or f"{car}_{kind}" in self.model_fields_set


def is_bag(path: str | Path) -> bool:
    """Whether ``path`` is a rosbag2 (by its contents): a directory with a rosbag2 ``metadata.yaml``, or an MCAP
    or sqlite3 storage file."""
    path = Path(path)
    if path.is_dir():
        meta = path / "metadata.yaml"
        return meta.is_file() and "rosbag2_bagfile_information" in meta.read_text(errors="replace")[:4096]
    if path.is_file():
        with open(path, "rb") as fh:
            head = fh.read(16)
        return head.startswith(_MCAP_MAGIC) or head.startswith(_SQLITE_MAGIC)
    return False


def cloud_points(msg) -> np.ndarray:
    """A sensor_msgs/PointCloud2 -> (N, 4) float32 x, y, z, intensity (0 when the cloud has none), finite points
    only."""
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in ("x", "y", "z") if n not in fields]
    if missing:
        raise ValueError(f"PointCloud2 has no field {', '.join(missing)} (fields: {', '.join(fields) or 'none'})")
    names = [n for n in ("x", "y", "z", "intensity") if n in fields]
    order = ">" if msg.is_bigendian else "<"
    for n in names:
        if fields[n].datatype not in _FIELD_TYPES:
            raise ValueError(f"PointCloud2 field {n} has unknown datatype {fields[n].datatype}")
    dtype = np.dtype(
        {
            "names": names,
            "formats": [order + _FIELD_TYPES[fields[n].datatype] for n in names],
            "offsets": [fields[n].offset for n in names],
            "itemsize": msg.point_step,
        }
    )
    n_pts = int(msg.width) * int(msg.height)
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.point_step <= 0 or msg.row_step < msg.width * msg.point_step or len(data) < msg.row_step * msg.height:
        raise ValueError(
            f"PointCloud2 of {msg.height} x {msg.width} points, point_step {msg.point_step}, row_step "
            f"{msg.row_step} needs {msg.row_step * msg.height} bytes, has {len(data)}"
        )
    rows = data[: msg.row_step * msg.height].reshape(msg.height, msg.row_step)[:, : msg.width * msg.point_step]
    rec = np.ascontiguousarray(rows).reshape(-1).view(dtype)[:n_pts]
    out = np.zeros((n_pts, 4), dtype=np.float32)
    for i, n in enumerate(names):
        out[:, i] = rec[n]
    return out[np.all(np.isfinite(out[:, :3]), axis=1)]


def pose_matrix(msg) -> np.ndarray:
    """Odometry, PoseStamped or PoseWithCovarianceStamped -> 4x4 (the pose's frame in the header's frame)."""
    p = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    t = np.array([p.position.x, p.position.y, p.position.z], dtype=float)
    if not np.all(np.isfinite(t)):
        raise ValueError("pose position is not finite")
    T = _rotation(p.orientation)
    T[:3, 3] = t
    return T


def _rotation(quaternion) -> np.ndarray:
    """A geometry_msgs/Quaternion -> 4x4 with that rotation."""
    q = np.array([quaternion.x, quaternion.y, quaternion.z, quaternion.w], dtype=float)
    norm = np.linalg.norm(q)
    if not (np.all(np.isfinite(q)) and abs(norm - 1.0) < 1e-3):
        raise ValueError(f"orientation is not a finite unit quaternion (|q| = {norm:.4g})")
    x, y, z, w = q / norm
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return T


def _stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _nearest(stamps: list[float], t: float, max_skew_s: float) -> int | None:
    i = bisect.bisect_left(stamps, t)
    best = min((j for j in (i - 1, i) if 0 <= j < len(stamps)), key=lambda j: abs(stamps[j] - t), default=None)
    return best if best is not None and abs(stamps[best] - t) <= max_skew_s else None


def _check_topics(path: Path, reader, topics: BagTopics) -> dict[tuple[str, str], object]:
    """Each wanted topic's connection, its type checked; a problem names the topic and what the bag has."""
    have = {c.topic: c for c in reader.connections}
    listing = ", ".join(f"{t} ({c.msgtype})" for t, c in sorted(have.items())) or "no topics"
    wanted: dict[tuple[str, str], object] = {}
    for car in CARS:
        for kind in KINDS:
            name = topics.topic(car, kind)
            if name is None:
                continue
            if name not in have:
                if topics.required(car, kind):
                    raise InputFileError(f"{path}: no topic {name} ({car} {kind}); the bag has {listing}")
                continue
            allowed = {
                "points": (POINTCLOUD2,),
                "odometry": ("nav_msgs/msg/Odometry",),
                "gnss": (*POSE_TYPES, NAVSATFIX),
                "heading": HEADING_TYPES,
            }.get(kind, POSE_TYPES)
            if have[name].msgtype not in allowed:
                raise InputFileError(f"{path}: topic {name} is {have[name].msgtype}, not {' or '.join(allowed)}")
            wanted[(car, kind)] = have[name]
    return wanted


@dataclass
class _Topic:
    """One wanted topic's messages, in header-time order: stamps, each message's place in the bag, and for the
    poses their values (clouds are read again when their frame is replayed, so a long drive is not held whole)."""

    stamps: list[float]
    order: list[int]  # log-order ordinal of each message
    values: list


@dataclass
class BagRun:
    """One two-car recording as the tracker replays it. ``groups()`` gives its frames in time order, ego first in
    each, reading each sweep from the bag as it is reached."""

    path: Path
    topics: BagTopics
    frame_ids: dict[str, str]  # car -> the frame id of its clouds (what the answers are expressed between)
    pairs: list[tuple[int, int]]  # (ego, peer) sweep, as indices into the two cloud topics' header-time order
    skipped: int  # peer sweeps with no ego sweep within max_skew_s
    _index: dict[tuple[str, str], _Topic]

    @property
    def name(self) -> str:
        return self.path.name

    def __len__(self) -> int:
        return len(self.pairs)

    def _pose(self, car: str, kind: str, t: float) -> np.ndarray | None:
        topic = self._index.get((car, kind))
        i = None if topic is None else _nearest(topic.stamps, t, self.topics.max_skew_s)
        mount = getattr(self.topics, f"{car}_base_to_lidar")
        return None if i is None else topic.values[i] @ (np.eye(4) if mount is None else np.asarray(mount, float))

    def _agent(self, car: str, i: int, t_frame: float, points: np.ndarray) -> AgentFrame:
        t = self._index[(car, "points")].stamps[i]
        extra: dict = {"timestamp_s": t_frame, "frame_id": self.frame_ids[car]}
        for kind, yaml_key in (("odometry", "odometry_pose"), ("gnss", "gnss_pose")):
            if (T := self._pose(car, kind, t)) is not None:
                extra[yaml_key] = T
        T_ref = self._pose(car, "reference", t)
        return AgentFrame(self.name, car, f"{t_frame:.6f}", self.path, T_ref, {}, extra=extra, points=points)

    def groups(self) -> Iterator[FrameGroup]:
        """The frames in time order; each sweep decoded from the bag when its frame is reached."""
        clouds = {car: self._index[(car, "points")] for car in CARS}
        # log-order ordinal of every sweep a frame needs -> (car, header-order index)
        need = Counter((car, clouds[car].order[i]) for pair in self.pairs for car, i in zip(CARS, pair))
        have: dict[tuple[str, int], np.ndarray] = {}
        sweeps = _messages(self.path, self.topics, kinds=("points",))
        for e, p in self.pairs:
            keys = [(car, clouds[car].order[i]) for car, i in zip(CARS, (e, p))]
            while not all(k in have for k in keys):
                (car, _kind), ordinal, _t, value = next(sweeps)
                if (car, ordinal) in need:
                    have[(car, ordinal)] = value
            t_frame = clouds["peer"].stamps[p]
            agents = {car: self._agent(car, i, t_frame, have[k]) for car, i, k in zip(CARS, (e, p), keys)}
            yield FrameGroup(self.name, f"{t_frame:.6f}", agents)
            for k in keys:  # kept while another frame needs it (an ego sweep paired with two peer sweeps)
                need[k] -= 1
                if need[k] == 0:
                    del have[k]


def _value(key: tuple[str, str], msg, keep_points: bool):
    """What a message gives: the points (or, not kept, the cloud's frame id), a 4x4 pose, a heading's rotation as
    a 4x4, or a fix as (lat, lon, alt) (None: no fix)."""
    if key[1] == "points":
        return cloud_points(msg) if keep_points else (msg.header.frame_id or key[0])
    if msg.__msgtype__ == NAVSATFIX:
        fix = np.array([msg.latitude, msg.longitude, msg.altitude], dtype=float)
        return fix if msg.status.status >= 0 and np.all(np.isfinite(fix)) else None
    if msg.__msgtype__ in HEADING_TYPES:
        q = msg.orientation if hasattr(msg, "orientation") else msg.quaternion
        return _rotation(q)
    return pose_matrix(msg)


def _messages(path: Path, topics: BagTopics, kinds=KINDS, keep_points=True):
    """(car, kind), ordinal on its topic, header stamp, value (the points or the 4x4 pose) of every wanted
    message in the bag's order. InputFileError for an unreadable bag, a missing or mistyped topic, a bad message."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    # The types read are standard messages, the same in every ROS 2 distribution: the latest definitions decode them.
    typestore = get_typestore(Stores.LATEST)
    try:
        reader = Reader(path)
        reader.open()
    except Exception as e:  # rosbags raises several types for a file that is not a bag
        raise InputFileError(f"{path}: not a readable rosbag2 ({e})") from None
    try:
        wanted = {k: c for k, c in _check_topics(path, reader, topics).items() if k[1] in kinds}
        by_conn = {id(c): key for key, c in wanted.items()}
        counts = dict.fromkeys(wanted, 0)
        for conn, _t, raw in reader.messages(connections=list(wanted.values())):
            key = by_conn[id(conn)]
            try:
                msg = typestore.deserialize_cdr(raw, conn.msgtype)
                value = _value(key, msg, keep_points)
            except Exception as e:
                raise InputFileError(f"{path}: topic {conn.topic}: message {counts[key]}: {e}") from None
            yield key, counts[key], _stamp(msg), value
            counts[key] += 1
    finally:
        reader.close()


def _index(path: Path, topics: BagTopics) -> tuple[dict[tuple[str, str], _Topic], dict[str, str]]:
    """Every wanted topic's stamps in header-time order, and the poses (one pass; the clouds are not kept)."""
    raw: dict[tuple[str, str], list] = {}
    frame_ids: dict[str, str] = {}
    for key, ordinal, t, value in _messages(path, topics, keep_points=False):
        if key[1] == "points":
            frame_ids.setdefault(key[0], value)
        if value is not None:  # a fix without a fix
            raw.setdefault(key, []).append((t, ordinal, value))
    for car in CARS:
        if (car, "points") not in raw:
            raise InputFileError(f"{path}: topic {topics.topic(car, 'points')} holds no messages")
    index = {}
    for key, rows in raw.items():  # in header-time order (a recorder writes in arrival order)
        rows.sort(key=lambda r: (r[0], r[1]))
        index[key] = _Topic([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows])
    if frame_ids["ego"] == frame_ids["peer"]:  # both clouds in e.g. 'velodyne': name the cars apart
        frame_ids = {car: f"{car}/{fid}" for car, fid in frame_ids.items()}
    _fixes_as_poses(path, topics, index)
    return index, frame_ids


def _fixes_as_poses(path: Path, topics: BagTopics, index: dict[tuple[str, str], _Topic]) -> None:
    """NavSatFix topics -> GNSS poses in one east-north-up frame (origin: the first fix, the ego's when it has
    one), oriented by the car's heading nearest each fix (within max_skew_s; a fix without one is dropped)."""
    fixes = [(car, index[(car, "gnss")]) for car in CARS if (car, "gnss") in index]
    fixes = [(car, topic) for car, topic in fixes if topic.values and np.asarray(topic.values[0]).shape == (3,)]
    if not fixes:
        return
    origin = fixes[0][1].values[0]
    for car, topic in fixes:
        heading = index.get((car, "heading"))
        if heading is None:
            raise InputFileError(
                f"{path}: topic {topics.topic(car, 'gnss')} is a NavSatFix: it needs the car's heading too "
                f"(--topic {car}_heading=TOPIC, sensor_msgs/Imu or geometry_msgs/QuaternionStamped)"
            )
        rows = []
        for t, ordinal, fix in zip(topic.stamps, topic.order, topic.values):
            j = _nearest(heading.stamps, t, topics.max_skew_s)
            if j is not None:
                T = heading.values[j].copy()
                T[:3, 3] = enu(fix, origin)
                rows.append((t, ordinal, T))
        index[(car, "gnss")] = _Topic([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows])


def read_bag(path: str | Path, topics: BagTopics | None = None, max_frames: int | None = None) -> BagRun:
    """A rosbag2 recording of two cars (module doc), indexed: each peer sweep paired with the ego sweep nearest in
    header time. Raises InputFileError (one line, naming the bag and the topic) for an unreadable bag, a missing or
    mistyped topic or a message that does not decode."""
    path, topics = Path(path), topics or BagTopics()
    index, frame_ids = _index(path, topics)
    ego, peer = index[("ego", "points")], index[("peer", "points")]
    pairs, skipped = [], 0
    for k, t_peer in enumerate(peer.stamps):
        j = _nearest(ego.stamps, t_peer, topics.max_skew_s)
        if j is None:
            skipped += 1
        elif max_frames is None or len(pairs) < max_frames:
            pairs.append((j, k))
    if not pairs:
        raise InputFileError(
            f"{path}: no peer sweep has an ego sweep within {topics.max_skew_s} s (max_skew_s) of its header stamp"
        )
    return BagRun(path, topics, frame_ids, pairs, skipped, index)
