"""What the sweeps' self-motion does to a far answer, and what de-skewing and the covariance's travel term do about
it (docs/engine.md, "Self-motion distortion").

    .venv/bin/python benchmarks/sweep_motion.py                 # the turn family, seed 7 (about 10 min on 2 cores)
    .venv/bin/python benchmarks/sweep_motion.py --pair 4        # one pair rendered with one thing changed at a time

Every scenario of `bb-align sim --family turn --scenarios 20 --seed 7 --fleet hdl64` is rendered three ways from
the same random draws: as simulated (not de-skewed), without self-motion distortion, and as simulated then
de-skewed with each car's true motion (`bb_align_client.deskew_sweep`). Each is aligned images only (as
`benchmarks/sim_vs_real.py` does), without and with the seeded 2 m / 2 deg prior, and scored as `bb-align
real-pairs` scores (right: within 1 m and 1 deg; covered: the error within 3 sigma along, across and in yaw). The
sweeps as simulated are aligned twice: with `covariance.sweep_travel_m` at 0 and at its default. Writes
docs/sweep_motion/ (records.jsonl, README.md, errors.png).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bb_align import AlignConfig, Aligner
from bb_align.engine.geometry import se2_params
from bb_align.lab.realpairs import RealPair, score, seeded_prior
from bb_align.lab.recording import RECORD_HELP, output_path
from bb_align.lab.sim.raycast import sensor_twist
from bb_align.lab.sim.scenario import Scenario, SimConfig
from bb_align.lab.sim.writer import scenario_distance, scenario_seed
from bb_align_client import deskew_sweep

SEED, N = 7, 20
BASE = SimConfig(min_distance_m=40.0, max_distance_m=70.0, fleet=("hdl64",), family="turn")


def scenario(index: int, config: SimConfig = BASE) -> Scenario:
    return Scenario(scenario_seed(SEED, index), 2, scenario_distance(SEED, index, N, BASE), config)


def twist(sc: Scenario, agent: int, t: float) -> tuple[np.ndarray, float]:
    """(vx, vy) of an agent's sensor in its own frame at time t, and its yaw rate (what the simulator writes)."""
    spec = sc.agents[agent]
    vx, vy, w = sensor_twist(sc.world, spec.vehicle, spec.mount, t)
    return np.array([vx, vy]), w


def clouds(sc: Scenario, deskew: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[float]]:
    """(ego points, peer points, T_ego_peer, each car's travel during its sweep in metres)."""
    fr = sc.frame(0)
    agents = [fr.agents["0"], fr.agents["1"]]
    T = np.linalg.inv(agents[0].T_world_sensor) @ agents[1].T_world_sensor
    pts, travel = [], []
    for k, a in enumerate(agents):
        v, w = twist(sc, k, a.time_s)
        period = 1.0 / sc.agents[k].sensor.spin_hz
        travel.append(float(np.hypot(*v) * period))
        pts.append(deskew_sweep(a.points, v, w, period_s=period) if deskew else a.points)
    return pts[0], pts[1], T, travel


def align(aligners: dict[str, Aligner], name: str, ego_pts, peer_pts, T) -> list[dict]:
    pair = RealPair(name, "sim", Path(), Path(), T)
    rows = []
    for label, aligner in aligners.items():
        ego, peer = aligner.prepare(ego_pts), aligner.prepare(peer_pts)
        for prior in (None, seeded_prior(pair)):
            r = aligner.align(ego, peer, T_prior=prior)
            rec = score(pair, r, prior is not None).__dict__
            yaw = float(np.degrees(se2_params(r.T_ego_peer)[0] - se2_params(T)[0]))
            rows.append({**rec, "engine": label, "yaw_err_deg": (yaw + 180.0) % 360.0 - 180.0})
    return rows


def family(out: Path) -> list[dict]:
    travel0 = Aligner(AlignConfig(covariance={"sweep_travel_m": 0.0}))
    travel1 = Aligner(AlignConfig(covariance={"sweep_travel_m": 1.0}))
    records = []
    for i in tqdm(range(N), desc="turn family"):
        name = f"sim_{SEED}_{i:04d}/000000"
        flat = BASE.model_copy(update={"distortion": False})
        renders = {
            "as simulated": (scenario(i), False, {"travel 0": travel0, "travel 1 m": travel1}),
            "without distortion": (scenario(i, flat), False, {"travel 0": travel0}),
            "de-skewed": (scenario(i), True, {"travel 0": travel0}),
        }
        for render, (sc, deskew, aligners) in renders.items():
            ego_pts, peer_pts, T, travel = clouds(sc, deskew)
            if np.hypot(T[0, 3], T[1, 3]) < 40.0:
                break
            for row in align(aligners, name, ego_pts, peer_pts, T):
                records.append({**row, "render": render, "travel_m": travel})
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "records.jsonl", "w") as fh:
        for r in records:
            fh.write(json.dumps(r, default=float) + "\n")
    return records


def table(records: list[dict]) -> str:
    lines = [
        "# Self-motion distortion on the turn family",
        "",
        'Made by `.venv/bin/python benchmarks/sweep_motion.py` (docs/engine.md, "Self-motion distortion"). Seed 7,',
        "the pairs at 40 m and more, images only. Right / wrong / refused as `bb-align real-pairs` scores; covered:",
        "answers whose error lies within 3 sigma along, across and in yaw; errors and 1-sigma: medians over answers.",
        "",
        "| sweeps | engine | prior | right / wrong / refused | covered | yaw error deg | t error m | yaw 1-sigma deg |"
        " worst yaw error / its 1-sigma |",
        "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    groups = sorted({(r["render"], r["engine"]) for r in records}, key=lambda g: (g[0] != "as simulated", g))
    for render, engine in groups:
        for prior in (False, True):
            rs = [r for r in records if r["render"] == render and r["engine"] == engine and r["prior"] == prior]
            counts = [sum(r["outcome"] == o for r in rs) for o in ("right", "wrong", "refused")]
            ans = [r for r in rs if r["success"]]
            if not ans:
                continue
            worst = max(ans, key=lambda r: abs(r["yaw_err_deg"]) / r["sigma_yaw_deg"])
            lines.append(
                f"| {render} | {engine} | {'2 m / 2 deg' if prior else 'none'} | {' / '.join(map(str, counts))} | "
                f"{sum(bool(r['covered']) for r in ans)} / {len(ans)} | "
                f"{np.median([abs(r['yaw_err_deg']) for r in ans]):.3f} | "
                f"{np.median([r['t_err_m'] for r in ans]):.3f} | "
                f"{np.median([r['sigma_yaw_deg'] for r in ans]):.3f} | "
                f"{abs(worst['yaw_err_deg']) / worst['sigma_yaw_deg']:.2f} ({worst['pair'].split('/')[0]}) |"
            )
    return "\n".join(lines) + "\n"


def plot(records: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    styles = {"as simulated": "tab:red", "without distortion": "tab:blue", "de-skewed": "tab:green"}
    for render, colour in styles.items():
        rs = [r for r in records if r["render"] == render and r["engine"] == "travel 0" and r["prior"] and r["success"]]
        travel = [r["travel_m"][1] - r["travel_m"][0] for r in rs]
        axes[0].scatter(travel, [r["yaw_err_deg"] for r in rs], color=colour, label=render, s=18)
    axes[0].set_xlabel("peer's minus ego's travel during a sweep, m")
    axes[0].set_ylabel("yaw error, deg (with the prior)")
    axes[0].axhline(0, color="k", lw=0.5)
    axes[0].legend(fontsize=8)
    for engine, colour in (("travel 0", "tab:orange"), ("travel 1 m", "tab:purple")):
        rs = [r for r in records if r["render"] == "as simulated" and r["engine"] == engine and r["success"]]
        z = sorted(abs(r["yaw_err_deg"]) / r["sigma_yaw_deg"] for r in rs)
        axes[1].plot(z, np.arange(1, len(z) + 1) / len(z), color=colour, label=f"sweep_travel_m: {engine}")
    axes[1].axvline(3, color="k", ls="--", lw=0.8)
    axes[1].set_xlabel("|yaw error| / yaw 1-sigma (sweeps as simulated)")
    axes[1].set_ylabel("share of answers")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def one_pair(index: int) -> None:
    """The pair rendered with one thing changed at a time (the same random draws)."""
    aligners = {"travel 0": Aligner(AlignConfig(covariance={"sweep_travel_m": 0.0}))}
    name = f"sim_{SEED}_{index:04d}/000000"

    def levelled(which: tuple[int, ...]) -> Scenario:
        sc = scenario(index)
        for k in which:
            sc.agents[k].mount = replace(sc.agents[k].mount, roll=0.0, pitch=0.0)
        return sc

    renders = {
        "as simulated": (scenario(index), False),
        "roll and pitch zeroed": (levelled((0, 1)), False),
        "peer levelled": (levelled((1,)), False),
        "ego levelled": (levelled((0,)), False),
        "without distortion": (scenario(index, BASE.model_copy(update={"distortion": False})), False),
        "de-skewed": (scenario(index), True),
    }
    tilt = [np.degrees([s.mount.roll, s.mount.pitch]).round(3).tolist() for s in scenario(index).agents]
    print(f"{name}: ego / peer roll, pitch (deg) {tilt}")
    for render, (sc, deskew) in renders.items():
        ego_pts, peer_pts, T, travel = clouds(sc, deskew)
        r = align(aligners, name, ego_pts, peer_pts, T)[0]
        print(
            f"{render:24s} travel {travel[0]:.2f} / {travel[1]:.2f} m  yaw error {r['yaw_err_deg']:+.3f} deg  "
            f"t error {r['t_err_m']:.3f} m  yaw 1-sigma {r['sigma_yaw_deg'] or float('nan'):.3f} deg  {r['outcome']}"
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pair", type=int, default=None, help="only this scenario, rendered one change at a time")
    ap.add_argument(
        "--out", type=Path, default=None, help="default: out/sweep_motion (docs/sweep_motion with --record)"
    )
    ap.add_argument("--record", action="store_true", help=RECORD_HELP)
    args = ap.parse_args()
    args.out = args.out or output_path("docs/sweep_motion", args.record)
    if args.pair is not None:
        one_pair(args.pair)
        return
    records = family(args.out)
    text = table(records)
    (args.out / "README.md").write_text(text)
    plot(records, args.out / "errors.png")
    print(text)


if __name__ == "__main__":
    main()
