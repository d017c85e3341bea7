"""The benchmark's figure: p50 stage times of engine and baseline per path (log scale), and the service's
latency and throughput when it was measured."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .run import COLD, HOT

_TITLES = {HOT: "peer frame vs cached ego frame", COLD: "cold pair (both frames prepared)"}


def peers_curve(ax, service: dict) -> None:
    """Peers vs throughput on ``ax``: frames offered, results and successful results per second against the
    number of peers (a curve over the measured counts), latency p50/p99 on a second axis."""
    runs = service["runs"]
    peers = sorted(runs, key=int)
    x = [int(p) for p in peers]
    ax.plot(x, [runs[p]["offered_fps"] for p in peers], "o:", color="#7f7f7f", label="peer frames offered /s")
    ax.plot(x, [runs[p]["results_fps"] for p in peers], "o-", color="#98df8a", label="results /s")
    good = [runs[p]["results_fps"] * runs[p]["success_fraction"] for p in peers]
    ax.plot(x, good, "o-", color="#2ca02c", label="successful results /s")
    ax.set_xticks(x, [str(p) for p in x])
    ax.set_xlabel("peers")
    ax.set_ylabel("frames per second")
    ax.set_ylim(bottom=0)
    ax2 = ax.twinx()
    ax2.plot(x, [runs[p]["latency_ms"]["p50"] for p in peers], "^-", color="#d62728", label="latency p50")
    ax2.plot(x, [runs[p]["latency_ms"]["p99"] for p in peers], "s--", color="#d62728", label="latency p99")
    ax2.set_ylabel("publish -> pose received (ms)")
    ax2.set_ylim(bottom=0)
    lines, lines2 = ax.get_legend_handles_labels(), ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], fontsize=7, loc="upper left")
    ax.grid(alpha=0.3)
    ax.set_title(f"service over Zenoh: peers vs throughput, every car at {service.get('rate_hz', 10):g} Hz", fontsize=9)


def plot_report(report: dict, path: str | Path) -> Path:
    from bb_align.io.plot import pyplot

    plt = pyplot()

    service = report.get("service") or {}
    runs = service.get("runs") or {}
    n_panels = 2 + (1 if runs else 0)
    fig, axes = plt.subplots(1, n_panels, figsize=(6.2 * n_panels, 4.8))
    for ax, key in zip(axes, (HOT, COLD)):
        eng, base = report["stages"][key]["engine"], report["stages"][key]["baseline"]
        names = [k for k in eng if k in base and k != "total_cpu" and (eng[k]["p50"] > 0.005 or base[k]["p50"] > 0.005)]
        x = np.arange(len(names))
        e = [max(eng[k]["p50"], 1e-3) for k in names]
        b = [max(base[k]["p50"], 1e-3) for k in names]
        ax.bar(x - 0.2, b, 0.4, label="baseline", color="#bbbbbb")
        ax.bar(x + 0.2, e, 0.4, label="engine", color="#1f77b4")
        for xi, k in zip(x, names):
            r = report["stages"][key]["speedup_p50"].get(k)
            if r:
                ax.text(xi, max(e[xi], b[xi]) * 1.3, f"{r:.0f}x" if r >= 10 else f"{r:.1f}x", ha="center", fontsize=7)
        ax.set_yscale("log")
        ax.set_xticks(x, names, rotation=40, ha="right", fontsize=8)
        ax.set_ylabel("p50 wall time per call (ms)")
        ax.set_title(
            f"{_TITLES[key]}\nengine {eng['total']['p50']:.1f} ms, baseline {base['total']['p50']:.0f} ms", fontsize=9
        )
        ax.grid(axis="y", alpha=0.3, which="both")
        ax.legend(fontsize=8)
    if runs:
        peers_curve(axes[-1], service)
    commit = (report.get("git") or {}).get("commit") or "?"
    load = report.get("load_avg", {}).get("start", [float("nan")])[0]
    fig.suptitle(
        f"bb-align bench  ({report['workload']['pairs']} pairs, {report['runs']} runs, "
        f"commit {commit[:10]}, load {load:.2f})",
        fontsize=10,
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
