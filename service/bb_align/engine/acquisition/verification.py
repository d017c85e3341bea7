"""Step 3 of the acquisition: dense verification. Each hypothesis is refined coarsely (dense point-to-line ICP on a
small subset of the peer's lit pixels) and scored by its dense overlap; the ``finalists`` best are refined fully
and scored again; a rival near the best is refined fully too (it may be the best's own basin)."""

from __future__ import annotations

import cv2
import numpy as np

from ..box_poses import BoxSet, box_agreement, same_size
from ..config import AcquireConfig, AlignConfig, RefineConfig
from ..parallel import contiguous, run_parts
from ..refine import BevCloud, coarse_verification_loop, covisible_share, facing_args, icp_params, refine_icp
from .decision import dense_score, rivals, score
from .model import Hypothesis, PriorWindow, distinct

# The coarse verification: every hypothesis refined on COARSE_POINTS peer pixels through these gates (metres),
# COARSE_ITERS_PER_GATE steps each; the finalists are then refined with the full refinement config.
COARSE_POINTS = 400
COARSE_GATES_M = (2.0, 1.0)
COARSE_ITERS_PER_GATE = 2
# A rival this close to the best (metres, degrees) may be the best's own basin, not yet converged: refined fully.
MERGE_WITHIN_M, MERGE_WITHIN_DEG = 4.0, 4.0


def coarse_config(refine: RefineConfig) -> RefineConfig:
    """The refinement config of the coarse verification."""
    return refine.model_copy(update={"gates_m": COARSE_GATES_M, "iters_per_gate": COARSE_ITERS_PER_GATE})


def covisible_map(ego_image: np.ndarray, min_value: int, radius_px: int) -> np.ndarray:
    """uint8 mask of the ego image's pixels within ``radius_px`` of a lit one: where the ego car saw structure."""
    lit = (ego_image >= min_value).astype(np.uint8)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
    return cv2.dilate(lit, k)


def covisible_fraction(mask: np.ndarray, cloud: BevCloud, pts: np.ndarray, T: np.ndarray) -> float:
    """Fraction of peer points that land, under T, where the ego car saw structure (its dilated lit pixels)."""
    if len(pts) == 0:
        return 0.0
    p = np.ascontiguousarray(pts @ T[:2, :2].T + T[:2, 2])
    return float(covisible_share(mask, p, cloud.range_m, cloud.resolution_m))


def coarse_verification(
    cloud: BevCloud,
    covis: np.ndarray,
    pts: np.ndarray,
    Ts: list[np.ndarray],
    coarse: RefineConfig,
    final_gate: float,
    threads: int = 1,
    normals: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each pose of ``Ts`` refined (refine_icp with ``coarse``; ``normals``: the peer points' normals, see
    refine_icp) and scored at it (overlap_fitness within ``final_gate``, covisible_fraction), in one compiled call
    per group of poses (``threads`` groups in parallel; the poses are independent): (poses (H, 3, 3), fitness,
    rmse_m, covisible)."""
    T = np.ascontiguousarray(np.array(Ts, dtype=np.float64).reshape(-1, 3, 3))
    p = np.ascontiguousarray(pts, dtype=np.float64)
    pn, min_cos = facing_args(p, normals, coarse.facing_min_cos)
    params = icp_params(coarse, min_cos)
    bounds = (coarse.max_correction_m, coarse.max_correction_deg, final_gate)

    def run(group: np.ndarray):
        return coarse_verification_loop(cloud.grid, covis, p, pn, np.ascontiguousarray(group), params, bounds)

    parts = run_parts(run, contiguous(T, threads) or [T])
    return tuple(np.concatenate([part[m] for part in parts]) for m in range(4))  # type: ignore[return-value]


Sample = tuple[np.ndarray, np.ndarray | None]  # peer points and their normals (or None)


def verify(
    hyps: list[Hypothesis],
    ego_cloud: BevCloud,
    covis: np.ndarray,
    coarse_sample: Sample,
    full_sample: Sample,
    config: AlignConfig,
    coarse: RefineConfig,
    boxes: tuple[BoxSet, BoxSet] | None = None,
    window: PriorWindow | None = None,
) -> None:
    """Coarse dense refinement (``coarse``, on ``coarse_sample``: peer points and their normals, or None) + score
    for every hypothesis, then a full refinement of the finalists on ``full_sample`` (in place). ``boxes``: the
    (ego, peer) boxes, paired per pose. ``window``: a hypothesis the refinement carries out of the prior's window is
    dropped (the list may end empty)."""
    a = config.acquire
    boxes = boxes if boxes is not None else (BoxSet.of(np.zeros((0, 7))),) * 2
    size_ok = same_size(boxes[1], boxes[0], a)  # the boxes' footprint agreement, the same under every pose
    _coarse_scores(hyps, ego_cloud, covis, coarse_sample, config.refine.gates_m[-1], coarse, boxes, a, size_ok)
    if window is not None:
        hyps[:] = [h for h in hyps if window.holds(h.T)]
    hyps.sort(key=lambda x: -score(x, a))
    _refine_finalists(hyps[: a.finalists], ego_cloud, covis, full_sample, config, boxes, size_ok)
    if window is not None:
        hyps[:] = [h for h in hyps if not h.refined or window.holds(h.T)]
    finals = sorted([h for h in hyps if h.refined], key=lambda x: -score(x, a))
    hyps[: len(finals)] = finals
    if not hyps:
        return
    merge_neighbours(hyps, ego_cloud, full_sample, config)


def _coarse_scores(hyps, ego_cloud, covis, sample: Sample, final_gate, coarse, boxes, a: AcquireConfig, size_ok):
    """Every hypothesis refined coarsely and scored at its coarse pose (in place)."""
    Ts, fitness, rmse, covisible = coarse_verification(
        ego_cloud, covis, sample[0], [h.T for h in hyps], coarse, final_gate, a.threads, sample[1]
    )
    for n, h in enumerate(hyps):
        h.T, h.fitness, h.rmse_m, h.covisible = Ts[n], float(fitness[n]), float(rmse[n]), float(covisible[n])
        h.box_pairs, h.box_score = box_agreement(h.T, boxes[1], boxes[0], a, size_ok)


def _refine_finalists(finalists, ego_cloud, covis, sample: Sample, config: AlignConfig, boxes, size_ok) -> None:
    """The finalists refined fully, in parallel (``acquire.threads``), and scored again (in place)."""
    a, rf = config.acquire, config.refine
    full_pts, full_normals = sample
    refined = run_parts(
        lambda hs: [refine_icp(ego_cloud, full_pts, h.T, rf, full_normals) for h in hs],
        contiguous(finalists, a.threads),
    )
    for h, ref in zip(finalists, [r for part in refined for r in part], strict=True):
        take_refinement(h, ref, ego_cloud, covis, full_pts, boxes, a, size_ok)


def take_refinement(h: Hypothesis, ref, ego_cloud, covis, pts, boxes, a: AcquireConfig, size_ok) -> None:
    """A hypothesis refined fully (``ref``: refine_icp's result on ``pts``): its pose, overlap, co-visible share and
    the (ego, peer) ``boxes`` paired under it."""
    h.T, h.fitness, h.rmse_m, h.refined = ref.T, ref.fitness, ref.rmse_m, True
    h.covisible = covisible_fraction(covis, ego_cloud, pts, h.T)
    h.box_pairs, h.box_score = box_agreement(h.T, boxes[1], boxes[0], a, size_ok)


def merge_neighbours(hyps: list[Hypothesis], ego_cloud: BevCloud, full_sample: Sample, config: AlignConfig) -> None:
    """A rival close to the best (within MERGE_WITHIN_M and MERGE_WITHIN_DEG) may be the same basin, only not yet
    converged by the coarse stage. Refine it fully: if it meets the best it is the same pose and no longer a rival;
    if not, it keeps its coarse values (the margin's calibration). Rivals only ever go away, so margins only grow
    when a 'rival' was the best pose itself."""
    a = config.acquire
    for _ in range(a.merge_checks):
        best = hyps[0]
        rival = max(rivals(hyps, a), key=lambda h: dense_score(h, a), default=None)  # the one the margin is over
        if rival is None or rival.refined or distinct(rival.T, [best], MERGE_WITHIN_M, MERGE_WITHIN_DEG):
            return
        T = refine_icp(ego_cloud, full_sample[0], rival.T, config.refine, full_sample[1]).T
        if distinct(T, [best], a.distinct_m, a.distinct_deg):
            return
        rival.T = T  # the same pose as the best: rivals() skips it from now on


def covisible(frame, config: AlignConfig) -> np.ndarray:
    """The frame's co-visibility mask (covisible_map within acquire.covisible_m), built once per frame."""
    a, mv = config.acquire, config.refine.min_pixel_value
    return frame.cached(
        ("covisible", a.covisible_m, mv),
        lambda: covisible_map(frame.bev.image, mv, max(1, int(round(a.covisible_m / frame.bev.resolution_m)))),
    )
