"""Figures of a tracking replay: per sequence, the answer's error and its 3-sigma bound over time; overall, the
fraction under 1 m & 1 deg by distance."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bb_align.io.plot import pyplot


def plot_sequence(records: list[dict], path: str | Path) -> None:
    """Yaw, x and y error of every answered frame with the answer's +-3 sigma, and the distance between the cars."""
    plt = pyplot()
    t = np.array([r["stamp"] - records[0]["stamp"] for r in records])
    ok = np.array([r["success"] for r in records])
    acq = np.array([r["ran_acquisition"] for r in records])
    err = np.array([r["err"] for r in records])
    sig = np.array([r["sigma"] if r["sigma"] is not None else [np.nan] * 3 for r in records], dtype=float)
    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    scale = (np.degrees(1.0), 1.0, 1.0)
    for i, (ax, name) in enumerate(zip(axes, ("yaw error [deg]", "x error [m]", "y error [m]"))):
        e, s = err[:, i] * scale[i], 3 * sig[:, i] * scale[i]
        ax.fill_between(t, np.where(ok, -s, np.nan), np.where(ok, s, np.nan), color="tab:blue", alpha=0.2, lw=0)
        ax.plot(t[ok], e[ok], ".", ms=3, color="tab:blue", label="answered (valid)")
        ax.plot(t[~ok], np.clip(e[~ok], -5, 5), "x", ms=3, color="tab:gray", label="not valid (clipped to 5)")
        ax.axhline(1.0, color="tab:red", lw=0.6, ls="--")
        ax.axhline(-1.0, color="tab:red", lw=0.6, ls="--")
        lim = max(1.5, float(np.nanpercentile(np.abs(np.where(ok, s, np.nan)), 95)) if ok.any() else 1.5)
        ax.set_ylim(-min(lim, 5), min(lim, 5))
        ax.set_ylabel(name)
    axes[0].legend(loc="upper right", fontsize=7)
    axes[3].plot(t, [r["distance_m"] for r in records], color="k", lw=1)
    axes[3].plot(
        t[acq],
        np.array([r["distance_m"] for r in records])[acq],
        "v",
        color="tab:orange",
        ms=4,
        label="full acquisition ran",
    )
    axes[3].set_ylabel("distance [m]")
    axes[3].set_xlabel("time [s]")
    axes[3].legend(loc="upper right", fontsize=7)
    axes[0].set_title(
        f"{records[0]['sequence']}: error and 3-sigma band (shaded) of each valid answer; red: 1 m / 1 deg"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_by_distance(summary: dict, path: str | Path) -> None:
    plt = pyplot()
    keys = list(summary["by_distance"])
    good = [100 * (summary["by_distance"][k]["frac_under_1m_1deg"] or 0) for k in keys]
    answered = [100 * (summary["by_distance"][k]["frac_answered"] or 0) for k in keys]
    x = np.arange(len(keys))
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.bar(x - 0.2, answered, 0.4, label="answered as valid", color="tab:gray")
    ax.bar(x + 0.2, good, 0.4, label="under 1 m & 1 deg", color="tab:blue")
    ax.set_xticks(x, [f"{k} m\n({summary['by_distance'][k]['frames']})" for k in keys])
    ax.set_ylabel("% of frames after the first answer")
    ax.set_ylim(0, 105)
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title(f"tracking: {summary['sequences']} sequences, wrong {100 * (summary['wrong_frames_frac'] or 0):.2f} %")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
