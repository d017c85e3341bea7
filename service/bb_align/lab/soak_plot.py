"""The soak's figure: results per second and drops per second through the phases (matplotlib PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _rates(samples: list[dict], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(mid times, per-second rate) of a cumulative counter sampled over time."""
    t = np.array([s["t"] for s in samples])
    v = np.array([s[key] for s in samples])
    if len(t) < 2:
        return np.zeros(0), np.zeros(0)
    return (t[1:] + t[:-1]) / 2, np.diff(v) / np.diff(t)


def plot_soak(report: dict, path: Path) -> None:
    from bb_align.io.plot import pyplot

    plt = pyplot()

    tl = report["timeline"]
    samples, arrivals = tl["samples"], np.array(tl["results"])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(11, 6.5), sharex=True)
    end = max([s["t"] for s in samples] + [0.0])
    if len(arrivals):
        bins = np.arange(0.0, end + 1.0, 1.0)
        counts, edges = np.histogram(arrivals, bins)
        ax1.plot((edges[1:] + edges[:-1]) / 2, counts, lw=1.0, label="results received / s")
    t, admitted = _rates(samples, "admitted")
    ax1.plot(t, admitted, lw=1.0, alpha=0.7, label="authenticated frames admitted / s")
    ax1.set_ylabel("per second")
    ax1.legend(fontsize=8, loc="upper left")
    for key, label in (
        ("rejected", "refused (at the door or the gate) / s"),
        ("lane_unverified", "intake drops, unverified lane / s"),
        ("lane_signed", "intake drops, signed lane / s"),
        ("lane_ego", "intake drops, ego lane / s"),
        ("queue_dropped", "latest-only queue drops / s"),
    ):
        t, r = _rates(samples, key)
        if len(r) and r.max() > 0:
            ax2.plot(t, np.maximum(r, 0.5), lw=1.0, label=label)  # zero shows at the floor of the log axis
    lanes = [k for k in ("lane_ego", "lane_signed", "lane_unverified") if samples and samples[-1][k] > 0]
    if samples and not lanes:
        ax2.plot([], [], " ", label="intake lane drops: none")
    ax2.set_yscale("log")
    ax2.set_ylim(bottom=0.5)
    ax2.set_ylabel("per second (log)")
    ax2.set_xlabel("seconds since the cars started")
    ax2.legend(fontsize=8, loc="upper left")
    for i, (name, a, b) in enumerate(tl["phases"]):
        for ax in (ax1, ax2):
            ax.axvspan(a, b, color=f"C{i % 10}", alpha=0.08)
        label = "warm-up + attacks" if name == "attacks" else name
        ax1.text((a + b) / 2, 1.01, label, transform=ax1.get_xaxis_transform(), ha="center", fontsize=8)
    flood = report.get("phases", {}).get("flood", {}).get("flooder")
    title = "bb-align soak: results and drops through the phases"
    if flood:
        title += f" (keyless flood: {flood['msg_per_s']:.0f} msg/s, {flood['mb_per_s']:.0f} MB/s)"
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
