"""The free-space conflict (engine/freespace.py) of acquired poses against the truth, from the records of
``benchmarks/acquisition_range.py --records``: how the conflict of right poses compares with that of gross aliases,
and what the bound (``free_space.max_conflict``) refuses. Reproduces docs/acquisition.md, "Session 13".

    PYTHONPATH=service:client .venv/bin/python benchmarks/acquisition_range.py DIR --range 100 --variants multi \\
        --records R.jsonl
    PYTHONPATH=service:client .venv/bin/python benchmarks/free_space_study.py R1.jsonl [R2.jsonl ...] \\
        --plot docs/acquisition/fig_free_space.png

A hypothesis is *right* within 1 m and 1 deg of the truth, *gross* beyond 5 m or 5 deg. The engine measures the
conflict of the best hypothesis and of its runner-up (the distinct pose the margin is taken over).
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np


def _error(h: dict, truth: list[float]) -> tuple[float, float]:
    yaw = (h["yaw_deg"] - math.degrees(truth[0]) + 180.0) % 360.0 - 180.0
    return math.hypot(h["tx"] - truth[1], h["ty"] - truth[2]), abs(yaw)


def classes(rows: list[dict]) -> dict[str, list[tuple[float, dict]]]:
    """Conflicts by class: right best accepted, right best refused, gross best (accepted or not), gross runner-up."""
    out: dict[str, list[tuple[float, dict]]] = {
        k: [] for k in ("right, accepted", "right, refused", "gross best", "gross runner-up")
    }
    for r in rows:
        a = r.get("acquisition")
        if not a or not a.get("best"):
            continue
        t, y = _error(a["best"], r["truth"])
        c = a["best"]["conflict"]
        if t < 1 and y < 1:
            out["right, accepted" if r["success"] else "right, refused"].append((c, r))
        elif t > 5 or y > 5:
            out["gross best"].append((c, r))
        ru = a.get("runner_up")
        if ru is not None:
            t, y = _error(ru, r["truth"])
            if t > 5 or y > 5:
                out["gross runner-up"].append((ru["conflict"], r))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("records", nargs="+")
    ap.add_argument("--bound", type=float, default=0.15, help="free_space.max_conflict to report against")
    ap.add_argument("--plot", default=None, help="write the histogram PNG here")
    args = ap.parse_args()
    rows = [json.loads(line) for f in args.records for line in open(f) if line.strip()]
    groups = classes(rows)
    print(f"{len(rows)} pairs from {len(args.records)} record files; bound {args.bound}")
    print("| class | n | median | p90 | p99 | max | above the bound |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name, items in groups.items():
        c = np.array([x for x, _ in items])
        if len(c) == 0:
            print(f"| {name} | 0 | | | | | |")
            continue
        p = np.percentile(c, [50, 90, 99])
        print(
            f"| {name} | {len(c)} | {p[0]:.3f} | {p[1]:.3f} | {p[2]:.3f} | {c.max():.3f} | {(c > args.bound).sum()} |"
        )
    refused = [r for r in rows if r.get("reason") == "free_space_conflict"]
    print(f"refused as free_space_conflict: {len(refused)}")
    for r in refused:
        t, y = _error(r["acquisition"]["best"], r["truth"])
        print(
            f"  {r['scenario']} peer {r['peer']}: {r['distance_m']:.0f} m apart, conflict "
            f"{r['acquisition']['best']['conflict']:.3f}, the refused pose {t:.1f} m / {y:.1f} deg off"
        )
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(8, 4.5))
        bins = np.linspace(0, max(0.5, max((x for g in groups.values() for x, _ in g), default=0.5)), 41)
        for name, items in groups.items():
            if items:
                ax.hist([x for x, _ in items], bins=bins, histtype="step", lw=1.6, label=f"{name} ({len(items)})")
        ax.axvline(args.bound, color="k", ls="--", lw=1, label=f"bound {args.bound}")
        ax.set_yscale("log")
        ax.set_xlabel("free-space conflict (share of tall structure landing where the other car saw through)")
        ax.set_ylabel("hypotheses")
        ax.set_title("Free-space conflict of acquired poses vs the truth")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)
        print(f"plot: {args.plot}")


if __name__ == "__main__":
    main()
