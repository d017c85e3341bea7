"""The free space in the acquisition's decision (engine.freespace): a hypothesis that lays one car's tall structure
where the other car's LiDAR saw through is ruled out as a rival, and a best hypothesis so ruled out gives way to
the best of the others (refined fully and measured again)."""

from __future__ import annotations

import numpy as np

from ..box_poses import same_size
from ..config import AlignConfig
from ..freespace import conflict, free_space_map, tall_points
from ..refine import refine_icp
from .model import Hypothesis, distinct
from .verification import covisible, take_refinement


def conflicts(ego, peer, hyps: list[Hypothesis], config: AlignConfig) -> None:
    """The free-space conflict of every hypothesis (in place): the peer's tall structure in the ego car's free space
    under T, and the ego's in the peer's under T^-1; the larger (engine.freespace). Each frame's maps are built once;
    "near structure" is the co-visibility mask (acquire.covisible_m)."""
    fs, mv, seed = config.free_space, config.refine.min_pixel_value, config.seed

    def maps(frame):
        def build():
            near = covisible(frame, config)
            return free_space_map(frame.bev, mv, near, fs), near, tall_points(frame.bev, fs, seed)

        return frame.cached(("free_space", fs, mv, config.acquire.covisible_m), build)

    (ego_free, ego_near, ego_tall), (peer_free, peer_near, peer_tall) = maps(ego), maps(peer)
    for h in hyps:
        h.conflict = max(
            conflict(ego_free, ego_near, ego.bev, peer_tall, h.T),
            conflict(peer_free, peer_near, peer.bev, ego_tall, np.linalg.inv(h.T)),
        )


def rival_bound(hyps: list[Hypothesis], config: AlignConfig) -> float:
    """The conflict above which a hypothesis is ruled out: free_space.rival_conflict, or the lower
    free_space.alias_conflict when the best is above it and a distinct hypothesis with some overlap
    (acquire.runner_up_floor) is clear of the free space (gave_way_max_conflict): the two LiDARs' free space
    then sets the two apart (on real streets an overlay of the two cars' near fields, 0.05-0.15, against the
    truth's at most 0.03)."""
    fs, a = config.free_space, config.acquire
    bound = fs.rival_conflict
    if fs.alias_conflict is None or hyps[0].conflict <= fs.alias_conflict:
        return bound
    clean = any(
        h.conflict <= min(fs.gave_way_max_conflict, fs.alias_conflict)
        and h.fitness >= a.runner_up_floor
        and distinct(h.T, [hyps[0]], a.distinct_m, a.distinct_deg)
        for h in hyps[1:]
    )
    return min(bound, fs.alias_conflict) if clean else bound


def without_ruled_out(ego, peer, hyps, ego_cloud, covis, full_sample, boxes, bound, config) -> list[Hypothesis]:
    """The hypotheses the free space does not rule out (conflict <= ``bound``), best first; the new best is
    refined fully (as verify's finalists are) and its conflict measured again at the refined pose, until the first
    is refined and not ruled out (at most ``acquire.finalists`` such refinements: then none is kept)."""
    a = config.acquire
    size_ok = same_size(boxes[1], boxes[0], a)
    kept = [h for h in hyps if h.conflict <= bound]
    for _ in range(a.finalists):
        if not kept or kept[0].refined:
            return kept  # refined hypotheses first, as verify orders them
        h = kept[0]
        ref = refine_icp(ego_cloud, full_sample[0], h.T, config.refine, full_sample[1])
        take_refinement(h, ref, ego_cloud, covis, full_sample[0], boxes, a, size_ok)
        conflicts(ego, peer, [h], config)
        if h.conflict > bound:
            kept.pop(0)  # refined into a pose the free space rules out
    return kept if kept and kept[0].refined else []
