"""Before / after of `bb-align recover` on simulated data: the README's "Use it on your dataset" numbers.

    .venv/bin/bb-align sim /tmp/rec_demo/sim --scenarios 20 --seed 5 --workers 2
    .venv/bin/bb-align recover /tmp/rec_demo/sim /tmp/rec_demo/out --pose-noise 2,2 --seed 1
    .venv/bin/python benchmarks/recover_demo.py /tmp/rec_demo/sim /tmp/rec_demo/out

The simulator writes the true poses; `--pose-noise 2,2` adds the paper's localisation noise (Gaussian, 2 m on x
and y, 2 deg on yaw) to every non-ego pose before recovery (the noisy pose is what the jsonl calls
T_ego_peer_reported, and what a failed frame keeps). This script reads the copy under OUT with the project's
reader and compares each non-ego agent's pose relative to the ego, before (noisy) and after (written), with the
truth under ROOT: the fraction of agent frames within 1 m and 1 deg, and the median errors.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bb_align.engine.geometry import pose_error
from bb_align.io.dataset import iter_frames
from bb_align.io.recover import JSONL_NAME
from bb_align.lab.evaluation.runner import DIST_BUCKETS


def compare(root: Path, out: Path, max_t_m: float = 1.0, max_r_deg: float = 1.0) -> dict:
    truth = {(g.scenario, g.timestamp): g for g in iter_frames(root)}
    written = {(g.scenario, g.timestamp): g for g in iter_frames(out)}
    before, after, ok, dist = [], [], [], []
    for line in (out / JSONL_NAME).read_text().splitlines():
        row = json.loads(line)
        key = (row["scenario"], row["timestamp"])
        t, w = truth[key], written[key]
        T_true = np.linalg.inv(t.ego.T_world_sensor) @ t.agents[row["agent"]].T_world_sensor
        T_written = np.linalg.inv(w.ego.T_world_sensor) @ w.agents[row["agent"]].T_world_sensor
        before.append(pose_error(np.asarray(row["T_ego_peer_reported"]), T_true))
        after.append(pose_error(T_written, T_true))
        ok.append(row["success"])
        dist.append(float(np.hypot(*T_true[:2, 3])))
    b, a, d = np.array(before), np.array(after), np.array(dist)

    def frac(e, sel=None):
        sel = np.ones(len(e), bool) if sel is None else sel
        return float(np.mean((e[sel, 0] < max_t_m) & (e[sel, 1] < max_r_deg))) if sel.any() else None

    return {
        "agent_frames": len(a),
        "recovered": int(np.sum(ok)),
        f"before_frac_under_{max_t_m:g}m_{max_r_deg:g}deg": frac(b),
        f"after_frac_under_{max_t_m:g}m_{max_r_deg:g}deg": frac(a),
        "before_median_t_m": float(np.median(b[:, 0])),
        "before_median_r_deg": float(np.median(b[:, 1])),
        "after_median_t_m": float(np.median(a[:, 0])),
        "after_median_r_deg": float(np.median(a[:, 1])),
        "by_distance": {
            name: {
                "agent_frames": int(((d >= lo) & (d < hi)).sum()),
                "before": frac(b, (d >= lo) & (d < hi)),
                "after": frac(a, (d >= lo) & (d < hi)),
            }
            for name, (lo, hi) in DIST_BUCKETS.items()
        },
        "recovered_but_over_limit": int(np.sum(np.array(ok) & ~((a[:, 0] < max_t_m) & (a[:, 1] < max_r_deg)))),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, help="the dataset with true poses (what `bb-align sim` wrote)")
    ap.add_argument("out", type=Path, help="the output of `bb-align recover ROOT OUT --pose-noise ...`")
    ap.add_argument("--max-t", type=float, default=1.0, help="translation limit, metres")
    ap.add_argument("--max-r", type=float, default=1.0, help="yaw limit, degrees")
    args = ap.parse_args()
    print(json.dumps(compare(args.root, args.out, args.max_t, args.max_r), indent=1))


if __name__ == "__main__":
    main()
