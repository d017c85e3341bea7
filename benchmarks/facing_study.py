"""The refinement started at the true pose, with and without the facing test (issue #11, session 14).

    PYTHONPATH=service:client .venv/bin/python benchmarks/facing_study.py SIM_ROOT [SIM_ROOT ...] [--cos=-1,0,0.5]
        [--min-distance 40] [--workers 2] [--plot docs/acquisition/fig_facing.png]

For every pair of the `bb-align sim` datasets at least ``--min-distance`` apart, the peer's sampled pixels are refined
onto the ego frame from the exact true pose (the engine's `refine_icp`, the default refinement config) once per
``facing_min_cos`` of ``--cos`` (-1: the test off, every pair of nearest pixels a correspondence). Started at the
truth, any error is the refinement's own bias. Prints per distance bucket the median error along the baseline (the
line from the ego sensor to the peer's; positive: the peer pulled towards the ego car), the median across it, and the
share still within 1 m & 1 deg; ``--plot`` draws the along-baseline error against distance.
"""

from __future__ import annotations

import argparse
import math
from multiprocessing import get_context

import numpy as np
from tqdm import tqdm

from bb_align.engine.config import AlignConfig, BevConfig
from bb_align.engine.geometry import se2, se2_params
from bb_align.engine.pipeline import Aligner
from bb_align.engine.refine import bev_samples, peer_normals, refine_icp
from bb_align.io.dataset import iter_frames

BUCKETS = [(0, 20), (20, 40), (40, 55), (55, 70), (70, 85), (85, 101)]
_state: dict = {}


def _init(range_m: float, cos: list[float]) -> None:
    from bb_align.lab.evaluation.runner import EvalConfig

    cfg = AlignConfig(bev=BevConfig(range_m=range_m))
    _state.update(aligner=Aligner(cfg), eval=EvalConfig(align=cfg), cos=cos)


def _run(job) -> list[dict]:
    """One ego frame with the peers of ``job`` (group, peer frames): the errors of the refinement from the truth."""
    from bb_align.lab.evaluation.runner import _load_agent

    group, peers = job
    al, ev = _state["aligner"], _state["eval"]
    rf, seed = al.config.refine, al.config.seed
    ego = _load_agent(group.ego, al, ev, group.scenario, group.timestamp).prepared
    cloud = ego.cloud(rf)
    out = []
    for pf in peers:
        peer = _load_agent(pf, al, ev, group.scenario, group.timestamp).prepared
        yaw, x, y = se2_params(np.linalg.inv(group.ego.T_world_sensor) @ pf.T_world_sensor)
        T_true = se2(yaw, x, y)
        pts = bev_samples(peer.bev, rf.min_pixel_value, [rf.max_peer_points], seed)[0]
        normals = peer_normals(peer.bev, pts, rf)
        u = np.array([x, y]) / max(math.hypot(x, y), 1e-9)  # the baseline's direction, ego frame
        row = {"scenario": group.scenario, "peer": pf.agent, "distance_m": math.hypot(x, y)}
        for c in _state["cos"]:
            cfg = rf.model_copy(update={"facing_min_cos": c})
            T = refine_icp(cloud, pts, T_true, cfg, None if c <= -1 else normals).T
            y_r, x_r, z_r = se2_params(T)
            e = np.array([x - x_r, y - z_r])  # truth - estimate
            dyaw = math.degrees((yaw - y_r + math.pi) % (2 * math.pi) - math.pi)
            row[str(c)] = (float(e @ u), float(e @ np.array([-u[1], u[0]])), dyaw)
        out.append(row)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--cos", default="-1,0,0.5", help="facing_min_cos values, e.g. --cos=-1,0,0.5 (-1: the test off)")
    ap.add_argument("--min-distance", type=float, default=40.0)
    ap.add_argument("--range", dest="range_m", type=float, default=100.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--plot", default=None)
    args = ap.parse_args()
    cos = [float(c) for c in args.cos.split(",")]

    jobs = []
    for root in args.roots:
        for group in iter_frames(root):
            peers = []
            for pf in group.peers:
                _, x, y = se2_params(np.linalg.inv(group.ego.T_world_sensor) @ pf.T_world_sensor)
                if math.hypot(x, y) >= args.min_distance:
                    peers.append(pf)
            if peers:
                jobs.append((group, peers))
    with get_context("spawn").Pool(args.workers, initializer=_init, initargs=(args.range_m, cos)) as pool:
        rows = [r for out in tqdm(pool.imap(_run, jobs), total=len(jobs), desc="pairs") for r in out]

    print(
        f"{len(rows)} pairs from {len(args.roots)} set(s), refined from the true pose; along: + = towards the ego car"
    )
    print("| distance | pairs | facing_min_cos | along, median | across, median abs | within 1 m & 1 deg |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for lo, hi in BUCKETS:
        sel = [r for r in rows if lo <= r["distance_m"] < hi]
        for c in cos:
            if not sel:
                continue
            e = np.array([r[str(c)] for r in sel])
            ok = (np.hypot(e[:, 0], e[:, 1]) < 1.0) & (np.abs(e[:, 2]) < 1.0)
            label = "off" if c <= -1 else f"{c:g}"
            print(
                f"| {lo}-{min(hi, 100)} m | {len(sel)} | {label} | {np.median(e[:, 0]):+.2f} m "
                f"| {np.median(np.abs(e[:, 1])):.2f} m | {100 * ok.mean():.0f} % |"
            )
    if args.plot:
        _plot(rows, cos, args.plot)
        print(f"plot: {args.plot}")


def _plot(rows: list[dict], cos: list[float], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = np.array([r["distance_m"] for r in rows])
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for c, colour in zip(cos, ["tab:red", "tab:orange", "tab:blue", "tab:green"], strict=False):
        along = np.array([r[str(c)][0] for r in rows])
        label = "facing test off" if c <= -1 else f"facing_min_cos {c:g}"
        ax.scatter(d, along, s=9, alpha=0.45, color=colour, label=label)
        mids, meds = [], []
        for lo, hi in BUCKETS:
            m = (d >= lo) & (d < hi)
            if m.sum() >= 3:
                mids.append(0.5 * (lo + min(hi, 100)))
                meds.append(np.median(along[m]))
        ax.plot(mids, meds, color=colour, lw=2)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_ylim(-1.5, 2.5)
    ax.set_xlabel("distance between the cars (m)")
    ax.set_ylabel("error along the baseline (m); + = towards the ego car")
    ax.set_title("Dense refinement started at the true pose (lines: medians by distance)")
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
