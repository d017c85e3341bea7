"""The swept sequences replayed through a real service, every successful answer checked against the truth.

``bb-align track`` runs the follower in-process; this sends the same sequences as cars do: per frame the ego's and
the peer's sweep encoded as wire Frames (BV image, boxes and scores, the GNSS-grade reported pose, the car's
odometry, stamped with the yaml's ``timestamp_s``) and posted to ``/v1/align`` (the ego frame inline), one peer id
per sequence, so the service keeps one track per sequence. The answers are scored as ``bb-align track`` scores
its records (bb_align.lab.tracking.summary): a wrong frame is a successful answer off by more than 1 m or 1 deg.

    with httpx.Client(base_url=url, timeout=60) as http:
        records = replay_through_service(http, "out/sweep23", max_frames=40)
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from bb_align.io.dataset import AgentFrame, FrameGroup, find_scenarios, iter_scenario_frames, parse_lidar_pose
from bb_align.io.defaults import DESKEW_DEFAULT
from bb_align.io.sweeps import deskewed

from .replay import scored_frame


def _frame_bytes(
    agent: AgentFrame,
    vehicle_id: str,
    stamp: float,
    seq: int,
    odometry: bool,
    bev: dict,
    gnss: bool = True,
    deskew: bool = DESKEW_DEFAULT,
) -> bytes:
    from bb_align_client import encode_frame

    extra = agent.extra
    gnss = parse_lidar_pose(extra["gnss_pose"]) if gnss and "gnss_pose" in extra else None
    odo = parse_lidar_pose(extra["odometry_pose"]) if odometry and "odometry_pose" in extra else None
    scores = None if agent.detection_scores is None else np.clip(agent.detection_scores, 0.0, 1.0)
    pts, boxes = agent.load_points(), agent.detections
    if deskew:  # as a sender with odometry does
        pts, boxes = deskewed(agent, pts, boxes)
    return encode_frame(
        pts,
        boxes,
        vehicle_id=vehicle_id,
        stamp=stamp,
        seq=seq,
        pose=gnss,
        odometry=odo,
        scores=scores,
        **bev,
    )


def replay_sequence_through_service(
    http,
    name: str,
    path: str | Path,
    peer_id: str,
    *,
    max_frames: int | None = None,
    **kwargs,
) -> list[dict]:
    """One sequence folder, frame by frame in order, through the service; one record per frame (the fields
    bb_align.lab.tracking.summary.summarize reads)."""
    groups = list(iter_scenario_frames(name, path))[:max_frames]
    return replay_groups_through_service(http, name, groups, peer_id, **kwargs)


def replay_groups_through_service(
    http,
    name: str,
    groups: Iterable[FrameGroup],
    peer_id: str,
    *,
    ego_id: str = "ego",
    odometry: bool = True,
    gnss: bool = True,
    bev: dict | None = None,
    deskew: bool = DESKEW_DEFAULT,
    frame_period_s: float = 0.1,
    stamp_offset_s: float = 100.0,
    bev_images: bool = False,
) -> list[dict]:
    """One sequence's frame groups (from a folder or a bag), in order, through the service; one record per frame.
    Wire stamps are the frames' times plus ``stamp_offset_s`` (a simulated sequence starts near 0; wire stamps are
    >= 0), and so are the records'. ``bev_images``: each record carries ``bev_png`` (ego, peer) as the cars drew
    them."""
    from bb_align.protocol import MSGPACK, load_result, pack_align_request

    records = []
    for k, group in enumerate(groups):
        ego, peer = group.ego, group.peers[0]
        # The yaml's times start near 0 (a mid-sweep time may be slightly negative); wire stamps are >= 0.
        stamp = stamp_offset_s + float(peer.extra.get("timestamp_s", k * frame_period_s))
        body = pack_align_request(
            _frame_bytes(peer, peer_id, stamp, k, odometry, bev or {}, gnss, deskew),
            _frame_bytes(ego, ego_id, stamp, k, odometry, bev or {}, gnss, deskew),
        )
        t0 = time.perf_counter()
        resp = http.post("/v1/align", content=body, headers={"content-type": MSGPACK})
        ms = (time.perf_counter() - t0) * 1e3
        if resp.status_code != 200:
            raise RuntimeError(f"{name} frame {k}: HTTP {resp.status_code}: {resp.text[:300]}")
        r = load_result(resp.content)
        known = ego.T_world_sensor is not None and peer.T_world_sensor is not None
        T_true = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor if known else None
        row = scored_frame(name, k, stamp, r, r.matrix(), T_true)
        err = row["err"]
        if bev_images:
            row["bev_png"] = (_bev_png(ego, bev or {}, deskew), _bev_png(peer, bev or {}, deskew))
        sigma = None if r.covariance is None else np.sqrt(np.maximum(np.diag(np.asarray(r.covariance)), 0)).tolist()
        records.append(
            row
            | {
                "confidence": float(r.confidence),
                "covariance": None if r.covariance is None else np.asarray(r.covariance).tolist(),
                "within_3sigma": None
                if sigma is None or err is None
                else all(abs(e) <= 3 * s for e, s in zip(err, sigma)),
                "ran_acquisition": r.source == "acquisition" or "acquire" in r.timings_ms,
                "ms": float(r.timings_ms.get("track_total", r.latency_ms or ms)),
                "round_trip_ms": ms,
                "ego_frame_ms": float(r.timings_ms.get("ego_features", 0.0)),
                "notes": r.notes[-1:] if not r.success else [],
            }
        )
    return records


def _bev_png(agent: AgentFrame, bev: dict, deskew: bool = DESKEW_DEFAULT) -> bytes:
    """The BV image a car sends for this sweep (encode_frame's), as PNG."""
    import cv2

    from bb_align.engine.bev import make_bev
    from bb_align.engine.config import BevConfig

    pts = agent.load_points()
    if deskew:  # the image the car drew
        pts, _ = deskewed(agent, pts, agent.detections)
    return cv2.imencode(".png", make_bev(pts, BevConfig(**bev)).image)[1].tobytes()


def replay_through_service(
    http,
    root: str | Path,
    *,
    limit: int | None = None,
    max_frames: int | None = None,
    odometry: bool = True,
    bev: dict | None = None,
    progress: Callable[[Iterable, str], Iterable] | None = None,
) -> list[dict]:
    """Every sequence under ``root`` (``bb-align sim --sweep``), each as its own peer id, through the service."""
    scenarios = find_scenarios(root)[:limit]
    if not scenarios:
        raise ValueError(f"no sequence folders under {root}")
    out = []
    items = list(enumerate(scenarios))
    for i, (name, path) in progress(items, "sequences") if progress else items:
        out += replay_sequence_through_service(
            http, name, path, f"seq{i}", odometry=odometry, max_frames=max_frames, bev=bev
        )
    return out


def wrong_answers(records: list[dict], max_m: float = 1.0, max_deg: float = 1.0) -> list[dict]:
    """The successful answers off the truth by more than max_m or max_deg."""
    return [r for r in records if r["success"] and (r["t_err_m"] > max_m or r["r_err_deg"] > max_deg)]
