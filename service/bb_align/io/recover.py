"""Recover every non-ego agent's pose of an OPV2V / V2V4Real dataset with the engine, and write a corrected copy.

For each (scenario, timestamp) the ego (lowest agent id) is prepared once; every other agent is aligned against
it (optionally gated by its reported pose: ``use_prior``). The copy under OUT is the dataset with, for each
non-ego agent whose alignment succeeded, ``lidar_pose`` replaced by

    T_world_peer = T_world_ego(reported) @ T_ego_peer(recovered)

written in the format it was read in (6-vector in degrees, or 4x4 nested or flat). x, y and yaw come from the
recovery; z, roll and pitch from the reported pose (the engine recovers the ground-plane part). A failed
alignment keeps the reported pose. Every other file is copied unchanged (point clouds and images hard-linked
when OUT is on the same file system). ``OUT/recovered_poses.jsonl`` has one row per frame and non-ego agent
(fields: :data:`ROW_FIELDS`); ``OUT/recover_summary.json`` the totals.

Resumable and never half-written: each file is written to a temporary name and renamed; a frame counts as done
when its rows are in the jsonl (written in one append after the frame's yaml files); a rerun with the same
ROOT, OUT and settings continues after the last finished frame. ROOT is only read.

A DAIR-V2X-C root (``bb_align.io.dair``) is recovered the same way by :func:`recover_dair_dataset`: the vehicle
is the ego, the roadside unit the peer, and the file rewritten is ``cooperative/calib/lidar_i2v/<veh id>.json``
(x, y and yaw recovered; z, roll and pitch kept from the file; its other keys kept).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field
from tqdm import tqdm

from bb_align.engine.boxes import as_boxes
from bb_align.engine.config import AlignConfig
from bb_align.engine.follow import Follower
from bb_align.engine.geometry import wrap_angle
from bb_align.engine.pipeline import Aligner
from bb_align.engine.result import AlignResult

from .dataset import AgentFrame, FrameGroup, iter_frames, parse_lidar_pose, world_to_x_pose, x_to_world
from .defaults import DESKEW_DEFAULT, DESKEW_HELP
from .detections import DetectionDir, boxes_from_array
from .sweeps import deskewed

JSONL_NAME = "recovered_poses.jsonl"
SUMMARY_NAME = "recover_summary.json"
RUN_NAME = ".bb_align_recover.json"  # the settings of the run that writes OUT (checked when resuming)
_TMP_PREFIX = ".bbrec-tmp-"
_COPIED_SUFFIXES = {".yaml", ".yml", ".json", ".txt"}  # small text files are copied, never hard-linked

ROW_FIELDS = (
    "scenario",  # scenario folder, with the split folder when there is one ("test/2021_08_18_19_48_05")
    "timestamp",
    "ego",  # ego agent id (lowest id of the frame)
    "agent",  # this non-ego agent's id
    "success",  # the engine's verdict; False: the written lidar_pose is the reported one
    "reason",  # why not (None on success)
    "pose_written",  # "recovered" or "reported"
    "T_ego_peer",  # 4x4, the engine's answer (best found, also on failure): p_ego = T_ego_peer @ p_peer
    "T_ego_peer_reported",  # 4x4 from the reported poses (the prior, when --prior)
    "yaw_deg",
    "tx",
    "ty",
    "confidence",
    "inliers_bv",
    "inliers_box",
    "covariance",  # the engine's pose covariance when it reports one, else None
    "boxes_ego",  # detections used (None: none available, stage 2 skipped)
    "boxes_peer",
)


class RecoverConfig(BaseModel):
    """Settings of a recovery run (every number of the engine is in ``align``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    align: AlignConfig = AlignConfig()
    use_prior: bool = Field(False, description="gate the engine's matches by the reported pose (T_prior)")
    pose_noise_t_m: float = Field(
        0.0, ge=0, description="demo: Gaussian noise (sigma, m) added to each non-ego x and y before recovery"
    )
    pose_noise_deg: float = Field(0.0, ge=0, description="demo: Gaussian noise (sigma, deg) on each non-ego yaw")
    seed: int = Field(0, description="seed of the demo pose noise")
    link: bool = Field(True, description="hard-link unchanged binary files (clouds, images) when possible")
    track: bool = Field(
        False,
        description="follow each peer through its scenario's frames (bb_align.engine.follow: acquire once, then "
        "refine from the prediction, constant-velocity model) instead of solving every frame alone; a resumed run "
        "starts its tracks afresh at the resume point",
    )
    frame_period_s: float = Field(
        0.1, gt=0, description="with track: the time of frame k when a yaml has no timestamp_s"
    )
    deskew: bool = Field(DESKEW_DEFAULT, description=DESKEW_HELP)


# ---- detections ----------------------------------------------------------------------------------------------


class DetectionSource(Protocol):
    """Where an agent frame's boxes come from. ``name`` is recorded in the summary."""

    name: str

    def __call__(self, agent: AgentFrame, points: np.ndarray) -> np.ndarray | None: ...


class YamlDetections:
    """The yaml's ``detections`` key (None when absent: stage 2 is skipped)."""

    name = "yaml"

    def __call__(self, agent: AgentFrame, points: np.ndarray) -> np.ndarray | None:
        return agent.detections


class FolderDetections:
    """Per-frame files under a folder (format: :mod:`bb_align.io.detections`)."""

    def __init__(self, root: str | Path):
        self.folder = DetectionDir(root)
        self.name = f"folder:{self.folder.root}"

    def __call__(self, agent: AgentFrame, points: np.ndarray) -> np.ndarray | None:
        return self.folder.load(agent.scenario, agent.agent, agent.timestamp)


class NoDetections:
    name = "none"

    def __call__(self, agent: AgentFrame, points: np.ndarray) -> np.ndarray | None:
        return None


# ---- poses ---------------------------------------------------------------------------------------------------


def pose_like(reported_value, T_world_sensor: np.ndarray) -> list:
    """A 4x4 T_world_sensor written the way ``reported_value`` was (6-vector, nested 4x4 or 16 flat numbers)."""
    arr = np.asarray(reported_value, dtype=float)
    if arr.size == 6:
        return [float(v) for v in world_to_x_pose(T_world_sensor)]
    T = np.asarray(T_world_sensor, dtype=float)
    return T.tolist() if arr.ndim == 2 else [float(v) for v in T.reshape(-1)]


def recovered_pose_value(reported_value, T_world_ego: np.ndarray, T_ego_peer: np.ndarray) -> list:
    """The yaml ``lidar_pose`` of a recovered peer: x, y, yaw of T_world_ego @ T_ego_peer, with z, roll and
    pitch of the reported pose, in the reported pose's format. The yaw is kept within 180 deg of the reported
    one (a 6-vector reading 350 stays near 350)."""
    T_world_peer = np.asarray(T_world_ego, dtype=float) @ np.asarray(T_ego_peer, dtype=float)
    x_rep = world_to_x_pose(parse_lidar_pose(reported_value))
    if np.asarray(reported_value).size == 6:
        x_rep[4] = float(np.asarray(reported_value, dtype=float).reshape(-1)[4])  # the yaw as written (e.g. 350)
    yaw = math.degrees(math.atan2(T_world_peer[1, 0], T_world_peer[0, 0]))
    yaw = x_rep[4] + math.degrees(float(wrap_angle(math.radians(yaw - x_rep[4]))))
    x_new = [float(T_world_peer[0, 3]), float(T_world_peer[1, 3]), x_rep[2], x_rep[3], yaw, x_rep[5]]
    if np.asarray(reported_value).size == 6:
        return x_new
    return pose_like(reported_value, x_to_world(x_new))


def noisy_pose_value(value, rng: np.random.Generator, sigma_t_m: float, sigma_deg: float) -> list:
    """OpenCOOD-style localisation noise (Gaussian on x, y and yaw), in the value's own format."""
    x = world_to_x_pose(parse_lidar_pose(value))
    x[0] += rng.normal(0, sigma_t_m)
    x[1] += rng.normal(0, sigma_t_m)
    x[4] += rng.normal(0, sigma_deg)
    return x if np.asarray(value).size == 6 else pose_like(value, x_to_world(x))


# ---- one frame -----------------------------------------------------------------------------------------------


@dataclass
class PeerInput:
    agent: str
    points: np.ndarray
    boxes: np.ndarray | None
    pose_value: object  # the reported lidar_pose as read (6-vector or 4x4)


@dataclass
class PeerRecovery:
    agent: str
    result: AlignResult
    T_ego_peer_reported: np.ndarray
    pose_value: object  # what to write: the recovered pose on success, the reported value otherwise
    boxes_peer: int | None


def recover_peers(
    aligner: Aligner,
    ego_points: np.ndarray,
    ego_boxes: np.ndarray | None,
    ego_pose_value,
    peers: Iterable[PeerInput],
    use_prior: bool = False,
    followers: Callable[[str], Follower] | None = None,
    stamp: float = 0.0,
) -> list[PeerRecovery]:
    """Align every peer against the ego (prepared once); the poses to write, and the evidence. ``followers``
    (peer id -> that peer's Follower): track each peer at ``stamp`` instead of aligning the frame alone (the
    reported pose then checks the acquisitions)."""
    T_world_ego = parse_lidar_pose(ego_pose_value)
    ego = aligner.prepare(ego_points, ego_boxes, features=followers is None)
    out = []
    for p in peers:
        T_rep = np.linalg.inv(T_world_ego) @ parse_lidar_pose(p.pose_value)
        if followers is not None:
            peer = aligner.prepare(p.points, p.boxes, features=False)
            res = followers(p.agent).step(ego, peer, stamp, T_prior=T_rep if use_prior else None)
        else:
            res = aligner.align(ego, aligner.prepare(p.points, p.boxes), T_prior=T_rep if use_prior else None)
        value = recovered_pose_value(p.pose_value, T_world_ego, res.T_ego_peer) if res.success else p.pose_value
        out.append(PeerRecovery(p.agent, res, T_rep, value, None if p.boxes is None else len(p.boxes)))
    return out


def _row(scenario: str, timestamp: str, ego: str, boxes_ego: int | None, r: PeerRecovery) -> dict:
    res = r.result
    d = res.to_dict()
    return {
        "scenario": scenario,
        "timestamp": timestamp,
        "ego": ego,
        "agent": r.agent,
        "success": d["success"],
        "reason": d["reason"],
        "pose_written": "recovered" if res.success else "reported",
        "T_ego_peer": d["T_ego_peer"],
        "T_ego_peer_reported": np.asarray(r.T_ego_peer_reported, dtype=float).tolist(),
        **{k: d[k] for k in ("yaw_deg", "tx", "ty", "confidence", "inliers_bv", "inliers_box", "covariance")},
        "source": d["source"],
        "track_state": d["track_state"],
        "boxes_ego": boxes_ego,
        "boxes_peer": r.boxes_peer,
    }


def recover_frame(frame: dict, aligner: Aligner, *, use_prior: bool = False, ego_id=None) -> dict:
    """Recover the non-ego agents' poses of one OpenCOOD-style frame dict (e.g. inside a dataset class's
    ``retrieve_base_data``, before the poses are used).

    ``frame``: ``{agent_id: {"lidar_np": (N, 3+) points in the agent's sensor frame (or "points"),
    "params": {"lidar_pose": [x, y, z, roll, yaw, pitch] (degrees) or a 4x4 T_world_sensor, ...},
    "detections": optional (K, 7) [x, y, z, l, w, h, yaw] or (K, 8, 3) corners in the sensor frame (also read
    from params["detections"]), "ego": optional bool}}``. The ego is the agent with ``"ego": True``, else
    ``ego_id``, else the lowest id.

    Returns a new dict of the same shape (arrays shared, ``params`` copied): each non-ego agent whose alignment
    succeeded has ``params["lidar_pose"]`` replaced by the recovered pose in the same format (see
    :func:`recovered_pose_value`); failed ones keep theirs. Every non-ego agent also gets ``"bb_align"``: the
    jsonl row of :data:`ROW_FIELDS` (success, reason, T_ego_peer, confidence, inliers, ...).
    """
    ego_key = _ego_key(frame, ego_id)
    ego_pts, ego_boxes, ego_pose = _unpack_agent(frame, ego_key)
    peers = [a for a in frame if a != ego_key]
    recs = recover_peers(
        aligner,
        ego_pts,
        ego_boxes,
        ego_pose,
        [PeerInput(str(a), *_unpack_agent(frame, a)) for a in peers],
        use_prior=use_prior,
    )
    out = {a: dict(v) for a, v in frame.items()}
    for a, r in zip(peers, recs):
        out[a]["params"] = {**frame[a]["params"], "lidar_pose": r.pose_value}
        out[a]["bb_align"] = _row("", "", str(ego_key), None if ego_boxes is None else len(ego_boxes), r)
    return out


def _ego_key(frame: dict, ego_id=None):
    """recover_frame's ego: the agent flagged ``"ego": True``, else ``ego_id``, else the lowest id."""
    from .dataset import agent_order

    if not isinstance(frame, dict) or len(frame) < 1:
        raise ValueError("frame must be a dict {agent_id: {'lidar_np': points, 'params': {'lidar_pose': ...}}}")
    flagged = [a for a, v in frame.items() if isinstance(v, dict) and v.get("ego")]
    ego_key = flagged[0] if flagged else (ego_id if ego_id is not None else None)
    if ego_key is None:
        by_text = {str(a): a for a in frame}
        ego_key = by_text[agent_order(by_text)[0]]
    if ego_key not in frame:
        raise ValueError(f"ego id {ego_key!r} is not in the frame (agents: {list(frame)})")
    return ego_key


def _unpack_agent(frame: dict, agent_id) -> tuple[np.ndarray, np.ndarray | None, object]:
    """One agent of recover_frame's dict, checked: (points, boxes or None, its lidar_pose value)."""
    entry = frame[agent_id]
    where = f"frame[{agent_id!r}]"
    if not isinstance(entry, dict) or not isinstance(entry.get("params"), dict):
        raise ValueError(f"{where} needs a 'params' dict")
    if "lidar_pose" not in entry["params"]:
        raise ValueError(f"{where}['params'] needs 'lidar_pose'")
    pts = entry.get("lidar_np", entry.get("points"))
    if pts is None:
        raise ValueError(f"{where} needs 'lidar_np' (or 'points'): (N, 3+) points in its sensor frame")
    pts = np.asarray(pts, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"{where}['lidar_np'] must be (N, 3+), got {pts.shape}")
    dets = entry.get("detections", entry["params"].get("detections"))
    boxes = None if dets is None else boxes_from_array(dets, f"{where} detections")
    try:
        parse_lidar_pose(entry["params"]["lidar_pose"])
    except ValueError as exc:
        raise ValueError(f"{where}['params']['lidar_pose']: {exc}") from exc
    return pts, boxes, entry["params"]["lidar_pose"]


# ---- files ---------------------------------------------------------------------------------------------------


def _tmp(dest: Path) -> Path:
    return dest.with_name(f"{_TMP_PREFIX}{os.getpid()}-{dest.name}")


def _atomic_text(dest: Path, text: str) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp(dest)
    with open(tmp, "w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, dest)


def _atomic_copy(src: Path, dest: Path, link: bool) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp(dest)
    tmp.unlink(missing_ok=True)
    if link and src.suffix.lower() not in _COPIED_SUFFIXES:
        try:
            os.link(src, tmp)
        except OSError:  # another file system, or links not allowed: copy
            shutil.copy2(src, tmp)
    else:
        shutil.copy2(src, tmp)
    os.replace(tmp, dest)


def _check_paths(root: Path, out: Path) -> tuple[Path, Path]:
    root, out = Path(root).resolve(), Path(out).resolve()
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root {root} is not a directory")
    if out == root or out.is_relative_to(root):
        raise ValueError(f"OUT {out} must not be ROOT or inside it (ROOT is never modified)")
    if root.is_relative_to(out):
        raise ValueError(f"OUT {out} must not contain ROOT {root}")
    _no_link_out_of(root)
    return root, out


def _no_link_out_of(root: Path) -> None:
    """Refuse (ValueError) a symbolic link under ROOT that leads outside it: nothing outside ROOT is read, or
    copied into OUT, through one. Links that stay inside ROOT are fine."""
    for dirpath, dirs, files in os.walk(root):  # does not descend into linked folders; they are checked here
        for name in (*dirs, *files):
            path = Path(dirpath) / name
            if path.is_symlink() and not path.resolve().is_relative_to(root):
                raise ValueError(
                    f"{path}: a symbolic link out of the dataset root (to {path.resolve()}); recover reads only "
                    "inside ROOT (give the linked folder's real path as ROOT, or copy it in)"
                )


def _out_path(out: Path, root: Path, src: Path) -> Path:
    """Where ``src`` (a file of ROOT) goes in OUT; refused (ValueError) if that is not inside OUT."""
    src = Path(os.path.normpath(src))
    dest = out / src.relative_to(root) if src.is_relative_to(root) else src
    if not dest.is_relative_to(out) or not dest.resolve().is_relative_to(out):
        raise ValueError(f"{src}: would be written to {dest}, outside OUT {out}")
    return dest


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def _start_run(root: Path, out: Path, settings: dict) -> None:
    """Create OUT, or check that it holds an earlier run of the same ROOT and settings."""
    marker = out / RUN_NAME
    if marker.is_file():
        before = json.loads(marker.read_text())
        if before != settings:
            flat_before, flat_now = _flat(before), _flat(settings)
            changed = sorted(k for k in set(flat_before) | set(flat_now) if flat_before.get(k) != flat_now.get(k))
            raise ValueError(f"OUT {out} holds a run with other settings ({', '.join(changed)}); use another OUT")
    elif out.exists() and any(out.iterdir()):
        raise ValueError(f"OUT {out} exists, is not empty and is not a bb-align recover output")
    else:
        _atomic_text(marker, json.dumps(settings, indent=1, sort_keys=True))
    for dirpath, _, files in os.walk(out):  # temporaries of an interrupted run
        for f in files:
            if f.startswith(_TMP_PREFIX):
                os.unlink(os.path.join(dirpath, f))


def _read_rows(path: Path) -> list[dict]:
    """The finished rows of the jsonl; a torn last line (interrupted append) is dropped."""
    if not path.is_file():
        return []
    rows = []
    text = path.read_text()
    for line in text.split("\n"):
        if not line.strip():
            continue
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return rows


def _mirror(root: Path, out: Path, skip: set[Path], link: bool) -> int:
    """Copy (or hard-link) every file of ROOT into OUT except ``skip``; files already there are kept."""
    n = 0
    for dirpath, dirs, files in os.walk(root):
        dirs.sort()
        for f in sorted(files):
            src = Path(dirpath) / f
            if src in skip:
                continue
            dest = _out_path(out, root, src)
            if dest.is_file() and dest.stat().st_size == src.stat().st_size:
                continue
            _atomic_copy(src, dest, link)
            n += 1
    return n


# ---- the dataset run -----------------------------------------------------------------------------------------


def recover_dataset(
    root: str | Path,
    out: str | Path,
    cfg: RecoverConfig | None = None,
    detections: DetectionSource | None = None,
    *,
    limit: int | None = None,
    progress: bool = True,
    aligner: Aligner | None = None,
    on_frame: Callable[[FrameGroup], None] | None = None,
) -> dict:
    """Recover every frame of ROOT into OUT (see the module docstring); returns the summary.

    ``limit``: stop after this many newly finished frames (the run is then resumable). ``detections``: the
    boxes' source (default: the yaml's ``detections``). ``on_frame`` is called after each finished frame."""
    from .dataset import is_dair_root

    if is_dair_root(root):
        return recover_dair_dataset(
            root, out, cfg, detections, limit=limit, progress=progress, aligner=aligner, on_frame=on_frame
        )
    cfg = cfg or RecoverConfig()
    detections = detections or YamlDetections()
    root, out = _check_paths(Path(root), Path(out))
    groups = list(iter_frames(root))
    if not groups:
        raise ValueError(f"no frame with two or more agents under {root} (scenario folders, or split folders)")
    settings = {"root": str(root), "detections": detections.name, "config": cfg.model_dump(mode="json")}
    _start_run(root, out, settings)

    scen_dirs = {g.scenario: g.ego.pcd_path.parent.parent for g in groups}
    rewritten = {scen_dirs[g.scenario] / p.agent / f"{g.timestamp}.yaml" for g in groups for p in g.peers}
    _mirror(root, out, rewritten, cfg.link)

    jsonl = out / JSONL_NAME
    done = _resume_rows(jsonl, {(g.scenario, g.timestamp): {p.agent for p in g.peers} for g in groups})

    aligner = aligner or Aligner(cfg.align)
    todo = [g for g in groups if (g.scenario, g.timestamp) not in done]
    bar = tqdm(
        total=len(groups), initial=len(groups) - len(todo), desc="recovering", unit="frame", disable=not progress
    )
    finished = 0
    tracks: dict[tuple[str, str], Follower] = {}  # (scenario, peer) -> its track, with cfg.track
    for g in todo:
        if limit is not None and finished >= limit:
            break
        followers = _followers(tracks, g.scenario, aligner) if cfg.track else None
        new_rows = _recover_group(g, out, root, scen_dirs[g.scenario], aligner, cfg, detections, followers)
        _append_rows(jsonl, new_rows)
        finished += 1
        bar.update()
        if on_frame is not None:
            on_frame(g)
    bar.close()
    summary = summarize_rows(_read_rows(jsonl), len(groups), settings)
    if summary["complete"]:
        _atomic_text(out / SUMMARY_NAME, json.dumps(summary, indent=1))
    return summary


def _followers(tracks: dict, scenario: str, aligner: Aligner) -> Callable[[str], Follower]:
    """Peer id -> that peer's Follower in ``scenario`` (kept in ``tracks``); a finished scenario's tracks go."""
    for key in [k for k in tracks if k[0] != scenario]:
        del tracks[key]

    def followers(agent: str) -> Follower:
        return tracks.setdefault((scenario, agent), Follower(aligner))

    return followers


def _append_rows(jsonl: Path, rows: list[dict]) -> None:
    """A frame's done-marker: its rows, in one append, on disk before the next frame starts."""
    with open(jsonl, "a") as fh:
        fh.write("".join(json.dumps(r) + "\n" for r in rows))
        fh.flush()
        os.fsync(fh.fileno())


def _recover_group(
    g: FrameGroup,
    out: Path,
    root: Path,
    scen_dir: Path,
    aligner: Aligner,
    cfg: RecoverConfig,
    detections: DetectionSource,
    followers: Callable[[str], Follower] | None = None,
) -> list[dict]:
    def raw_yaml(agent: AgentFrame) -> dict:
        return yaml.safe_load((scen_dir / agent.agent / f"{g.timestamp}.yaml").read_text())

    def sent(agent: AgentFrame):
        """The agent's cloud and boxes as its car sends them (de-skewed with ``cfg.deskew``, as eval and track)."""
        pts = agent.load_points()
        b = detections(agent, pts)
        b = None if b is None else as_boxes(b)
        return deskewed(agent, pts, b) if cfg.deskew else (pts, b)

    ego = g.ego
    ego_pts, ego_boxes = sent(ego)
    ego_pose = raw_yaml(ego)["lidar_pose"]
    metas, peers = {}, []
    for p in g.peers:
        meta = raw_yaml(p)
        if cfg.pose_noise_t_m > 0 or cfg.pose_noise_deg > 0:
            rng = np.random.default_rng(
                [cfg.seed, *(zlib.crc32(k.encode()) for k in (g.scenario, g.timestamp, p.agent))]
            )
            meta["lidar_pose"] = noisy_pose_value(meta["lidar_pose"], rng, cfg.pose_noise_t_m, cfg.pose_noise_deg)
        metas[p.agent] = meta
        pts, p_boxes = sent(p)
        peers.append(PeerInput(p.agent, pts, p_boxes, meta["lidar_pose"]))
    t = ego.extra.get("timestamp_s")
    stamp = float(t) if t is not None else int(g.timestamp) * cfg.frame_period_s if g.timestamp.isdigit() else 0.0
    recs = recover_peers(
        aligner, ego_pts, ego_boxes, ego_pose, peers, use_prior=cfg.use_prior, followers=followers, stamp=stamp
    )
    rows = []
    for r in recs:
        meta = {**metas[r.agent], "lidar_pose": r.pose_value}
        dest = _out_path(out, root, scen_dir / r.agent / f"{g.timestamp}.yaml")
        _atomic_text(dest, yaml.safe_dump(meta, sort_keys=False, default_flow_style=None))
        rows.append(_row(g.scenario, g.timestamp, ego.agent, None if ego_boxes is None else len(ego_boxes), r))
    return rows


def summarize_rows(rows: list[dict], frames_total: int, settings: dict) -> dict:
    """Totals over the jsonl rows (deterministic: the same for an interrupted-and-resumed run)."""
    reasons: dict[str, int] = {}
    for r in rows:
        reasons[r["reason"] or "success"] = reasons.get(r["reason"] or "success", 0) + 1
    frames_done = len({(r["scenario"], r["timestamp"]) for r in rows})
    n = len(rows)
    return {
        "frames": frames_total,
        "frames_done": frames_done,
        "complete": frames_done == frames_total,
        "agent_frames": n,
        "recovered": sum(1 for r in rows if r["success"]),
        "kept_reported": sum(1 for r in rows if not r["success"]),
        "outcomes": dict(sorted(reasons.items(), key=lambda kv: -kv[1])),
        "detections": settings["detections"],
        "agent_frames_with_boxes": {
            "ego": sum(1 for r in rows if r["boxes_ego"] is not None),
            "peer": sum(1 for r in rows if r["boxes_peer"] is not None),
        },
        "root": settings["root"],
        "config": settings["config"],
    }


# ---- DAIR-V2X-C ----------------------------------------------------------------------------------------------


class LabelDetections(YamlDetections):
    """DAIR-V2X-C: each side's own labels (vehicle classes) as its boxes."""

    name = "labels"


def _resume_rows(jsonl: Path, expected: dict[tuple, set]) -> set:
    """The finished frames of an earlier run: (scenario, timestamp) keys whose rows cover every expected peer.
    The jsonl is trimmed to them (a frame half-appended, or a torn last line, is redone)."""
    rows = _read_rows(jsonl)
    have: dict[tuple, set] = {}
    for r in rows:
        have.setdefault((r["scenario"], r["timestamp"]), set()).add(r["agent"])
    done = {k for k, agents in have.items() if expected.get(k) == agents}
    kept = [r for r in rows if (r["scenario"], r["timestamp"]) in done]
    if len(kept) != len(rows) or (jsonl.is_file() and not jsonl.read_text().endswith("\n") and rows):
        _atomic_text(jsonl, "".join(json.dumps(r) + "\n" for r in kept))
    return done


def _recover_dair_pair(g: FrameGroup, pair, base: Path, root: Path, out: Path, aligner, cfg, detections) -> dict:
    """One cooperative frame: aligned, its recovered lidar_i2v written into OUT; its jsonl row."""
    from .dair import calib_text, read_calib

    ego, peer = g.ego, g.peers[0]
    ego_pts, peer_pts = ego.load_points(), peer.load_points()
    ego_boxes, peer_boxes = detections(ego, ego_pts), detections(peer, peer_pts)
    ego_boxes = None if ego_boxes is None else as_boxes(ego_boxes)
    peer_boxes = None if peer_boxes is None else as_boxes(peer_boxes)
    T_rep = read_calib(pair.lidar_i2v)
    pose_value = T_rep.tolist()
    if cfg.pose_noise_t_m > 0 or cfg.pose_noise_deg > 0:
        rng = np.random.default_rng([cfg.seed, zlib.crc32(pair.vehicle_id.encode())])
        pose_value = noisy_pose_value(pose_value, rng, cfg.pose_noise_t_m, cfg.pose_noise_deg)
    (rec,) = recover_peers(
        aligner,
        ego_pts,
        ego_boxes,
        np.eye(4).tolist(),
        [PeerInput(peer.agent, peer_pts, peer_boxes, pose_value)],
        use_prior=cfg.use_prior,
    )
    template = json.loads(pair.lidar_i2v.read_text())
    dest = _out_path(out, root, pair.lidar_i2v)
    _atomic_text(dest, calib_text(np.asarray(rec.pose_value, dtype=float), template))
    row = _row("", pair.vehicle_id, ego.agent, None if ego_boxes is None else len(ego_boxes), rec)
    row["infrastructure_frame"] = pair.infra_id
    row["lidar_i2v"] = str(pair.lidar_i2v.relative_to(base))
    return row


def recover_dair_dataset(
    root: str | Path,
    out: str | Path,
    cfg: RecoverConfig | None = None,
    detections: DetectionSource | None = None,
    *,
    limit: int | None = None,
    progress: bool = True,
    aligner: Aligner | None = None,
    on_frame: Callable[[FrameGroup], None] | None = None,
) -> dict:
    """Recover every cooperative frame of a DAIR-V2X-C root into OUT: a copy of ROOT whose
    ``cooperative/calib/lidar_i2v/<veh id>.json`` holds the recovered roadside->vehicle transform (failures keep
    the file as it was), plus the jsonl and summary of :func:`recover_dataset`. ``detections`` defaults to the
    labels. Resumable the same way; ``track`` is not supported (cooperative frames are not one sequence)."""
    from .dair import find_dair_root, frame_group, read_pairs

    cfg = cfg or RecoverConfig()
    if cfg.track:
        raise ValueError("track (--track) is not supported on DAIR-V2X-C roots; recover each frame alone")
    if detections is None or (isinstance(detections, YamlDetections) and not isinstance(detections, LabelDetections)):
        detections = LabelDetections()
    root, out = _check_paths(Path(root), Path(out))
    base = find_dair_root(root)
    pairs, skipped = read_pairs(root)
    if not pairs:
        raise ValueError(f"no complete cooperative frame under {base} ({len(skipped)} listed with missing files)")
    settings = {
        "root": str(root),
        "layout": "dair-v2x-c",
        "detections": detections.name,
        "config": cfg.model_dump(mode="json"),
    }
    _start_run(root, out, settings)
    _mirror(root, out, {p.lidar_i2v for p in pairs}, cfg.link)
    jsonl = out / JSONL_NAME
    done = _resume_rows(jsonl, {("", p.vehicle_id): {"infrastructure-side"} for p in pairs})

    aligner = aligner or Aligner(cfg.align)
    todo = [p for p in pairs if ("", p.vehicle_id) not in done]
    bar = tqdm(total=len(pairs), initial=len(pairs) - len(todo), desc="recovering", unit="frame", disable=not progress)
    finished = 0
    for pair in todo:
        if limit is not None and finished >= limit:
            break
        g = frame_group(base, pair)
        _append_rows(jsonl, [_recover_dair_pair(g, pair, base, root, out, aligner, cfg, detections)])
        finished += 1
        bar.update()
        if on_frame is not None:
            on_frame(g)
    bar.close()
    summary = summarize_rows(_read_rows(jsonl), len(pairs), settings)
    summary["layout"] = "dair-v2x-c"
    summary["frames_left_out"] = skipped
    if summary["complete"]:
        _atomic_text(out / SUMMARY_NAME, json.dumps(summary, indent=1))
    return summary
