"""Calibrate the tracker's noise settings offline on recorded measurements.

`bb-align track ROOT --records R.jsonl` keeps, per frame, the engine's own measurement (pose and covariance), both
cars' odometry and the truth. Refining from a slightly different prediction lands on nearly the same pose, so the
filter can be re-run on those recorded measurements in milliseconds for a grid of settings
(measurement_inflation, odometry drift, answer sigma) and each setting scored as `bb-align track` scores it:
fraction under 1 m & 1 deg within 70 m and beyond, wrong answers, and how often the 3-sigma band holds the true
error. The chosen setting is then checked with a real `bb-align track` run (docs/tracking.md).

    python benchmarks/track_calibration.py R.jsonl [R2.jsonl ...] [--grid JSON] [--out docs/tracking/calibration.txt]
"""

from __future__ import annotations

import argparse
import itertools
import json
from collections import defaultdict

import numpy as np

from bb_align.engine.config import TrackConfig
from bb_align.engine.covariance import left_covariance, params_covariance
from bb_align.engine.geometry import pose_error, se2
from bb_align.engine.tracker import Evidence, Measurement, PeerTrack, combine
from bb_align.lab.tracking.replay import error_components

GRID = {
    "measurement_inflation": (1.0, 2.0, 4.0, 8.0, 16.0),
    "odometry_drift_m_per_s": (0.05, 0.1, 0.2),
    "odometry_drift_deg_per_s": (0.05, 0.1),
    "answer_sigma_m": (0.3, 0.35),
    "boxes": (True,),
    "box_sigma_m": (1.3,),
}


def _sequences(paths: list[str]) -> dict[str, list[dict]]:
    seqs = defaultdict(list)
    for p in paths:
        for line in open(p):
            r = json.loads(line)
            seqs[f"{p}:{r['sequence']}"].append(r)
    return seqs


def _measurement(r: dict, inflation: float, cfg: TrackConfig) -> Measurement:
    """The frame's recorded measurement as the follower built it: the engine run's pose and covariance (inflated
    unless an acquisition), fused with the boxes' measurement when one was recorded and they agree; its evidence
    the same without the inflation. The refinement's fitness is not recorded: the support check is not replayed."""
    if r["measured"] is None or r["measured_cov"] is None:
        return Measurement(False, reason=r["reason"] or "none")
    T = se2(*r["measured"])
    cov = left_covariance(np.array(r["measured_cov"]), T)
    scale = inflation if r["source"] != "acquisition" else 1.0
    m, own = Measurement(True, T, scale * cov), Measurement(True, T, cov)
    if r.get("box_measured") is not None and r["source"] != "acquisition" and cfg.boxes:
        # Recorded at the default box_sigma_m; the covariance scales with its square.
        scale = (cfg.box_sigma_m / TrackConfig().box_sigma_m) ** 2
        box = Measurement(True, se2(*r["box_measured"]), scale * np.array(r["box_cov"]))
        m, _ = combine(m, box, cfg.box_agreement_chi2)
        own, _ = combine(own, box, cfg.box_agreement_chi2)
    m.evidence = Evidence(own.T_ego_peer, own.covariance, 1.0)
    return m


def run(seqs: dict[str, list[dict]], cfg: TrackConfig, inflation: float, odometry: bool = True) -> dict:
    rows = []
    for recs in seqs.values():
        track, started = PeerTrack(cfg), False
        for r in recs:
            m = _measurement(r, inflation, cfg)
            O = r["odometry"] if odometry else None
            O_e, O_p = (se2(*O[0]), se2(*O[1])) if O else (None, None)
            a = track.step(r["stamp"], lambda T_pred, m=m: m, lambda T_prior, m=m: m, O_e, O_p)
            started |= a.valid
            if not started:
                continue
            T_true = se2(*r["truth"])
            row = {"d": r["distance_m"], "valid": a.valid, "good": False, "inside": None}
            if a.valid:
                t, deg = pose_error(a.T_ego_peer, T_true)
                row["good"] = t <= 1.0 and deg <= 1.0
                e = np.array(error_components(a.T_ego_peer, T_true))
                sig = np.sqrt(np.diag(params_covariance(a.covariance, a.T_ego_peer)))
                row["inside"] = bool(np.all(np.abs(e) <= 3 * sig))
            rows.append(row)
    within = [x for x in rows if x["d"] < 70]
    far = [x for x in rows if x["d"] >= 70]
    answered = [x for x in rows if x["valid"]]
    return {
        "within_70m": np.mean([x["good"] for x in within]),
        "70+": np.mean([x["good"] for x in far]) if far else float("nan"),
        "wrong": np.mean([x["valid"] and not x["good"] for x in rows]),
        "inside_3sigma": np.mean([x["inside"] for x in answered]) if answered else float("nan"),
        "frames": len(rows),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("records", nargs="+")
    ap.add_argument("--out", default=None)
    ap.add_argument("--no-odometry", action="store_true", help="the constant-velocity model (odometry ignored)")
    ap.add_argument("--grid", default=None, help='JSON overriding GRID entries, e.g. {"answer_sigma_m": [0.4]}')
    args = ap.parse_args()
    grid = GRID | (json.loads(args.grid) if args.grid else {})
    seqs = _sequences(args.records)
    lines = ["inflation drift_m drift_deg answer_sigma boxes box_sigma | within70 70+ wrong inside3sigma frames"]
    for values in itertools.product(*grid.values()):
        p = dict(zip(grid, values))
        infl = p.pop("measurement_inflation")
        cfg = TrackConfig(**p, measurement_inflation=infl, measurement_inflation_without_odometry=infl)
        s = run(seqs, cfg, infl, odometry=not args.no_odometry)
        lines.append(
            f"{infl:9g} {p['odometry_drift_m_per_s']:7g} {p['odometry_drift_deg_per_s']:9g} {p['answer_sigma_m']:12g}"
            f" {str(p['boxes']):>5} {p['box_sigma_m']:9g} |"
            f" {100 * s['within_70m']:7.1f} {100 * s['70+']:5.1f} {100 * s['wrong']:5.2f} "
            f"{100 * s['inside_3sigma']:11.1f} {s['frames']:6d}"
        )
        print(lines[-1], flush=True)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
