"""How well would the two cars' boxes alone place the peer at range? A diagnosis for tracking beyond 70 m.

Beyond 70 m the track's refinement is weak and biased along the street (docs/tracking.md). Box corners of the cars
both detected constrain that direction independently of the BV images. This measures, on swept sequences
(`bb-align sim OUT --sweep`), the box stage alone (`bb_align.engine.boxes.align_boxes`) started from a track-like
prediction (the true pose moved 0.7 m in a seeded random direction and 0.3 deg): how often at least two box pairs
exist, and the error of the box-aligned pose, by distance. No engine run, no tracker: a bound on what fusing box
corners as a second measurement could give.

    python benchmarks/track_boxes_at_range.py ROOT [--every 3] [--out docs/tracking/boxes_at_range.txt]
        [--plot docs/tracking/boxes_at_range.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bb_align.engine.boxes import align_boxes
from bb_align.engine.geometry import ground_se2, pose_error, se2
from bb_align.io.dataset import iter_scenario_frames
from bb_align.io.plot import pyplot

BUCKETS = {"20-40": (20.0, 40.0), "40-70": (40.0, 70.0), "70+": (70.0, np.inf)}


def measure(root: Path, every: int, start_m: float, start_deg: float, seed: int) -> np.ndarray:
    """Rows (distance, pairs, start error m, box-aligned error m, box-aligned error deg) per sampled frame."""
    rng = np.random.default_rng(seed)
    rows = []
    for seq in tqdm(sorted(p for p in root.iterdir() if p.is_dir()), desc="sequences"):
        for k, group in enumerate(iter_scenario_frames(seq.name, seq)):
            if k % every:
                continue
            ego, peer = group.ego, group.peers[0]
            T_true = ground_se2(np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor)
            a = rng.uniform(0, 2 * np.pi)
            T_start = se2(np.radians(rng.normal(0, start_deg)), start_m * np.cos(a), start_m * np.sin(a)) @ T_true
            boxes = align_boxes(ego.detections, peer.detections, T_start)
            t0, _ = pose_error(T_start, T_true)
            t1, r1 = pose_error(boxes.T_box @ T_start, T_true)
            rows.append((float(np.hypot(*T_true[:2, 2])), boxes.pairs, t0, t1, r1))
    return np.array(rows)


def report(rows: np.ndarray, header: str) -> str:
    lines = [
        header,
        "distance | frames | >= 2 box pairs | pairs p50 | box-aligned t err p50 / p90 m | < 0.3 m | yaw p50 deg",
    ]
    for name, (lo, hi) in BUCKETS.items():
        s = rows[(rows[:, 0] >= lo) & (rows[:, 0] < hi)]
        ok = s[s[:, 1] >= 2]
        if not len(ok):
            lines.append(f"{name:>8} | {len(s):6d} | none")
            continue
        lines.append(
            f"{name:>8} | {len(s):6d} | {np.mean(s[:, 1] >= 2):14.0%} | {np.median(s[:, 1]):9.0f} | "
            f"{np.median(ok[:, 3]):.2f} / {np.percentile(ok[:, 3], 90):.2f} | {np.mean(ok[:, 3] < 0.3):7.0%} | "
            f"{np.median(ok[:, 4]):.2f}"
        )
    return "\n".join(lines)


def plot(rows: np.ndarray, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, (lo, hi) in BUCKETS.items():
        s = rows[(rows[:, 0] >= lo) & (rows[:, 0] < hi) & (rows[:, 1] >= 2)]
        if len(s):
            v = np.sort(s[:, 3])
            ax.step(v, np.arange(1, len(v) + 1) / len(v), where="post", label=f"{name} m ({len(v)} frames)")
    ax.axvline(0.7, color="grey", ls=":", lw=0.8, label="start error (0.7 m)")
    ax.set_xlim(0, 2.5)
    ax.set_xlabel("translation error of the box-aligned pose (m)")
    ax.set_ylabel("fraction of frames with >= 2 box pairs")
    ax.set_title("Box corners alone, from a track-like prediction")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="swept sequences (bb-align sim OUT --sweep)")
    ap.add_argument("--every", type=int, default=3, help="every n-th frame of each sequence")
    ap.add_argument("--start-m", type=float, default=0.7)
    ap.add_argument("--start-deg", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--plot", type=Path)
    a = ap.parse_args()
    rows = measure(a.root, a.every, a.start_m, a.start_deg, a.seed)
    text = report(
        rows,
        f"# benchmarks/track_boxes_at_range.py {a.root} --every {a.every} (start {a.start_m} m / {a.start_deg} deg)",
    )
    print(text)
    if a.out:
        a.out.write_text(text + "\n")
    if a.plot:
        plot(rows, a.plot)


if __name__ == "__main__":
    main()
