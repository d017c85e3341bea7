"""What do successive frames' errors share? The stream's evidence (bb_align.engine.evidence) fuses the last frames
of a track and widens the fused covariance by ``1 + rho (n - 1)``; this measures ``rho`` on recorded tracks
(`bb-align track ROOT --records R.jsonl`, sweeps with odometry; or the real runs of benchmarks/track_real.py), with
the truth (the reference) known.

    bb-align sim out/sweep101 --sweep --scenarios 4 --frames 150 --seed 101
    bb-align track out/sweep101 --records out/sweep101.jsonl
    python benchmarks/track_real.py --data ../shared/data --out docs/tracking/real_runs
    python benchmarks/evidence_correlation.py out/sweep101.jsonl docs/tracking/real_runs.json \
        --check out/sweep7373.jsonl --out docs/tracking/evidence_correlation

For every frame whose own evidence entered the stream (``evidence_err``, ``evidence_cov``: a measurement of the
odometry offset, its error against the true offset): the error whitened by its covariance's Cholesky factor.
Between two frames of one track at most ``window_s`` apart, per axis (yaw, x, y), the mean product of the whitened
errors (not centred: a bias the frames share counts; not normalised: errors smaller than their covariances share
less in those units, and the fusion only needs that product to be bounded), beside the mean square (1 for an
exact covariance). What frames share depends on where they were taken (``engine.evidence.SharedError``): pairs
taken while both cars stayed within ``track.evidence_same_place_m`` of each other's place give the model's near
``rho``, pairs at least one ``evidence_decorrelation_m`` beyond it its far ``rho``; each is the largest product of a
sequence of the sets it is chosen on, rounded up to a tenth (records without odometry count as one place); the
``--check`` sets (held out) must not exceed them. Then, for each
``rho`` of a grid, every frame's window fused as the stream fuses it, and the share of fused errors inside their
chi2(3) 99 % ellipsoid (the plot). Writes OUT.json, OUT.md and OUT.png.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer

from bb_align.engine.config import TrackConfig
from bb_align.engine.evidence import OffsetSample, SharedError, StreamEvidence, moved_m
from bb_align.engine.geometry import log_left, se2
from bb_align.engine.tracker import shared_error
from bb_align.lab.recording import RECORD_HELP, output_path

CHI2_3_99 = 11.345
RHOS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
BANDS = ((0.0, 40.0), (40.0, 70.0), (70.0, 1e9))
FAR_M = 70.0  # the band where the stream's evidence matters most, measured on its own too
MIN_FRAMES = 20  # a sequence's correlation counts when it has at least this many frames with evidence


def load(path: Path) -> list[dict]:
    """Frame records: JSON lines from `bb-align track --records`, or benchmarks/track_real.py's OUT.json (its
    runs with odometry, each step a frame of the sequence named by its row)."""
    if path.suffix == ".json":
        body = json.loads(path.read_text())
        return [
            s | {"sequence": key, "frame": s["step"]}
            for key, steps in body["steps"].items()
            if key.split(" ")[1] == "with"
            for s in steps
        ]
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def segments(records: list[dict]) -> list[list[dict]]:
    """Runs of frames of one sequence and one track (a track ends at an acquisition or a loss) that carry evidence."""
    out: list[list[dict]] = []
    current: list[dict] = []
    last_seq = None
    for r in records:
        new_track = r["sequence"] != last_seq or (r.get("event") or "").find("acquired") >= 0 or r["state"] == "lost"
        if new_track and current:
            out.append(current)
            current = []
        last_seq = r["sequence"]
        if r.get("evidence_err") is not None:
            current.append(r)
    if current:
        out.append(current)
    return out


def whitened(r: dict) -> np.ndarray:
    L = np.linalg.cholesky(np.asarray(r["evidence_cov"]))
    return np.linalg.solve(L, np.asarray(r["evidence_err"]))


def places(r: dict) -> np.ndarray | None:
    """Where the two cars were (``odometry``: each car's (yaw, x, y) in its own odometry frame), or None."""
    odo = r.get("odometry")
    return None if odo is None else np.array([odo[0][1:], odo[1][1:]], dtype=float)


def moments(segs: list[list[dict]], window_s: float, lo_m: float = 0.0, hi_m: float = np.inf):
    """Per axis (yaw, x, y): the mean product of the whitened errors of frame pairs at most window_s apart whose
    cars moved between lo_m and hi_m (metres) between them, the number of such pairs, and the mean square of a
    frame's whitened error."""
    prods, pairs, squares, frames = np.zeros(3), 0, np.zeros(3), 0
    for seg in segs:
        w = [whitened(r) for r in seg]
        t = [r["stamp"] for r in seg]
        moved = moved_m([places(r) for r in seg])  # as the stream counts it (0 without odometry: one place)
        squares, frames = squares + sum(x**2 for x in w), frames + len(w)
        for i in range(len(seg)):
            for j in range(i + 1, len(seg)):
                if t[j] - t[i] > window_s:
                    break
                if lo_m <= moved[i, j] <= hi_m:
                    prods, pairs = prods + w[i] * w[j], pairs + 1
    return (prods / max(pairs, 1)).tolist(), pairs, (squares / max(frames, 1)).tolist()


def fused_d2(segs: list[list[dict]], shared: SharedError, cfg: TrackConfig) -> list[tuple[float, float]]:
    """(distance m, squared Mahalanobis distance of the fused error) of every frame's window fused as the stream
    fuses it (``StreamEvidence``, the track's window and agreement) with ``shared``: each frame's measurement is
    its recorded error about the true offset (the drift between frames is in neither)."""
    out, no_drift = [], np.zeros((3, 3))
    for seg in segs:
        ev = StreamEvidence(
            cfg.evidence_window_s, cfg.evidence_max_frames, shared, cfg.gate_chi2, cfg.evidence_agreement
        )
        for r in seg:
            X = se2(*r["evidence_err"])
            ev.add(OffsetSample(r["stamp"], X, np.asarray(r["evidence_cov"]), no_drift, places(r)))
            f = ev.fused(r["stamp"])
            e = log_left(f.X, np.eye(3))
            out.append((r["distance_m"], float(e @ np.linalg.solve(f.covariance, e))))
    return out


def main(
    records: list[Path] = typer.Argument(..., exists=True, dir_okay=False, help="record files rho is chosen on"),
    check: list[Path] = typer.Option([], exists=True, dir_okay=False, help="held-out record files it is checked on"),
    out: Path | None = typer.Option(
        None,
        help="OUT.json, OUT.md, OUT.png (default under out/; under docs/ with --record)",
    ),
    record: bool = typer.Option(False, "--record", help=RECORD_HELP),
) -> None:
    out = out or output_path("docs/tracking/evidence_correlation", record)
    cfg = TrackConfig()
    near_m, apart_m = cfg.evidence_same_place_m, cfg.evidence_same_place_m + cfg.evidence_decorrelation_m
    sets, per_sequence, loaded = {}, {}, {}
    for path in [*records, *check]:
        role = "check" if path in check else "choose"
        rows = loaded[path] = load(path)
        for name in dict.fromkeys(r["sequence"] for r in rows):
            seq = segments([r for r in rows if r["sequence"] == name])
            far = [[r for r in s if r["distance_m"] >= FAR_M] for s in seq]  # the far band alone, too
            for label, part in ((name, seq), (f"{name} ({FAR_M:g}+ m)", far)):
                if sum(len(s) for s in part) >= MIN_FRAMES:
                    shared, _, square = moments(part, cfg.evidence_window_s, hi_m=near_m)
                    apart, n_apart, _ = moments(part, cfg.evidence_window_s, lo_m=apart_m)
                    per_sequence[f"{path.name}: {label}"] = {
                        "role": role,
                        "shared": shared,
                        "shared_apart": apart if n_apart >= MIN_FRAMES else None,
                        "square": square,
                    }

    # The model's near and far rho must cover the largest product of any sequence and axis they are chosen on.
    def largest(role: str, key: str) -> float:
        return max((max(c[key]) for c in per_sequence.values() if c["role"] == role and c[key]), default=0.0)

    largest_near = {r: largest(r, "shared") for r in ("choose", "check")}
    largest_apart = {r: largest(r, "shared_apart") for r in ("choose", "check")}
    chosen = float(min(1.0, np.ceil(round(largest_near["choose"], 2) * 10) / 10))
    chosen_far = float(min(chosen, np.ceil(round(largest_apart["choose"], 2) * 10) / 10))
    model = SharedError(chosen, chosen_far, cfg.evidence_same_place_m, cfg.evidence_decorrelation_m)
    configured = shared_error(cfg)
    one_frame = cfg.model_copy(update={"evidence_max_frames": 1})
    for path, rows in loaded.items():
        segs = segments(rows)
        if not sum(len(s) for s in segs):
            raise typer.BadParameter(f"{path}: no frame with evidence_err (record with odometry on)")
        covered = {"single frame": share_inside(fused_d2(segs, SharedError(0.0), one_frame))}
        by_band: dict[str, dict[str, float]] = {}
        runs = {f"rho {rho:g}": SharedError(rho) for rho in RHOS} | {"place model": model, "configured": configured}
        for key, shared in runs.items():
            d2s = fused_d2(segs, shared, cfg)
            covered[key] = share_inside(d2s)
            for lo, hi in BANDS:
                name = f"{lo:g}-{hi:g} m" if hi < 1e9 else f"{lo:g}+ m"
                by_band.setdefault(name, {})[key] = share_inside([x for x in d2s if lo <= x[0] < hi])
        shared, _, square = moments(segs, cfg.evidence_window_s, hi_m=near_m)
        apart, n_apart, _ = moments(segs, cfg.evidence_window_s, lo_m=apart_m)
        sets[str(path)] = {
            "role": "check" if path in check else "choose",
            "frames": sum(len(s) for s in segs),
            "tracks": len(segs),
            "shared_yaw_x_y": shared,
            "shared_apart_yaw_x_y": apart if n_apart else None,
            "square_yaw_x_y": square,
            "share_within_chi2_99": covered,
            "share_within_chi2_99_by_band": by_band,
        }
    command = "python benchmarks/evidence_correlation.py " + " ".join(str(p) for p in records)
    command += "".join(f" --check {p}" for p in check) + f" --out {out}"
    body = {"command": command, "window_s": cfg.evidence_window_s, "max_frames": cfg.evidence_max_frames}
    body |= {"same_place_m": near_m, "apart_m": apart_m, "sets": sets, "per_sequence": per_sequence}
    body |= {"largest_shared": largest_near, "largest_shared_apart": largest_apart}
    body |= {"chosen_rho": chosen, "chosen_rho_far": chosen_far}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(body, indent=1) + "\n")
    lines = [
        f"Made by `{command}`. Frames at most {cfg.evidence_window_s:g} s apart in one track: per axis (yaw / x / y)",
        f"the mean product of two frames' whitened errors, for pairs whose cars moved at most {near_m:g} m between",
        f"them (shared) and at least {apart_m:g} m (apart), and a frame's mean square (1: an exact covariance); the",
        f"share of fused errors inside their chi2(3) 99 % ellipsoid, fused as the stream fuses them (up to "
        f"{cfg.evidence_max_frames} frames): with rho 0 and with the place model chosen here (near {chosen:g}, far "
        f"{chosen_far:g}).",
        "",
        "| set | role | frames | shared yaw / x / y | apart yaw / x / y | square yaw / x / y | inside 99 %: one frame "
        "| fused, rho 0 | fused, place model |",
        "| --- | --- | ---: | --- | --- | --- | ---: | ---: | ---: |",
    ]
    for name, o in sets.items():
        c, a, q, cov = o["shared_yaw_x_y"], o["shared_apart_yaw_x_y"], o["square_yaw_x_y"], o["share_within_chi2_99"]
        lines.append(
            f"| {name} | {o['role']} | {o['frames']} | {_three(c)} | {'-' if a is None else _three(a)} | {_three(q)} | "
            f"{cov['single frame']:.3f} | {cov['rho 0']:.3f} | {cov['place model']:.3f} |"
        )
    lines += [
        "",
        "| sequence (at least 20 frames; alone beyond 70 m too) | role | shared yaw / x / y | apart yaw / x / y | "
        "square yaw / x / y |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, o in per_sequence.items():
        a = o["shared_apart"]
        apart = "-" if a is None else _three(a)
        lines.append(f"| {name} | {o['role']} | {_three(o['shared'])} | {apart} | {_three(o['square'])} |")

    def verdict(role_key: dict, value: float) -> str:
        return "within" if role_key["check"] <= value else "BEYOND"

    lines += [
        "",
        f"Largest shared product of a sequence in one place: {largest_near['choose']:.2f} where rho is chosen, so "
        f"**near rho {chosen:g}**; {largest_near['check']:.2f} on the held-out sets ({verdict(largest_near, chosen)} "
        f"it). Apart: {largest_apart['choose']:.2f}, so **far rho {chosen_far:g}**; {largest_apart['check']:.2f} "
        f"held out ({verdict(largest_apart, chosen_far)} it).",
    ]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    plot(sets, out.with_suffix(".png"))
    print("\n".join(lines))


def share_inside(d2s: list[tuple[float, float]]) -> float:
    return float(np.mean([d2 <= CHI2_3_99 for _, d2 in d2s])) if d2s else float("nan")


def _three(v: list[float]) -> str:
    return " / ".join(f"{x:.2f}" for x in v)


def plot(sets: dict[str, dict], path: Path) -> None:
    """Per set, the share of fused errors inside their 99 % ellipsoid against the rho assumed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for name, o in sets.items():
        shares = {k: v for k, v in o["share_within_chi2_99"].items() if k.startswith("rho")}
        line = ax.plot([float(k.split()[1]) for k in shares], list(shares.values()), "o-", label=Path(name).stem)
        ax.axhline(o["share_within_chi2_99"]["place model"], color=line[0].get_color(), ls="--", lw=0.8)
    ax.axhline(0.99, color="0.6", ls=":", lw=0.8, label="nominal 0.99")
    ax.set_xlabel("rho (one correlation assumed between frames; dashed: the place model)")
    ax.set_ylabel("fused errors inside chi2(3) 99 %")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    typer.run(main)
