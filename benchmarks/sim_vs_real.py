"""Simulated far pairs beside the real ones: what the images hold at range, how the engine's evidence looks, and
what the engine answers, with and without a prior.

    make bench-sim-real       (or, by hand:)
    .venv/bin/python benchmarks/sim_vs_real.py --data ../shared/data \
        --sim "mixed, >= 70 m=out/bench_accuracy@70" --sim "street family=out/sim_street" \
        --sim "turn family=out/sim_turn"
    .venv/bin/python benchmarks/sim_vs_real.py --data ../shared/data --sim "street family=out/sim_street" --keep
        (re-measures the real pairs and the street family only; the other sets stay as in the JSON)

Per pair (real: KITTI 00 at 73-80 m; simulated: each set's pairs at least MIN_M apart): lit pixels of the peer's
BV image by range band, the dense overlap at the true pose, the best distinct hypothesis's overlap (no prior)
against the truth's, the landscape's shape along the baseline at the truth (score at the truth minus the best score
within 2 m along it: negative when the landscape ramps away from the truth), and the engine's outcome without and
with the seeded 2 m / 2 deg prior (right / wrong / refused, scored as `bb-align real-pairs` scores: within 1 m and
1 deg; every answer's 3-sigma checked). Medians per set as a markdown table and JSON (docs/real_pairs/), and a plot.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bb_align import AlignConfig, Aligner
from bb_align.engine.geometry import ground_se2, pose_error, se2
from bb_align.engine.landscape import Fields, score_grid
from bb_align.engine.refine import overlap_fitness
from bb_align.lab.realpairs import RealPair, kitti00_far, score, seeded_prior, simulated_pairs
from bb_align.lab.recording import RECORD_HELP, output_path
from bb_align.lab.sim.realism import lit_by_band

REAL = "real: KITTI 00, 73-80 m"


def along_baseline(aligner: Aligner, ego_cloud, pts_peer, G) -> np.ndarray:
    """The landscape's score along the baseline at the truth's yaw: 21 cells of 0.2 m, +-2 m, the truth in the
    middle (index 10)."""
    cfg = aligner.config
    fields = Fields.of(ego_cloud, cfg.landscape)
    S = score_grid(fields.fine, ego_cloud, pts_peer[: cfg.landscape.max_points], G, np.array([0.0]), 10, 0.2)[0]
    base = G[:2, 2] / np.linalg.norm(G[:2, 2])
    return np.array([S[10 + int(round(k * base[0])), 10 + int(round(k * base[1]))] for k in range(-10, 11)])


def ramp_along(along: np.ndarray) -> float:
    """S(truth) - max along the baseline: 0 when the truth is the best, negative when the landscape ramps away."""
    return float(along[10] - along.max())


def measure(aligner: Aligner, pair: RealPair, pts_ego, pts_peer) -> dict:
    cfg = aligner.config
    ego, peer = aligner.prepare(pts_ego), aligner.prepare(pts_peer)
    G = ground_se2(pair.T_ref)
    ego_cloud = ego.cloud(cfg.refine)
    sample = aligner.refiner.sample(peer.bev)
    truth_fit, _ = overlap_fitness(ego_cloud, sample[0], G, cfg.refine.gates_m[-1])
    plain = aligner.align(ego, peer)
    alias = 0.0
    for h in [] if plain.acquisition is None else plain.acquisition.to_dict()["all"]:
        t_err, r_err = pose_error(se2(np.radians(h["yaw_deg"]), h["tx"], h["ty"]), G)
        if t_err > 3 or r_err > 3:
            alias = max(alias, h["fitness"])
    with_prior = aligner.align(ego, peer, T_prior=seeded_prior(pair))
    along = along_baseline(aligner, ego_cloud, sample[0], G)
    return {
        "pair": pair.name,
        "distance_m": pair.distance_m,
        "lit_peer": lit_by_band(peer.bev),
        "truth_fitness": truth_fit,
        "alias_fitness": alias,
        "ramp": ramp_along(along),
        "peak_offset_cells": int(np.argmax(along)) - 10,  # where along the baseline the best is (0.2 m cells)
        "no_prior": score(pair, plain, False).__dict__,
        "prior": score(pair, with_prior, True).__dict__,
    }


def real_pairs(data: Path) -> list[tuple[RealPair, np.ndarray, np.ndarray]]:
    from bb_align.io.clouds import load_cloud

    return [(p, load_cloud(p.ego), load_cloud(p.peer)) for p in kitti00_far(data)]


def outcomes(rows: list[dict], key: str) -> str:
    counts = [sum(r[key]["outcome"] == o for r in rows) for o in ("right", "wrong", "refused")]
    answered = [r[key] for r in rows if r[key]["success"]]
    covered = sum(bool(r["covered"]) for r in answered)
    return f"{' / '.join(map(str, counts))} ({covered}/{len(answered)} in 3 sigma)"


def table(sets: dict[str, list[dict]], command: str) -> str:
    lines = [
        "# Simulated far pairs beside the real ones",
        "",
        f"Made by `{command}`. Medians per set. Lit: the peer's BV pixels by range from its own sensor. Overlap: the",
        "fraction of the peer's pixels within 0.4 m of an ego pixel. Ramp: the landscape's score at the truth minus",
        "its best within 2 m along the baseline (0 when the truth is the best). Outcomes: right / wrong / refused,",
        "right = within 1 m and 1 deg (`bb-align real-pairs`' scoring), and how many answers' 3 sigma cover their",
        "error; the prior is the truth moved 2 m and turned 2 deg, seeded by the pair's name. Images only, no",
        "boxes (the KITTI runs have none), so the simulated benchmark's own numbers, with boxes, differ.",
        "",
        "| set | pairs | lit 0-20 / 20-40 / 40-70 / 70-100 m | overlap at the truth | best alias overlap | "
        "alias above the truth | ramp (median, 10th pct) | no prior | with prior |",
        "| --- | ---: | --- | ---: | ---: | ---: | --- | --- | --- |",
    ]
    for name, rs in sets.items():
        if not rs:
            continue
        lit = np.median([r["lit_peer"] for r in rs], axis=0).astype(int)
        ramp = np.array([r["ramp"] for r in rs])
        above = sum(r["alias_fitness"] > r["truth_fitness"] for r in rs)
        lines.append(
            f"| {name} | {len(rs)} | {' / '.join(map(str, lit))} | "
            f"{np.median([r['truth_fitness'] for r in rs]):.3f} | {np.median([r['alias_fitness'] for r in rs]):.3f} | "
            f"{above} / {len(rs)} | {np.median(ramp):.4f}, {np.percentile(ramp, 10):.4f} | "
            f"{outcomes(rs, 'no_prior')} | {outcomes(rs, 'prior')} |"
        )
    return "\n".join(lines) + "\n"


def plot(sets: dict[str, list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    names = [n for n, rs in sets.items() if rs]
    for ax, key, title in ((axes[0], "no_prior", "no prior"), (axes[1], "prior", "2 m / 2 deg prior")):
        bottom = np.zeros(len(names))
        for outcome, colour in (("right", "tab:green"), ("wrong", "tab:red"), ("refused", "tab:gray")):
            share = np.array([np.mean([r[key]["outcome"] == outcome for r in sets[n]]) for n in names])
            ax.bar(range(len(names)), share, bottom=bottom, color=colour, label=outcome)
            bottom += share
        ax.set_xticks(range(len(names)), names, rotation=20, ha="right", fontsize=8)
        ax.set_ylabel("share of pairs")
        ax.set_title(title)
        ax.legend(fontsize=8)
    axes[2].boxplot([[r["ramp"] for r in sets[n]] for n in names])
    axes[2].set_xticks(range(1, len(names) + 1), names, rotation=20, ha="right", fontsize=8)
    axes[2].set_ylabel("landscape at the truth - best within 2 m")
    axes[2].set_title("ramp along the baseline")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument(
        "--sim", action="append", default=[], help="LABEL=DIR[@MIN_M], a simulated set, its pairs >= MIN_M (40) apart"
    )
    ap.add_argument("--out", type=Path, default=None, help="default: out/real_pairs (docs/real_pairs with --record)")
    ap.add_argument("--record", action="store_true", help=RECORD_HELP)
    ap.add_argument(
        "--keep",
        action="store_true",
        help="keep the sets already in OUT/sim_vs_real.json that this run does not measure (in their order)",
    )
    args = ap.parse_args()
    args.out = args.out or output_path("docs/real_pairs", args.record)
    aligner = Aligner(AlignConfig())
    kept = json.loads((args.out / "sim_vs_real.json").read_text()) if args.keep else {}
    sets: dict[str, list[dict]] = {REAL: []}
    for pair, pts_ego, pts_peer in tqdm(real_pairs(args.data), desc="real"):
        sets[REAL].append(measure(aligner, pair, pts_ego, pts_peer))
    for spec in args.sim:
        label, _, where = spec.rpartition("=")
        root, _, min_m = where.partition("@")
        pairs = list(simulated_pairs(Path(root), float(min_m or 40.0)))
        sets[label] = [measure(aligner, *p) for p in tqdm(pairs, desc=label)]
    if kept:  # the measured sets replace their namesakes; the others stay as they were measured
        sets = {name: sets.get(name, rows) for name, rows in kept.items()} | sets
    command = "make bench-sim-real"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "sim_vs_real.md").write_text(table(sets, command))
    (args.out / "sim_vs_real.json").write_text(json.dumps(sets, indent=1, default=float) + "\n")
    plot(sets, args.out / "sim_vs_real.png")
    print(table(sets, command))


if __name__ == "__main__":
    main()
