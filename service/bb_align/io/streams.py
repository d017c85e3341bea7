"""Two cars' recent frames from their folders, for `bb-align align EGO_DIR PEER_DIR` (Aligner.align_stream).

Each folder holds one car's frames in the sequence layout `bb-align track` reads (``<stamp>.yaml`` beside its
cloud, OpenCOOD's agent folder): every yaml with the car's ``odometry_pose`` (6-vector or 4x4, as ``lidar_pose``)
and optionally ``timestamp_s``. Frames are paired by name; the last ``frames`` pairs are the stream.
"""

from __future__ import annotations

from pathlib import Path

from bb_align.engine.stream_acquire import StreamFrame

from .dataset import AgentFrame, parse_lidar_pose, read_agent_frame
from .defaults import DESKEW_DEFAULT
from .sweeps import deskewed

FRAME_PERIOD_S = 0.1  # stamp step when a yaml has no timestamp_s


def _agent_frames(folder: Path) -> dict[str, AgentFrame]:
    out = {}
    for path in sorted(folder.glob("*.yaml")):
        frame = read_agent_frame(path)
        if "odometry_pose" not in frame.extra:
            raise ValueError(f"{path}: no 'odometry_pose' (a stream needs each car's odometry)")
        out[path.stem] = frame
    if not out:
        raise ValueError(f"{folder}: no <stamp>.yaml frames (the sequence layout of `bb-align track`)")
    return out


def stream_frames(
    aligner, ego_dir: Path, peer_dir: Path, frames: int, deskew: bool = DESKEW_DEFAULT
) -> tuple[list[StreamFrame], AgentFrame, AgentFrame]:
    """The last ``frames`` frame pairs of the two folders, prepared, with their odometry and stamps; and the last
    pair's two agent frames (for their reference poses)."""
    ego, peer = _agent_frames(Path(ego_dir)), _agent_frames(Path(peer_dir))
    names = sorted(set(ego) & set(peer))[-frames:]
    if not names:
        raise ValueError(f"{peer_dir}: no frame shares its name with a frame of {ego_dir}")
    out = []
    for k, name in enumerate(names):
        prepared = []
        for agent in (ego[name], peer[name]):
            pts, boxes = agent.load_points(), agent.detections
            if deskew:  # as a sender with odometry does
                pts, boxes = deskewed(agent, pts, boxes)
            prepared.append(aligner.prepare(pts, boxes))
        stamp = float(peer[name].extra.get("timestamp_s", k * FRAME_PERIOD_S))
        O_ego, O_peer = (parse_lidar_pose(a.extra["odometry_pose"]) for a in (ego[name], peer[name]))
        out.append(StreamFrame(prepared[0], prepared[1], O_ego, O_peer, stamp))
    return out, ego[names[-1]], peer[names[-1]]
