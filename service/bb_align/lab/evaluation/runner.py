"""Run the engine over a dataset: every (scenario, timestamp), ego = lowest agent id, each other agent a peer.

Per agent frame the engine's ``prepare`` runs once; each peer is aligned against the ego and compared with the
true relative pose ``T_ego_peer_true = inv(T_world_ego) @ T_world_peer``. The same pair also gets the stage-1
result (T_bv alone), the graph-matching baseline, and the late-fusion detection test (peer boxes fused into
the ego frame with a noisy, the recovered, and the true pose).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from tqdm import tqdm

from bb_align.engine.boxes import transform_boxes
from bb_align.engine.config import AlignConfig
from bb_align.engine.deskew import deskew_sweep
from bb_align.engine.geometry import (
    ground_se2,
    pose_error,
    se2,
    se2_params,
    se3_from_se2,
    transform_points_2d,
    wrap_angle,
)
from bb_align.engine.matching import match_descriptors
from bb_align.engine.pipeline import Aligner
from bb_align.engine.verdict import STAGE2_FAILURES
from bb_align.io.dataset import AgentFrame, FrameGroup, iter_frames
from bb_align.io.defaults import DESKEW_DEFAULT, DESKEW_HELP
from bb_align.io.detections import DetectionDir, load_detection_file
from bb_align.io.sweeps import deskew_boxes, sweep_twist

from ..sim.detections import DetectionModel, detect, frame_rng, points_per_vehicle, vehicles_in_sensor
from .ap import match_frame, nms_bev
from .baseline import GraphMatchConfig, graph_match

# The one definition of the distance bins (metres, [lo, hi)): the accuracy tables and figures bin pairs by the
# distance between the cars, Table I (late-fusion AP) bins boxes by their distance from the ego, with these.
DIST_BUCKETS = {"0-20": (0.0, 20.0), "20-40": (20.0, 40.0), "40-70": (40.0, 70.0), "70+": (70.0, math.inf)}
AP_RANGES = {**DIST_BUCKETS, "all": (0.0, math.inf)}
AP_IOUS = (0.5, 0.7)
POSES = ("noisy", "recovered", "true")
_STAGE2_REASONS = {r.value for r in STAGE2_FAILURES}


class EvalConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    align: AlignConfig = AlignConfig()
    detection: DetectionModel = Field(DetectionModel(), description="the detector model of simulate_detections")
    simulate_detections: bool = Field(
        False, description="simulate every agent's detections from its ground-truth labels (never implicitly)"
    )
    detections_dir: str | None = Field(
        None, description="per-frame detection files (bb_align.io.detections); used instead of the yaml's"
    )
    baseline: GraphMatchConfig = GraphMatchConfig()
    pose_noise_t_m: float = Field(2.0, ge=0, description="sigma_t of the peer pose noise for the AP test")
    pose_noise_deg: float = Field(2.0, ge=0, description="sigma_theta of the peer pose noise for the AP test")
    use_prior: bool = Field(False, description="give the engine the noisy pose as a GNSS-grade prior (T_prior)")
    deskew: bool = Field(DESKEW_DEFAULT, description=DESKEW_HELP)
    common_min_points: int = Field(10, ge=1, description="a car is 'seen' by an agent with this many points")
    nms_iou: float = Field(0.15, gt=0, le=1, description="late-fusion NMS threshold (OpenCOOD's)")
    system_error_offset: bool = Field(
        False,
        description="DAIR-V2X-C: score against lidar_i2v shifted by the frame's system_error_offset (bb_align.io.dair)",
    )
    seed: int = 0


@dataclass
class PairRecord:
    scenario: str
    timestamp: str
    ego: str
    peer: str
    distance_m: float
    true_yaw_deg: float
    ego_sensor: str
    peer_sensor: str
    ego_points: int
    peer_points: int
    ego_boxes: int
    peer_boxes: int
    common_cars: int
    success: bool
    reason: str | None
    t_err_m: float
    r_err_deg: float
    inliers_bv: int
    inliers_box: int
    confidence: float
    stage2_applied: bool
    stage1_success: bool
    stage1_t_err_m: float
    stage1_r_err_deg: float
    baseline_success: bool
    baseline_matches: int
    baseline_t_err_m: float
    baseline_r_err_deg: float
    prepare_ms: float
    align_ms: float
    matches_bv: int = 0
    # Oracle diagnostics (true pose known): peer keypoints with an ego keypoint within 2 m under the true pose
    # (what overlap allows), and how many of the engine's descriptor matches are right (what matching finds).
    oracle_repeatable_kp: int = 0
    oracle_correct_matches: int = 0
    ego_detections: str = ""  # where the boxes came from: yaml, folder, simulated or none
    peer_detections: str = ""
    deskewed: bool = False  # both clouds were de-skewed with their sweep's motion before prepare
    # The result's 3x3 covariance of (yaw rad, tx m, ty m) and the true error in those parameters (truth minus
    # estimate, yaw wrapped): what the covariance claims and what it should cover.
    covariance: list | None = None
    error_params: list | None = None
    # AP material: {pose: {range: {"n_gt": int, "scores": [...], "tp@0.5": [...], "tp@0.7": [...]}}}
    ap: dict = field(default_factory=dict, repr=False)

    def to_dict(self, with_ap: bool = False) -> dict:
        d = asdict(self)
        if not with_ap:
            d.pop("ap")
        return d


def _frame_rng(cfg: EvalConfig, *keys: str) -> np.random.Generator:
    return frame_rng(cfg.seed, *keys)


@dataclass
class _Agent:
    frame: AgentFrame
    points: np.ndarray
    boxes: np.ndarray
    scores: np.ndarray
    seen: dict[str, int]  # vehicle id -> points on it
    prepared: object
    prepare_ms: float
    detection_source: str  # yaml, folder, simulated or none
    gt_ids: dict[str, int]  # the labels in the sensor frame (de-skewed with the cloud): id -> row of gt
    gt: np.ndarray
    deskewed: bool


def _load_agent(agent: AgentFrame, aligner: Aligner, cfg: EvalConfig, scenario: str, ts: str) -> _Agent:
    pts = agent.load_points()
    ids, gt = vehicles_in_sensor(agent)
    seen = points_per_vehicle(agent, pts, gt, ids)
    twist = sweep_twist(agent) if cfg.deskew else None
    if twist is not None:
        pts = deskew_sweep(pts, *twist[:2], period_s=twist[2]).astype(pts.dtype)
        # the simulator labels a car its sweep hit where the distorted sweep shows it, the others at mid-sweep
        hit = np.array([seen.get(i, 0) > 0 for i in ids], dtype=bool)
        if hit.any():
            gt = gt.copy()
            gt[hit] = deskew_boxes(gt[hit], *twist[:2], twist[2])
    if cfg.simulate_detections:
        counts = np.array([seen[i] for i in ids], dtype=np.int64)
        det = detect(gt, counts, pts, _frame_rng(cfg, scenario, agent.agent, ts), cfg.detection)
        boxes, scores, source = det.boxes, det.scores, "simulated"
    else:
        found = None
        if cfg.detections_dir is not None:
            found = DetectionDir(cfg.detections_dir).path_for(scenario, agent.agent, agent.timestamp or ts)
        if found is not None:
            boxes, scores = load_detection_file(found)
            scores = scores if scores is not None else np.ones(len(boxes))
            source = "folder"
        elif cfg.detections_dir is None and agent.detections is not None:
            boxes = agent.detections
            scores = agent.detection_scores if agent.detection_scores is not None else np.ones(len(boxes))
            source = str(agent.extra.get("detections_from", "yaml"))  # DAIR-V2X-C: its labels
        else:  # no detections: stage 2 is skipped, late fusion has no boxes from this agent
            boxes, scores, source = np.zeros((0, 7)), np.zeros(0), "none"
        if twist is not None and source != "simulated":  # a detector run on the de-skewed cloud finds them here
            boxes = deskew_boxes(boxes, *twist[:2], twist[2])
    t0 = time.perf_counter()
    prepared = aligner.prepare(pts, boxes)
    ms = (time.perf_counter() - t0) * 1e3
    return _Agent(agent, pts, boxes, scores, seen, prepared, ms, source, ids, gt, twist is not None)


def _ap_material(ego: _Agent, peer: _Agent, T_ego_peer_by_pose: dict[str, np.ndarray], cfg: EvalConfig) -> dict:
    """Late fusion per pose: ego boxes + peer boxes moved into the ego frame, NMS, TP flags per range/IoU."""
    ids, gt = ego.gt_ids, ego.gt
    visible = np.array([ego.seen.get(i, 0) + peer.seen.get(i, 0) > 0 for i in ids], dtype=bool)
    gt = gt[visible] if len(gt) else gt
    out = {}
    for pose, T in T_ego_peer_by_pose.items():
        peer_in_ego = transform_boxes(se2(*se2_params(T)), peer.boxes)  # ground-plane part of a 3x3 or 4x4
        boxes = np.concatenate([ego.boxes, peer_in_ego])
        scores = np.concatenate([ego.scores, peer.scores])
        keep = nms_bev(boxes, scores, cfg.nms_iou) if len(boxes) else np.zeros(0, dtype=np.int64)
        boxes, scores = boxes[keep], scores[keep]
        d_pred = np.hypot(boxes[:, 0], boxes[:, 1]) if len(boxes) else np.zeros(0)
        d_gt = np.hypot(gt[:, 0], gt[:, 1]) if len(gt) else np.zeros(0)
        per_range = {}
        for name, (lo, hi) in AP_RANGES.items():
            sp = (d_pred >= lo) & (d_pred < hi)
            sg = (d_gt >= lo) & (d_gt < hi)
            entry = {"n_gt": int(sg.sum()), "scores": scores[sp].tolist()}
            for iou in AP_IOUS:
                entry[f"tp@{iou}"] = match_frame(boxes[sp], scores[sp], gt[sg], iou).tolist()
            per_range[name] = entry
        out[pose] = per_range
    return out


def _oracle(ego, peer, T_ego_peer_true: np.ndarray, cfg: EvalConfig, tol_m: float = 2.0) -> tuple[int, int]:
    """(repeatable peer keypoints, correct descriptor matches) under the true pose: a diagnosis of stage 1."""
    e, p = ego.prepared, peer.prepared
    if not len(e.keypoints_xy) or not len(p.keypoints_xy):
        return 0, 0
    kp_peer = transform_points_2d(se2(*se2_params(T_ego_peer_true)), p.keypoints_xy)
    d = np.linalg.norm(kp_peer[:, None, :] - e.keypoints_xy[None, :, :], axis=2)
    repeatable = int((d.min(axis=1) < tol_m).sum())
    i_p, i_e = match_descriptors(
        p.descriptors,
        np.concatenate([e.descriptors, e.descriptors_flipped]),
        mutual=cfg.align.match.mutual,
        ratio=cfg.align.match.ratio,
    )
    i_e = i_e % len(e.descriptors)
    correct = int((np.linalg.norm(kp_peer[i_p] - e.keypoints_xy[i_e], axis=1) < tol_m).sum())
    return repeatable, correct


def _noisy(T_ego_peer_true: np.ndarray, rng: np.random.Generator, cfg: EvalConfig) -> np.ndarray:
    """OpenCOOD-style pose noise on the peer: Gaussian on its x, y (sigma_t) and yaw (sigma_theta)."""
    yaw, tx, ty = se2_params(T_ego_peer_true)
    return se2(
        yaw + np.radians(rng.normal(0, cfg.pose_noise_deg)),
        tx + rng.normal(0, cfg.pose_noise_t_m),
        ty + rng.normal(0, cfg.pose_noise_t_m),
    )


def evaluate_group(group: FrameGroup, aligner: Aligner, cfg: EvalConfig) -> list[PairRecord]:
    """All pairs (ego, peer) of one timestamp."""
    ego = _load_agent(group.ego, aligner, cfg, group.scenario, group.timestamp)
    records = []
    for peer_frame in group.peers:
        peer = _load_agent(peer_frame, aligner, cfg, group.scenario, group.timestamp)
        T_true = np.linalg.inv(ego.frame.T_world_sensor) @ peer_frame.T_world_sensor
        rng = _frame_rng(cfg, group.scenario, group.timestamp, peer_frame.agent, "noise")
        T_noisy = _noisy(T_true, rng, cfg)
        t0 = time.perf_counter()
        res = aligner.align(ego.prepared, peer.prepared, T_prior=T_noisy if cfg.use_prior else None)
        align_ms = (time.perf_counter() - t0) * 1e3
        t_err, r_err = pose_error(res.T_ego_peer, T_true)
        s1_t, s1_r = pose_error(se3_from_se2(res.T_bv), T_true)
        s1_ok = res.success or res.reason in _STAGE2_REASONS
        gm = graph_match(ego.boxes, peer.boxes, cfg.baseline)
        g_t, g_r = pose_error(gm.T_ego_peer, T_true)
        common = sum(
            1
            for i, n in ego.seen.items()
            if n >= cfg.common_min_points and peer.seen.get(i, 0) >= cfg.common_min_points
        )
        T_rec = res.T_ego_peer if res.success else T_noisy  # a failed recovery keeps the reported pose
        rep, correct = _oracle(ego, peer, T_true, cfg)
        yaw, tx, ty = se2_params(T_true)
        err = np.subtract((yaw, tx, ty), se2_params(ground_se2(res.T_ego_peer)))
        err[0] = wrap_angle(err[0])
        records.append(
            PairRecord(
                scenario=group.scenario,
                timestamp=group.timestamp,
                ego=ego.frame.agent,
                peer=peer_frame.agent,
                distance_m=float(np.hypot(tx, ty)),
                true_yaw_deg=float(np.degrees(yaw)),
                ego_sensor=str(ego.frame.extra.get("sensor", "")),
                peer_sensor=str(peer_frame.extra.get("sensor", "")),
                ego_points=len(ego.points),
                peer_points=len(peer.points),
                ego_boxes=len(ego.boxes),
                peer_boxes=len(peer.boxes),
                common_cars=int(common),
                success=bool(res.success),
                reason=res.reason,
                t_err_m=t_err,
                r_err_deg=r_err,
                inliers_bv=int(res.inliers_bv),
                inliers_box=int(res.inliers_box),
                confidence=float(res.confidence),
                stage2_applied=bool(res.stage2_applied),
                stage1_success=bool(s1_ok),
                stage1_t_err_m=s1_t,
                stage1_r_err_deg=s1_r,
                baseline_success=bool(gm.success),
                baseline_matches=int(gm.matches),
                baseline_t_err_m=g_t,
                baseline_r_err_deg=g_r,
                prepare_ms=ego.prepare_ms + peer.prepare_ms,
                align_ms=align_ms,
                matches_bv=int(res.matches_bv),
                oracle_repeatable_kp=rep,
                oracle_correct_matches=correct,
                ego_detections=ego.detection_source,
                peer_detections=peer.detection_source,
                deskewed=ego.deskewed and peer.deskewed,
                covariance=None if res.covariance is None else np.asarray(res.covariance, float).tolist(),
                error_params=[float(v) for v in err],
                ap=_ap_material(ego, peer, {"noisy": T_noisy, "recovered": se3_from_se2(T_rec), "true": T_true}, cfg),
            )
        )
    return records


# ---- parallel driver ---------------------------------------------------------------------------------------

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
_worker_state: dict = {}  # per worker process: its Aligner and config (a cache, built once)


def _init_worker(cfg_json: str) -> None:
    # An exception here would make the pool respawn workers forever: keep it for _run_one to raise.
    try:
        cfg = EvalConfig.model_validate_json(cfg_json)
        _worker_state["cfg"] = cfg
        _worker_state["aligner"] = Aligner(cfg.align)
    except Exception as exc:  # noqa: BLE001 - re-raised in the task, where the pool reports it
        _worker_state["error"] = exc


def _run_one(group: FrameGroup) -> list[PairRecord]:
    if "error" in _worker_state:
        raise RuntimeError(f"evaluation worker failed to start: {_worker_state['error']!r}")
    return evaluate_group(group, _worker_state["aligner"], _worker_state["cfg"])


def evaluate_dataset(
    root, cfg: EvalConfig | None = None, limit: int | None = None, workers: int | None = None, progress: bool = True
) -> list[PairRecord]:
    """Evaluate every frame group under ``root`` (the first ``limit`` pairs' groups when given)."""
    cfg = cfg or EvalConfig()
    groups = []
    n_pairs = 0
    for g in iter_frames(root, system_error_offset=cfg.system_error_offset):
        if limit is not None and n_pairs >= limit:
            break
        groups.append(g)
        n_pairs += len(g.peers)
    if not groups:
        raise ValueError(f"no frame with two or more agents under {root}")
    workers = workers if workers is not None else min(2, os.cpu_count() or 1)
    records: list[PairRecord] = []
    bar = tqdm(total=n_pairs, desc="aligning", unit="pair", disable=not progress)
    if workers <= 1:
        aligner = Aligner(cfg.align)
        for g in groups:
            recs = evaluate_group(g, aligner, cfg)
            records += recs
            bar.update(len(recs))
    else:
        saved = {k: os.environ.get(k) for k in _THREAD_VARS}
        os.environ.update({k: "1" for k in _THREAD_VARS})  # one thread per worker process: no oversubscription
        try:
            with get_context("spawn").Pool(
                workers, initializer=_init_worker, initargs=(cfg.model_dump_json(),)
            ) as pool:
                for recs in pool.imap(_run_one, groups):
                    records += recs
                    bar.update(len(recs))
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    bar.close()
    if limit is not None:
        records = records[:limit]
    return records
