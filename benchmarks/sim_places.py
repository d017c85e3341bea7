"""Simulated street places beside the real one: each rendered as the real KITTI 00 run is, and the real place's
outcome placed within their distribution.

    make bench-sim-places      (or: .venv/bin/python benchmarks/sim_places.py --data ../shared/data --places 40)

Why places: the 20 real far pairs are one street seen from 10 follower positions over 7 m (frames 0-9) against
the car ahead (frames 94, 95), so they are one sample of "a street", not twenty. Comparing them with twenty
independent simulated pairs compares one street's rate with a rate over streets. Here every simulated place gets
the real run's design: the street family (a car following another 73-81 m ahead, HDL-64E, de-skewed as KITTI's
scans are, both cars moving), 10 consecutive sweeps of the follower against 2 consecutive sweeps of the car ahead
taken from the middle of the ten (so each place's median distance is its drawn one), 20 pairs per place, each
aligned without and with the seeded 2 m / 2 deg prior and scored as `bb-align real-pairs` scores (right within 1 m
and 1 deg). The real place is the KITTI 00 run's 20 pairs through the same aligner.

Reported per path: each place's right / wrong / refused, the simulated places' distribution of right answers, and
the real place's standing in it: the share of simulated places that answer at least as many pairs right.
Writes docs/sim/places.{md,json,png}.
"""

from __future__ import annotations

import argparse
import functools
import json
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from bb_align import AlignConfig, Aligner
from bb_align.lab.realpairs import RealPair, kitti00_far, score, seeded_prior
from bb_align.lab.recording import RECORD_HELP, output_path
from bb_align.lab.sim.scenario import Scenario, SimConfig

EGO_SWEEPS, PEER_SWEEPS = 10, 2  # the real run: follower frames 0-9, the car ahead's frames 94 and 95
OUTCOMES = ("right", "wrong", "refused")
PATHS = ("no_prior", "prior")
# The real place's design: the HDL-64E on both cars, de-skewed sweeps, both cars moving, 73-81 m apart.
PLACE_CONFIG = SimConfig(
    family="street", fleet=("hdl64",), distortion=False, min_distance_m=73, max_distance_m=81, stopped_prob=0.0
)


def place_pairs(seed: int, ego_sweeps: int = EGO_SWEEPS, peer_sweeps: int = PEER_SWEEPS, config=PLACE_CONFIG):
    """One simulated place's pairs: (pair, pts_ego, pts_peer) for every follower sweep against every leader sweep."""
    scenario = Scenario(seed, 2, None, config)
    follower = [scenario.frame(k).agents["0"] for k in range(ego_sweeps)]
    # the leader's sweeps from the middle of the follower's: each place's median distance is the one drawn
    first = (ego_sweeps - peer_sweeps) // 2
    leader = [scenario.frame(k).agents["1"] for k in range(first, first + peer_sweeps)]
    out = []
    for i, ego in enumerate(follower):
        for j, peer in enumerate(leader):
            T_ego_peer = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
            out.append((RealPair(f"place{seed}/{i}<-{j}", "sim", Path(), Path(), T_ego_peer), ego.points, peer.points))
    return out


@functools.cache  # once per worker process
def _aligner() -> Aligner:
    return Aligner(AlignConfig())


def outcomes(pairs) -> dict:
    """Each pair aligned without and with its seeded prior: the outcome strings per path (clouds prepared once)."""
    aligner = _aligner()
    prepared: dict[int, object] = {}  # by the cloud array's identity: a place's pairs share their sweeps

    def prep(points):
        key = id(points)
        if key not in prepared:
            prepared[key] = aligner.prepare(points)
        return prepared[key]

    rows = {path: [] for path in PATHS}
    for pair, pts_ego, pts_peer in pairs:
        ego, peer = prep(pts_ego), prep(pts_peer)
        rows["no_prior"].append(score(pair, aligner.align(ego, peer), False).outcome)
        rows["prior"].append(score(pair, aligner.align(ego, peer, T_prior=seeded_prior(pair)), True).outcome)
    return rows


def _run(job: tuple[str, object]) -> dict:
    kind, arg = job
    if kind == "real":
        from bb_align.io.clouds import load_cloud

        load = functools.cache(load_cloud)  # 12 scans in 20 pairs: each loaded (and so prepared) once
        pairs = [(p, load(p.ego), load(p.peer)) for p in kitti00_far(arg)]
        name = "real: KITTI 00"
    else:
        pairs = place_pairs(int(arg))
        name = f"sim seed {arg}"
    rows = outcomes(pairs)
    return {
        "place": name,
        "distance_m": round(float(np.median([p.distance_m for p, _, _ in pairs])), 1),
        **{path: {o: rows[path].count(o) for o in OUTCOMES} for path in PATHS},
    }


def standing(sim_right: list[int], real_right: int) -> float:
    """The share of simulated places answering at least as many pairs right as the real place."""
    return float(np.mean(np.asarray(sim_right) >= real_right)) if len(sim_right) else float("nan")


def summary(rows: list[dict]) -> dict:
    real = next(r for r in rows if r["place"].startswith("real"))
    sim = [r for r in rows if r is not real]
    out = {"places": len(sim)}
    for path in PATHS:
        right = [r[path]["right"] for r in sim]
        out[path] = {
            "real_right": real[path]["right"],
            "sim_right_quartiles": [float(q) for q in np.percentile(right, [25, 50, 75])],
            "sim_right_mean": float(np.mean(right)),
            "sim_places_at_least_real": standing(right, real[path]["right"]),
            "sim_places_none_right": int(sum(v == 0 for v in right)),
            "sim_wrong": int(sum(r[path]["wrong"] for r in sim)),
            "sim_pairs": int(sum(sum(r[path].values()) for r in sim)),
        }
    return out


def table(rows: list[dict], summ: dict, command: str) -> str:
    lines = [
        "# Simulated street places beside the real one",
        "",
        f"Made by `{command}`. Each simulated place is rendered as the real KITTI 00 run is (10 consecutive",
        "follower sweeps against 2 consecutive sweeps of the car 73-81 m ahead: 20 pairs) and every pair aligned",
        "without and with the seeded 2 m / 2 deg prior; right = within 1 m and 1 deg. Standing: the share of",
        "simulated places answering at least as many of their 20 pairs right as the real place.",
        "",
        "| path | real place right | simulated places: right, quartiles (mean) | places with none right | standing "
        "of the real place | simulated wrong |",
        "| --- | ---: | --- | ---: | ---: | ---: |",
    ]
    for path in PATHS:
        s = summ[path]
        q = " / ".join(f"{v:g}" for v in s["sim_right_quartiles"])
        lines.append(
            f"| {path.replace('_', ' ')} | {s['real_right']} / 20 | {q} ({s['sim_right_mean']:.1f}) | "
            f"{s['sim_places_none_right']} / {summ['places']} | {s['sim_places_at_least_real']:.2f} | "
            f"{s['sim_wrong']} of {s['sim_pairs']} |"
        )
    lines += ["", "| place | median distance (m) | no prior right / wrong / refused | prior right / wrong / refused |"]
    lines.append("| --- | ---: | --- | --- |")
    for r in rows:
        cells = [" / ".join(str(r[p][o]) for o in OUTCOMES) for p in PATHS]
        lines.append(f"| {r['place']} | {r['distance_m']} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    real = next(r for r in rows if r["place"].startswith("real"))
    sim = [r for r in rows if r is not real]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
    for ax, key in zip(axes, PATHS, strict=True):
        ax.hist([r[key]["right"] for r in sim], bins=np.arange(-0.5, 21.5, 1.0), color="tab:blue", alpha=0.8)
        ax.axvline(real[key]["right"], color="tab:red", lw=2, label="real place (KITTI 00)")
        ax.set_xlabel(f"pairs right of 20, {key.replace('_', ' ')}")
        ax.set_xlim(-0.5, 20.5)
    axes[0].set_ylabel("simulated places")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{len(sim)} simulated street places, each run as the real one is", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--places", type=int, default=40)
    ap.add_argument("--seed", type=int, default=11, help="places are scenarios seed * 100003 + k")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="default: out/sim/places (docs/sim/places with --record)")
    ap.add_argument("--record", action="store_true", help=RECORD_HELP)
    args = ap.parse_args()
    args.out = args.out or output_path("docs/sim/places", args.record)
    from tqdm import tqdm

    jobs = [("real", args.data)] + [("sim", args.seed * 100003 + k) for k in range(args.places)]
    with Pool(args.workers) as pool:
        rows = list(tqdm(pool.imap(_run, jobs), total=len(jobs), desc="places"))
    summ = summary(rows)
    command = f"python benchmarks/sim_places.py --places {args.places} --seed {args.seed}"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"summary": summ, "places": rows}, indent=1) + "\n")
    args.out.with_suffix(".md").write_text(table(rows, summ, command))
    plot(rows, args.out.with_suffix(".png"))
    print(table(rows, summ, command))


if __name__ == "__main__":
    main()
