"""The service under rising load: total results per second, per-peer share and latency with 4, 8 and 16 peers.

    PYTHONPATH=service:client .venv/bin/python benchmarks/service_load.py --peers 4,8,16 --seconds 15 \
        --warmup 8 --json docs/performance_load.json --plot docs/performance_load.png \
        --compare before=docs/performance_load_before.json

Each peer count runs in a fresh service process (Ed25519 off: the fleet HMAC key; tracking on, odometry sent, the
defaults of ``bb-align bench``'s service part, bb_align.lab.bench.throughput): the ego and N simulated peers 10-40
m away publish signed frames at 10 Hz over Zenoh on loopback for the warm-up and the measured window. Recorded
per run: results per second in total and per peer (the fairness: the least-served peer's share), frames dropped,
outcomes (acquisitions vs tracked frames), latency publish -> result (p50/p99) and the service's cores.
``--stagger``: each peer publishes at its own phase of the 100 ms period, spread evenly (LiDARs not synchronised
to a common clock); by default every car's frame goes out at the same instant (phase-locked LiDARs: each sweep's
frames arrive as one burst). ``--compare OLD.json`` draws a recorded earlier run beside this one (e.g. the code
before a change, run with its tree on PYTHONPATH). The machine may be shared: the JSON records the load average
before and after each run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path


def _load_avg() -> float:
    return os.getloadavg()[0]


def measure(peers: list[int], seconds: float, workers: int, warmup_s: float = 2.0, stagger: bool = False) -> dict:
    from bb_align.engine.config import AlignConfig
    from bb_align.lab.bench.throughput import ServiceBenchConfig, measure_service

    cfg = ServiceBenchConfig(peer_counts=peers, seconds=seconds, workers=workers, warmup_s=warmup_s, stagger=stagger)
    load_before = _load_avg()
    t0 = time.time()
    report = measure_service(cfg, AlignConfig())
    report["load_average"] = {"before": load_before, "after": _load_avg()}
    report["wall_s"] = time.time() - t0
    return report


def per_peer(run: dict) -> dict:
    """The least and most results per second any one peer got (fairness), from the run's outcomes per peer."""
    shares = run.get("per_peer_results_fps") or {}
    if not shares:
        return {}
    return {"min": min(shares.values()), "max": max(shares.values())}


def plot(reports: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    for label, rep in reports.items():
        runs = sorted(rep["runs"].values(), key=lambda r: r["peers"])
        n = [r["peers"] for r in runs]
        line = ax1.plot(n, [r["results_fps"] for r in runs], "o-", label=label)[0]
        if all("measured_fps" in r for r in runs):  # answered from a measurement of their own (the rest: the stream)
            ax1.plot(n, [r["measured_fps"] for r in runs], "x--", color=line.get_color(), label=f"{label}, measured")
        ax2.plot(n, [r["latency_ms"]["p99"] for r in runs], "o-", color=line.get_color(), label=f"{label} p99")
        ax2.plot(n, [r["latency_ms"]["p50"] for r in runs], "x--", color=line.get_color(), label=f"{label} p50")
    ax1.set_xlabel("peers at 10 Hz")
    ax1.set_ylabel("results per second (all peers)")
    ax1.set_ylim(bottom=0)
    ax2.set_xlabel("peers at 10 Hz")
    ax2.set_ylabel("latency publish -> result (ms)")
    ax2.set_yscale("log")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("bb-align service under load (2-core VM; the load average is in each JSON)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--peers", default="4,8,16")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--warmup", type=float, default=2.0, help="seconds of publishing before the window")
    ap.add_argument(
        "--stagger",
        action="store_true",
        help="each peer publishes at its own phase of the period (LiDARs not synchronised); default: all at once",
    )
    ap.add_argument("--label", default="now")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--compare", action="append", default=[], help="LABEL=FILE.json of an earlier run (repeatable)")
    ap.add_argument("--replot", action="store_true", help="measure nothing: plot the recorded --json again")
    args = ap.parse_args(argv)
    try:
        peers = sorted({int(p) for p in args.peers.split(",") if p.strip()})
    except ValueError:
        print(f"service_load: --peers: not comma-separated integers: {args.peers!r}", file=sys.stderr)
        return 2
    if args.replot and args.json is None:
        print("service_load: --replot: needs --json FILE", file=sys.stderr)
        return 2
    if args.replot:  # no measurement: draw the recorded --json (and --compare) again
        report = json.loads(args.json.read_text())
    else:
        report = measure(peers, args.seconds, args.workers, args.warmup, args.stagger)
        report["label"] = args.label
        report["command"] = "benchmarks/service_load.py " + " ".join(argv if argv is not None else sys.argv[1:])
    for n, run in sorted(report["runs"].items(), key=lambda kv: int(kv[0])):
        lat = run["latency_ms"]
        print(
            f"{n:>3} peers: {run['results_fps']:6.1f} results/s ({run.get('measured_fps', float('nan')):.1f} "
            f"measured), dropped {run['drop_fraction']:.0%}, p50 {lat['p50']:.0f} ms, p99 {lat['p99']:.0f} ms, "
            f"per peer {per_peer(run)}, {run['outcomes']}, sources {run.get('sources')}, wrong {run.get('wrong')}"
        )
    if args.json is not None and not args.replot:
        args.json.write_text(json.dumps(report, indent=1, default=float))
    if args.plot is not None:
        reports = {}
        for spec in args.compare:
            label, _, file = str(spec).partition("=")
            reports[label] = json.loads(Path(file).read_text())
        reports[args.label if args.replot else report["label"]] = report
        plot(reports, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
