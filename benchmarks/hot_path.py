"""Quick hot-path timing used for each speed step of issue 5 (docs/performance.md, "What was done for speed").

    .venv/bin/python benchmarks/hot_path.py [--set mim.coarse_scales=0 ...]

Three seeded simulated pairs (20, 30 and 45 m apart); per pair the ego frame is prepared and warmed once (the
service's cache), then 12 times: peer PNG bytes -> decode -> Aligner.prepare -> Aligner.align. Prints the median
and p90 of the wall time (the first 3 runs dropped) and the median of each engine stage. About 10 s on 2 cores;
`bb-align bench` is the full, recorded benchmark.

    .venv/bin/python benchmarks/hot_path.py --against /path/to/old/checkout --rounds 3

runs this script in child processes, alternating the other checkout's code (its service/ and client/ on
PYTHONPATH) with this one's, ``--rounds`` times each: on a machine shared with other jobs, old and new then see the
same load in turn. Prints each run and the median of each side's p50s.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

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
    ap.add_argument("--against", type=Path, default=None, help="another checkout: alternate its code with this one's")
    ap.add_argument("--rounds", type=int, default=3, help="with --against: runs of each side")
    ap.add_argument("--json-line", action="store_true", help="print one JSON line (p50, p90, stages) at the end")
    args = ap.parse_args()
    if args.against is not None:
        return alternate(args)
    cfg = with_overrides(AlignConfig(), args.set)
    if args.range_m is not None:
        cfg = cfg.model_copy(update={"bev": BevConfig(range_m=args.range_m)})
    if args.mode is not None:
        cfg = cfg.model_copy(update={"acquire": cfg.acquire.model_copy(update={"mode": args.mode})})
    aligner = Aligner(cfg)
    aligner.warm_up()
    rows: list[tuple[float, dict[str, float]]] = []
    cpu: list[float] = []  # process CPU time of each call (both engine threads): steadier than wall on a busy box
    for seed, distance_m in [(3, 30.0), (5, 20.0), (7, 45.0)]:
        frame = simulate_sequence(seed, 1, 2, distance_m)[0]
        ego_car, peer_car = frame.agents["0"], frame.agents["1"]
        ego = aligner.warm(aligner.prepare(make_bev(ego_car.points, cfg.bev), ego_car.boxes))
        bev_peer = make_bev(peer_car.points, cfg.bev)
        png = bev_peer.to_png()
        for _ in range(12):
            t0, c0 = time.perf_counter(), time.process_time()
            peer = aligner.prepare(BevImage.from_png(png, **bev_peer.meta()), peer_car.boxes)
            result = aligner.align(ego, peer)
            rows.append(((time.perf_counter() - t0) * 1e3, {**peer.timings_ms, **result.timings_ms}))
            cpu.append((time.process_time() - c0) * 1e3)
    wall = [ms for ms, _ in rows[3:]]
    stages = {k: round(float(np.median([t.get(k, 0.0) for _, t in rows[3:]])), 1) for k in rows[0][1]}
    print(f"range {cfg.bev.range_m} m, acquire {cfg.acquire.mode}, overrides {args.set}:", end=" ")
    cpu_p50 = float(np.median(cpu[3:]))
    print(
        f"hot path p50 {np.median(wall):.1f} ms, p90 {np.percentile(wall, 90):.1f} ms, CPU p50 {cpu_p50:.1f} ms; "
        f"stages p50 ms {stages}"
    )
    if args.json_line:
        row = {"p50": float(np.median(wall)), "p90": float(np.percentile(wall, 90)), "cpu_p50": cpu_p50}
        print(json.dumps({**row, "stages": stages}))


def alternate(args) -> None:
    """Old and new code in turn (child processes), ``args.rounds`` times each; the medians of their p50s."""
    here = Path(__file__).resolve().parents[1]
    sides = {"old": args.against.resolve(), "new": here}
    passed = [a for s in args.set for a in ("--set", s)]
    passed += [] if args.range_m is None else ["--range", str(args.range_m)]
    passed += [] if args.mode is None else ["--mode", args.mode]
    p50s: dict[str, list[float]] = {k: [] for k in sides}
    cpus: dict[str, list[float]] = {k: [] for k in sides}
    print(f"load average at the start {os.getloadavg()[0]:.1f}")
    for r in range(args.rounds):
        for label, root in sides.items():
            env = {**os.environ, "PYTHONPATH": f"{root / 'service'}:{root / 'client'}"}
            out = (
                subprocess.run(
                    [sys.executable, str(Path(__file__).resolve()), "--json-line", *passed],
                    env=env,
                    capture_output=True,
                    text=True,
                    check=True,
                )
                .stdout.strip()
                .splitlines()
            )
            row = json.loads(out[-1])
            p50s[label].append(row["p50"])
            cpus[label].append(row.get("cpu_p50", float("nan")))
            print(f"round {r + 1} {label} ({root}): {out[-2]}", flush=True)
    print(f"load average at the end {os.getloadavg()[0]:.1f}")
    old, new = np.median(p50s["old"]), np.median(p50s["new"])
    print(f"hot path p50, median of {args.rounds} runs each: old {old:.1f} ms, new {new:.1f} ms ({new / old:.2f}x)")
    old_cpu, new_cpu = np.median(cpus["old"]), np.median(cpus["new"])
    print(
        f"hot path CPU p50, median of the runs: old {old_cpu:.1f} ms, new {new_cpu:.1f} ms ({new_cpu / old_cpu:.2f}x)"
    )


if __name__ == "__main__":
    main()
