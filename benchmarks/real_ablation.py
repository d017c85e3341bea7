"""What the engine needs on the real far street: the KITTI 00 pairs (73-80 m) with one kind of structure taken out
of both scans, aligned with and without the seeded 2 m / 2 deg prior.

    .venv/bin/python benchmarks/real_ablation.py --data ../shared/data

Each scan's lit BV pixels are classed as alias_anatomy.py classes keypoints (low: under 2.3 m above the local
ground; wall: a tall straight line; tall: other tall things, i.e. trees, poles, building corners), and the points
within 0.6 m of the chosen class's pixels are removed. ``random`` removes pixels drawn at random (seeded by the
scan) until about as many points go as ``tall`` takes: the control, since any removal takes information away. Writes
docs/real_pairs/ablation.md and .json.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from bb_align import AlignConfig, Aligner
from bb_align.engine.bev import make_bev
from bb_align.io.clouds import load_cloud
from bb_align.lab.realpairs import kitti00_far, score, seeded_prior
from bb_align.lab.recording import RECORD_HELP, output_path

MODES = ("none", "wall", "tall", "random")
RADIUS_M = 0.6  # points this close to a removed pixel's centre go with it (a 0.4 m pixel and its neighbours' edges)


@functools.cache  # once per worker process
def _classify():
    path = Path(__file__).resolve().with_name("alias_anatomy.py")
    spec = importlib.util.spec_from_file_location("bench_alias_anatomy_for_ablation", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.classify


def ablate(points: np.ndarray, mode: str, classify) -> np.ndarray:
    """The scan without the points near its ``mode`` pixels (module doc)."""
    if mode == "none":
        return points
    bev = make_bev(points)
    xy = bev.pixel_to_metre(np.argwhere(bev.image > 0))
    classes = classify(np.asarray(points)[:, :3], xy)
    xy_pts = np.asarray(points)[:, :2]
    if mode == "random":  # random pixels until as many points go as the tall things take
        tall = xy[classes == "tall"]
        n_target = int((cKDTree(tall).query(xy_pts)[0] <= RADIUS_M).sum()) if len(tall) else 0
        order = np.random.default_rng(len(points)).permutation(len(xy))

        def removed(k: int) -> int:
            return int((cKDTree(xy[order[:k]]).query(xy_pts)[0] <= RADIUS_M).sum()) if k else 0

        lo, hi = 0, len(xy)  # the fewest pixels that take n_target points (removed(k) grows with k)
        while lo < hi:
            mid = (lo + hi) // 2
            lo, hi = (mid + 1, hi) if removed(mid) < n_target else (lo, mid)
        drop = xy[order[:lo]]
    else:
        drop = xy[classes == mode]
    if not len(drop):
        return points
    d, _ = cKDTree(drop).query(xy_pts)
    return points[d > RADIUS_M]


@functools.cache  # once per worker process
def _aligner() -> Aligner:
    return Aligner(AlignConfig())


def _run(job: tuple[str, object]) -> dict:
    mode, pair = job
    classify, aligner = _classify(), _aligner()
    pts_ego, pts_peer = (ablate(load_cloud(p), mode, classify) for p in (pair.ego, pair.peer))
    ego, peer = aligner.prepare(pts_ego), aligner.prepare(pts_peer)
    plain, prior = aligner.align(ego, peer), aligner.align(ego, peer, T_prior=seeded_prior(pair))
    return {
        "mode": mode,
        "pair": pair.name,
        "kept_ego": len(pts_ego),
        "kept_peer": len(pts_peer),
        "no_prior": score(pair, plain, False).__dict__,
        "prior": score(pair, prior, True).__dict__,
    }


def table(rows: list[dict]) -> str:
    lines = [
        "# The real far street with one kind of structure taken out",
        "",
        "Made by `python benchmarks/real_ablation.py --data ../shared/data`. KITTI 00, 20 pairs 73-80 m; right /",
        "wrong / refused as `bb-align real-pairs` scores them (right: within 1 m and 1 deg of the reference); covered:",
        "the wrong answers within their 3 sigma.",
        "",
        "| removed | points kept (median) | no prior | with the prior | wrong answers covered |",
        "| --- | ---: | --- | --- | --- |",
    ]
    for mode in MODES:
        rs = [r for r in rows if r["mode"] == mode]
        outcome = {
            k: " / ".join(str(sum(r[k]["outcome"] == o for r in rs)) for o in ("right", "wrong", "refused"))
            for k in ("no_prior", "prior")
        }
        wrong = [r[k] for r in rs for k in ("no_prior", "prior") if r[k]["outcome"] == "wrong"]
        kept = np.median([r["kept_peer"] for r in rs])
        lines.append(
            f"| {mode} | {kept:.0f} | {outcome['no_prior']} | {outcome['prior']} | "
            f"{sum(bool(w['covered']) for w in wrong)} / {len(wrong)} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="default: out/real_pairs/ablation (docs/real_pairs/ablation with --record)",
    )
    ap.add_argument("--record", action="store_true", help=RECORD_HELP)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    args.out = args.out or output_path("docs/real_pairs/ablation", args.record)
    pairs = kitti00_far(args.data)
    jobs = [(mode, pair) for mode in MODES for pair in pairs]
    from tqdm import tqdm

    with Pool(args.workers) as pool:
        rows = list(tqdm(pool.imap(_run, jobs), total=len(jobs), desc="ablation"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1, default=float) + "\n")
    args.out.with_suffix(".md").write_text(table(rows))
    print(table(rows))


if __name__ == "__main__":
    main()
