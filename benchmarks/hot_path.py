"""Quick hot-path timing used for each speed step of issue 5 (docs/performance.md, "What was done for speed").

    .venv/bin/python benchmarks/hot_path.py [--set mim.coarse_scales=0 ...]

Three seeded simulated pairs (20, 30 and 45 m apart); per pair the ego frame is prepared and warmed once (the
service's cache), then 12 times: peer PNG bytes -> decode -> Aligner.prepare -> Aligner.align. Prints the median
and p90 of the wall time (the first 3 runs dropped) and the median of each engine stage. About 10 s on 2 cores;
`bb-align bench` is the full, recorded benchmark.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bb_align import AlignConfig, Aligner, make_bev
from bb_align.engine.bev import BevImage
from bb_align.engine.config import BevConfig, with_overrides
from bb_align.lab.sim import simulate_sequence


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--range", type=float, default=None, dest="range_m", help="BV half width (default: config's)")
    ap.add_argument("--mode", choices=["paper", "multi"], default=None, help="acquire.mode (default: config's)")
    ap.add_argument("--set", action="append", default=[], help="section.key=JSON override, e.g. mim.coarse_scales=0")
    args = ap.parse_args()
    cfg = with_overrides(AlignConfig(), args.set)
    if args.range_m is not None:
        cfg = cfg.model_copy(update={"bev": BevConfig(range_m=args.range_m)})
    if args.mode is not None:
        cfg = cfg.model_copy(update={"acquire": cfg.acquire.model_copy(update={"mode": args.mode})})
    aligner = Aligner(cfg)
    aligner.warm_up()
    rows: list[tuple[float, dict[str, float]]] = []
    for seed, distance_m in [(3, 30.0), (5, 20.0), (7, 45.0)]:
        frame = simulate_sequence(seed, 1, 2, distance_m)[0]
        ego_car, peer_car = frame.agents["0"], frame.agents["1"]
        ego = aligner.warm(aligner.prepare(make_bev(ego_car.points, cfg.bev), ego_car.boxes))
        bev_peer = make_bev(peer_car.points, cfg.bev)
        png = bev_peer.to_png()
        for _ in range(12):
            t0 = time.perf_counter()
            peer = aligner.prepare(BevImage.from_png(png, **bev_peer.meta()), peer_car.boxes)
            result = aligner.align(ego, peer)
            rows.append(((time.perf_counter() - t0) * 1e3, {**peer.timings_ms, **result.timings_ms}))
    wall = [ms for ms, _ in rows[3:]]
    stages = {k: round(float(np.median([t.get(k, 0.0) for _, t in rows[3:]])), 1) for k in rows[0][1]}
    print(f"range {cfg.bev.range_m} m, acquire {cfg.acquire.mode}, overrides {args.set}:", end=" ")
    print(f"hot path p50 {np.median(wall):.1f} ms, p90 {np.percentile(wall, 90):.1f} ms; stages p50 ms {stages}")


if __name__ == "__main__":
    main()
