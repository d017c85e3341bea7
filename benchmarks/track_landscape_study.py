"""Is the pose landscape's covariance an honest, tighter bound for a tracked frame than the refinement's?

For frames of `bb-align sim --sweep` sequences: the dense refinement from a prediction near the truth (the truth
moved by a draw of N(0, 0.2 deg / 0.2 m), as a track's prediction is off), as the tracker measures
(``Aligner.measure``); its covariance (the refinement's Hessian, what the tracker's evidence rule uses today) and
the pose landscape's around the refined pose (engine.landscape: the correlative grid and ``with_refinement``, as
the acquisition judges its answer). Per distance band: how often each covariance bounds the measurement's own
error within 1 m and 1 deg at 3 sigma (what the tracker's evidence rule asks of a frame whose answer is its
measurement), and how often such a bounded frame is in fact off by more (a wrong success), the normalised errors'
99th percentile per axis, and the landscape's time.

    python benchmarks/track_landscape_study.py out/sweep23 --every 2 --json docs/tracking/landscape_seed23.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import typer
from tqdm import tqdm

from bb_align.engine.config import AlignConfig
from bb_align.engine.geometry import se2, se2_params, worst_sigma_m
from bb_align.engine.landscape import Fields, landscape, with_refinement
from bb_align.engine.pipeline import Aligner
from bb_align.io.dataset import find_scenarios, iter_scenario_frames
from bb_align.lab.tracking.replay import error_components

BANDS = ((0, 40), (40, 70), (70, 1e9))


def measure_frame(aligner: Aligner, group, rng) -> dict | None:
    cfg, lc = aligner.config, aligner.config.landscape
    ego, peer = group.ego, group.peers[0]
    T_true = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
    e = aligner.prepare(ego.load_points(), ego.detections, features=False)
    p = aligner.prepare(peer.load_points(), peer.detections, features=False)
    y, x, t = se2_params(T_true[np.ix_([0, 1, 3], [0, 1, 3])])
    dy, dx, dt = rng.normal(0, [np.radians(0.2), 0.2, 0.2])
    r = aligner.measure(e, p, se2(y + dy, x + dx, t + dt))
    if not r.success or r.covariance is None:
        return None
    T_m = r.T_bv
    t0 = time.perf_counter()
    ego_cloud = e.cloud(cfg.refine)
    fields = Fields.of(ego_cloud, lc)
    pts = p.cached(("refine_sample", cfg.seed), lambda: aligner.refiner.sample(p.bev))[0][: lc.max_points]
    L = landscape(ego_cloud, fields, pts, T_m, lc)
    T_l, cov_l = (L.T, L.covariance) if L.at_edge else with_refinement(L, T_m, lc.refinement_d2)
    ms = (time.perf_counter() - t0) * 1e3
    out = {"distance_m": float(np.hypot(x, t)), "landscape_ms": ms, "at_edge": bool(L.at_edge)}
    for name, T, cov in (("hessian", T_m, np.asarray(r.covariance)), ("landscape", T_l, np.asarray(cov_l))):
        err = np.array(error_components(T, T_true[np.ix_([0, 1, 3], [0, 1, 3])]))
        sig = np.sqrt(np.maximum(np.diag(cov), 1e-18))
        out[name] = {
            "err": err.tolist(),
            "sigma": sig.tolist(),
            "t_bound_m": 3 * worst_sigma_m(cov),
            "r_bound_deg": 3 * float(np.degrees(sig[0])),
            "t_err_m": float(np.hypot(err[1], err[2])),
            "r_err_deg": float(np.degrees(abs(err[0]))),
        }
    return out


def tabulate(rows: list[dict]) -> list[str]:
    lines = ["band      frames | covariance  bounded  wrong-of-bounded  z99 yaw/x/y  sigma p50 m/deg"]
    for lo, hi in BANDS:
        b = [r for r in rows if lo <= r["distance_m"] < hi]
        if not b:
            continue
        for name in ("hessian", "landscape"):
            ok = [r for r in b if r[name]["t_bound_m"] <= 1.0 and r[name]["r_bound_deg"] <= 1.0]
            wrong = [r for r in ok if r[name]["t_err_m"] > 1.0 or r[name]["r_err_deg"] > 1.0]
            z = np.array([np.abs(r[name]["err"]) / np.array(r[name]["sigma"]) for r in b])
            s_m = np.median([r[name]["t_bound_m"] / 3 for r in b])
            s_d = np.median([r[name]["r_bound_deg"] / 3 for r in b])
            lines.append(
                f"{lo:>3g}-{hi:<5g} {len(b):6d} | {name:10s} {100 * len(ok) / len(b):6.1f} %  {len(wrong):4d}"
                f"            {'/'.join(f'{v:.1f}' for v in np.percentile(z, 99, axis=0))}   {s_m:.2f}/{s_d:.2f}"
            )
    ms = [r["landscape_ms"] for r in rows]
    lines.append(
        f"landscape per frame: p50 {np.median(ms):.0f} ms, p90 {np.percentile(ms, 90):.0f} ms; "
        f"at the window's edge: {sum(r['at_edge'] for r in rows)} of {len(rows)}"
    )
    return lines


def main(
    root: Path = typer.Argument(..., exists=True, file_okay=False),
    every: int = typer.Option(2, min=1, help="every n-th frame"),
    limit: int | None = typer.Option(None, min=1),
    seed: int = typer.Option(0, help="the predictions' draws"),
    json_out: Path | None = typer.Option(None, "--json"),
) -> None:
    aligner = Aligner(AlignConfig())
    rng = np.random.default_rng(seed)
    rows = []
    for name, path in tqdm(find_scenarios(root)[:limit], desc="sequences"):
        for k, group in enumerate(iter_scenario_frames(name, path)):
            if k % every == 0 and (row := measure_frame(aligner, group, rng)) is not None:
                rows.append({"sequence": name, "frame": k, **row})
    lines = tabulate(rows)
    print("\n".join(lines))
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps({"root": str(root), "every": every, "table": lines, "rows": rows}))


if __name__ == "__main__":
    typer.run(main)
