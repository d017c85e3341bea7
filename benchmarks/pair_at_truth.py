"""One simulated pair, judged against its truth: the engine's answer, the dense overlap at the answer and at the true
pose (every refinement gate), the refinement started at the truth, and the overlap along the covariance's weakest
translation axis. Used for issue #11's far-range wrong success (docs/acquisition.md, session 9).

    bb-align sim DIR --scenarios 80 --seed 4242 --workers 2
    PYTHONPATH=service:client .venv/bin/python benchmarks/pair_at_truth.py DIR sim_4242_0060 1
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import acquisition_range as ar  # noqa: E402  (its loaders and variants)
from bb_align.engine.geometry import pose_error, se2, se2_params  # noqa: E402
from bb_align.engine.refine import bev_points, overlap_fitness, refine_icp  # noqa: E402
from bb_align.io.dataset import iter_frames  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("root")
    ap.add_argument("scenario")
    ap.add_argument("peer")
    ap.add_argument("--range", type=float, default=100.0, dest="range_m")
    args = ap.parse_args()
    ar._init(["multi"], args.range_m, [])
    from bb_align.lab.evaluation.runner import _load_agent

    cfg, prep = ar._state["eval"], ar._state["prep"]
    aligner = ar._state["aligners"]["multi"]
    group = next(g for g in iter_frames(args.root) if g.scenario == args.scenario)
    peer_frame = next(p for p in group.peers if p.agent == args.peer)
    ego = _load_agent(group.ego, prep, cfg, group.scenario, group.timestamp)
    peer = _load_agent(peer_frame, prep, cfg, group.scenario, group.timestamp)
    T_true = se2(*se2_params(np.linalg.inv(ego.frame.T_world_sensor) @ peer_frame.T_world_sensor))
    r = aligner.align(ego.prepared, peer.prepared)
    rf = aligner.config.refine
    cloud = ego.prepared.cloud(rf)
    pts_peer = bev_points(peer.prepared.bev, rf.min_pixel_value, rf.max_peer_points, seed=aligner.config.seed)
    print(f"answer: success {r.success} ({r.reason}), error {pose_error(r.T_ego_peer, T_true)} (m, deg)")
    T_bv = np.asarray(r.T_bv)
    for name, T in [("stage-1 pose", T_bv), ("truth", T_true)]:
        fits = {g: round(overlap_fitness(cloud, pts_peer, T, g)[0], 3) for g in rf.gates_m}
        print(f"overlap at the {name} by gate (m): {fits}")
    from_truth = refine_icp(cloud, pts_peer, T_true, rf)
    print(f"refinement started at the truth ends {pose_error(from_truth.T, T_true)} (m, deg) away")
    if r.covariance is not None:
        w, V = np.linalg.eigh(np.asarray(r.covariance)[1:, 1:])
        u = V[:, -1]
        offset = T_true[:2, 2] - T_bv[:2, 2]
        print(
            f"weakest axis {np.round(u, 3)}, sigma {np.sqrt(w[-1]):.2f} m; truth offset {np.round(offset, 2)} m, "
            f"{offset @ u:+.2f} m along it"
        )
        profile = []
        for s in np.arange(-3.0, 3.01, 0.5):
            T = T_bv.copy()
            T[:2, 2] += s * u
            profile.append(f"{s:+.1f}: {overlap_fitness(cloud, pts_peer, T, rf.gates_m[-1])[0]:.3f}")
        print("overlap along it (m: fraction):", ", ".join(profile))


if __name__ == "__main__":
    main()
