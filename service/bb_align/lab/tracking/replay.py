"""Replay recorded two-car sequences frame by frame through the engine's follower (the same tracker the service
runs) and compare every answer with the truth.

Each scenario folder is one sequence: the ego is the lowest agent id, the next agent the peer. Per frame: both
clouds become BV images (the senders' work, not timed), the follower steps at the peer's ``timestamp_s`` with the
two cars' ``odometry_pose`` when the yaml has one, and the answer is compared with
``T_ego_peer_true = inv(T_world_ego) @ T_world_peer``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sized
from itertools import islice
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from tqdm import tqdm

from bb_align.engine.config import AlignConfig
from bb_align.engine.follow import Follower
from bb_align.engine.geometry import ground_se2, log_left, pose_error, se2_params, wrap_angle
from bb_align.engine.pipeline import Aligner
from bb_align.io.dataset import FrameGroup, iter_scenario_frames, parse_lidar_pose
from bb_align.io.defaults import DESKEW_DEFAULT, DESKEW_HELP
from bb_align.io.sweeps import deskewed


class ReplayConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    align: AlignConfig = AlignConfig()
    use_odometry: bool = Field(True, description="fuse the yaml's odometry_pose (else: constant-velocity model)")
    use_gnss: bool = Field(
        True, description="the yaml's gnss_pose (reported poses) as the acquisitions' prior, as the service does"
    )
    deskew: bool = Field(DESKEW_DEFAULT, description=DESKEW_HELP)
    frame_period_s: float = Field(0.1, gt=0, description="stamp of frame k when a yaml has no timestamp_s")
    max_frames: int | None = Field(None, ge=1, description="replay only the first frames of each sequence")
    bev_images: bool = Field(False, description="keep each frame's two BV images (PNG) in its record (--bag-out)")
    unmeasured_every: int | None = Field(
        None,
        ge=2,
        description="every n-th frame is answered from the track's stream without measuring it when the track can "
        "give such an answer (Follower.unmeasured), as a service behind its frames answers those that waited past "
        "unmeasured_after_s (at 8 peers in bursts about every other frame); None: every frame is measured",
    )


def _stamp(group: FrameGroup, k: int, cfg: ReplayConfig) -> float:
    peer = group.peers[0]
    t = peer.extra.get("timestamp_s")
    return float(t) if t is not None else k * cfg.frame_period_s


def _odometry(group: FrameGroup) -> tuple[np.ndarray | None, np.ndarray | None]:
    ego, peer = group.ego, group.peers[0]
    if "odometry_pose" not in ego.extra or "odometry_pose" not in peer.extra:
        return None, None
    return parse_lidar_pose(ego.extra["odometry_pose"]), parse_lidar_pose(peer.extra["odometry_pose"])


def _cloud(agent, cfg: ReplayConfig) -> tuple[np.ndarray, np.ndarray | None]:
    """An agent's points and detected boxes as its car sends them (de-skewed with ``cfg.deskew``)."""
    pts, boxes = agent.load_points(), agent.detections
    return deskewed(agent, pts, boxes) if cfg.deskew else (pts, boxes)


def _reported(group: FrameGroup) -> np.ndarray | None:
    """T_ego_peer as the two cars' reported (GNSS) poses say, when both have one."""
    ego, peer = group.ego, group.peers[0]
    if "gnss_pose" not in ego.extra or "gnss_pose" not in peer.extra:
        return None
    return np.linalg.inv(parse_lidar_pose(ego.extra["gnss_pose"])) @ parse_lidar_pose(peer.extra["gnss_pose"])


def error_components(T_est: np.ndarray, T_true: np.ndarray) -> list[float]:
    """(yaw rad, tx m, ty m) of the estimate minus the truth: the components the result's covariance is of."""
    e, t = se2_params(T_est), se2_params(T_true)
    return [float(wrap_angle(e[0] - t[0])), e[1] - t[1], e[2] - t[2]]


def scored_frame(name: str, k: int, stamp: float, r, T_est: np.ndarray, T_true: np.ndarray | None) -> dict:
    """The fields every tracked frame's record shares, as `bb-align track` scores them: the answer ``r`` (an engine
    AlignResult or a wire Result: source, track state and event, success, reason) and its pose ``T_est`` against
    the truth (``None``: a recording without one, e.g. a bag; the errors are then None)."""
    t_err, r_err = (None, None) if T_true is None else pose_error(T_est, T_true)
    return {
        "sequence": name,
        "frame": k,
        "stamp": stamp,
        "distance_m": float(np.linalg.norm((T_est if T_true is None else T_true)[:2, 3])),
        "source": r.source,
        "state": r.track_state,
        "event": r.track_event,
        "success": bool(r.success),
        "reason": r.reason,
        "t_err_m": t_err,
        "r_err_deg": r_err,
        "err": None if T_true is None else error_components(T_est, T_true),  # (yaw rad, tx m, ty m), est - truth
        "T_ego_peer": np.asarray(T_est, dtype=float).tolist(),  # the answer's pose (4x4)
    }


def stream_sample(follower: Follower, stamp: float, O_ego, O_peer, T_true: np.ndarray) -> dict:
    """This frame's own evidence as the stream holds it (a measurement of the odometry offset X, with odometry):
    its error against the true offset (left increment, yaw rad / m / m) and covariance; what
    benchmarks/evidence_correlation.py measures the frames' correlation on."""
    samples = follower.track.stream.samples
    if O_ego is None or T_true is None or not samples or samples[-1].stamp != stamp:
        return {"evidence_err": None, "evidence_cov": None}
    s = samples[-1]
    X_true = ground_se2(O_ego) @ ground_se2(T_true) @ np.linalg.inv(ground_se2(O_peer))
    return {"evidence_err": log_left(s.X, X_true).tolist(), "evidence_cov": np.asarray(s.covariance).tolist()}


def replay_sequence(name: str, path: str | Path, cfg: ReplayConfig, progress: bool = False) -> list[dict]:
    """Every frame of one sequence folder through a fresh follower; one record per frame."""
    return replay_groups(name, list(iter_scenario_frames(name, path)), cfg, progress)


def bev_png(frame) -> bytes:
    """A prepared frame's BV image as PNG bytes (row 0 is +x, the car's front; column 0 is +y, its left)."""
    import cv2

    ok, buf = cv2.imencode(".png", frame.bev.image)
    if not ok:
        raise RuntimeError("PNG encoding of a BV image failed")
    return buf.tobytes()


def _answer(follower: Follower, cfg: ReplayConfig, k: int, frames, O_ego, O_peer, T_prior):
    """Frame k's answer and whether the frame was measured: from the stream on every ``cfg.unmeasured_every``-th
    frame when the track can answer so (with odometry), else a step of the follower."""
    ego_frame, peer_frame, stamp = frames
    n = cfg.unmeasured_every
    if n is not None and O_ego is not None and k % n == n - 1:
        r = follower.unmeasured(stamp, O_ego=O_ego, O_peer=O_peer)
        if r is not None:
            return r, False
    return follower.step(ego_frame, peer_frame, stamp, O_ego=O_ego, O_peer=O_peer, T_prior=T_prior), True


def replay_groups(name: str, groups: Iterable[FrameGroup], cfg: ReplayConfig, progress: bool = False) -> list[dict]:
    """Every frame of one sequence (its frame groups in time order, from a folder or a bag) through a fresh
    follower; one record per frame. ``cfg.bev_images``: each record also carries ``bev_png`` (ego, peer)."""
    aligner = Aligner(cfg.align)
    follower = Follower(aligner)
    total = len(groups) if isinstance(groups, Sized) else None
    groups = islice(groups, cfg.max_frames)
    records = []
    bar = tqdm(groups, desc=name, unit="frame", total=total, disable=not progress, leave=False)
    for k, group in enumerate(bar):
        ego, peer = group.ego, group.peers[0]
        ego_frame = aligner.prepare(*_cloud(ego, cfg), features=False)
        t0 = time.perf_counter()
        aligner.ready_to_track(ego_frame)  # per ego frame, shared by every peer (the service does it on arrival)
        ego_ms = (time.perf_counter() - t0) * 1e3
        peer_frame = aligner.prepare(*_cloud(peer, cfg), features=False)
        O_ego, O_peer = _odometry(group) if cfg.use_odometry else (None, None)
        stamp = _stamp(group, k, cfg)
        T_prior = _reported(group) if cfg.use_gnss else None
        r, measured_now = _answer(follower, cfg, k, (ego_frame, peer_frame, stamp), O_ego, O_peer, T_prior)
        known = ego.T_world_sensor is not None and peer.T_world_sensor is not None
        T_true = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor if known else None
        row = scored_frame(name, k, stamp, r, r.T_ego_peer, T_true)
        err = row["err"]
        if cfg.bev_images:
            row["bev_png"] = (bev_png(ego_frame), bev_png(peer_frame))
        # The engine run's own pose (the refinement's measurement, or the acquisition) before the track fused it.
        measured, measured_cov = (follower.last_measured if measured_now else None) or (None, None)
        sigma = None if r.covariance is None else np.sqrt(np.maximum(np.diag(r.covariance), 0.0)).tolist()
        records.append(
            row
            | {
                "kind": peer.extra.get("sweep"),
                "confidence": float(r.confidence),
                "measured": None if measured is None else list(se2_params(measured)),
                "odometry": None if O_ego is None else [list(se2_params(O_ego)), list(se2_params(O_peer))],
                "truth": None if T_true is None else list(se2_params(T_true)),
                "measured_err": None if measured is None or T_true is None else error_components(measured, T_true),
                "measured_cov": None if measured_cov is None else np.asarray(measured_cov).tolist(),
                # The boxes' own measurement of this frame (fused with the refinement's when they agree).
                "box_measured": list(se2_params(follower.last_boxes.T_ego_peer)) if follower.last_boxes.ok else None,
                "box_cov": np.asarray(follower.last_boxes.covariance).tolist() if follower.last_boxes.ok else None,
                "sigma": sigma,  # 1-sigma of (yaw rad, tx m, ty m) from the answer's covariance
                "covariance": None if r.covariance is None else np.asarray(r.covariance).tolist(),
                "within_3sigma": None
                if sigma is None or err is None
                else all(abs(e) <= 3 * s for e, s in zip(err, sigma)),
                **stream_sample(follower, stamp, O_ego, O_peer, T_true),
                "ran_acquisition": "acquire" in r.timings_ms,
                "unmeasured": not measured_now,  # answered from the stream unmeasured (ReplayConfig.unmeasured_every)
                "ms": float(r.timings_ms.get("track_total", math.nan)),
                "ego_frame_ms": ego_ms,
            }
        )
    return records


def _replay_star(args) -> list[dict]:
    return replay_sequence(*args)
