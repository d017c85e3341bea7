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
exact covariance). The model has one ``rho`` for every axis and place: the largest product of a sequence of the
sets it is chosen on, rounded up to a tenth; the ``--check`` sets (held out) must not exceed it. Then, for each
``rho`` of a grid, every frame's window fused as the stream fuses it, and the share of fused errors inside their
chi2(3) 99 % ellipsoid (the plot). Writes OUT.json, OUT.md and OUT.png.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer

from bb_align.engine.config import TrackConfig
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


def moments(segs: list[list[dict]], window_s: float) -> tuple[list[float], list[float]]:
    """Per axis (yaw, x, y): the mean product of the whitened errors of frame pairs at most window_s apart, and the
    mean square of a frame's whitened error."""
    prods, pairs, squares, frames = np.zeros(3), 0, np.zeros(3), 0
    for seg in segs:
        w = [whitened(r) for r in seg]
        t = [r["stamp"] for r in seg]
        squares, frames = squares + sum(x**2 for x in w), frames + len(w)
        for i in range(len(seg)):
            for j in range(i + 1, len(seg)):
                if t[j] - t[i] > window_s:
                    break
                prods, pairs = prods + w[i] * w[j], pairs + 1
    return (prods / max(pairs, 1)).tolist(), (squares / max(frames, 1)).tolist()


def fused_d2(segs: list[list[dict]], rho: float, window_s: float, max_frames: int) -> list[tuple[float, float]]:
    """(distance m, squared Mahalanobis distance of the fused error) of every frame's window fused with ``rho``."""
    out = []
    for seg in segs:
        for j, r in enumerate(seg):
            win = [q for q in seg[max(0, j - max_frames + 1) : j + 1] if r["stamp"] - q["stamp"] <= window_s]
            info = sum(np.linalg.inv(np.asarray(q["evidence_cov"])) for q in win)
            vec = sum(np.linalg.inv(np.asarray(q["evidence_cov"])) @ np.asarray(q["evidence_err"]) for q in win)
            cov = np.linalg.inv(info) * (1.0 + rho * (len(win) - 1))
            e = np.linalg.solve(info, vec)
            out.append((r["distance_m"], float(e @ np.linalg.solve(cov, e))))
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
    sets, per_sequence = {}, {}
    for path in [*records, *check]:
        role = "check" if path in check else "choose"
        rows = load(path)
        for name in dict.fromkeys(r["sequence"] for r in rows):
            seq = segments([r for r in rows if r["sequence"] == name])
            far = [[r for r in s if r["distance_m"] >= FAR_M] for s in seq]  # the far band alone, too
            for label, part in ((name, seq), (f"{name} ({FAR_M:g}+ m)", far)):
                if sum(len(s) for s in part) >= MIN_FRAMES:
                    shared, square = moments(part, cfg.evidence_window_s)
                    per_sequence[f"{path.name}: {label}"] = {"role": role, "shared": shared, "square": square}
        segs = segments(rows)
        if not sum(len(s) for s in segs):
            raise typer.BadParameter(f"{path}: no frame with evidence_err (record with odometry on)")
        covered = {"single frame": float(np.mean([d2 <= CHI2_3_99 for _, d2 in fused_d2(segs, 0.0, 0.0, 1)]))}
        by_band: dict[str, dict[str, float]] = {}
        for rho in RHOS:
            d2s = fused_d2(segs, rho, cfg.evidence_window_s, cfg.evidence_max_frames)
            covered[f"rho {rho:g}"] = float(np.mean([d2 <= CHI2_3_99 for _, d2 in d2s]))
            for lo, hi in BANDS:
                band = [d2 <= CHI2_3_99 for dist, d2 in d2s if lo <= dist < hi]
                name = f"{lo:g}-{hi:g} m" if hi < 1e9 else f"{lo:g}+ m"
                by_band.setdefault(name, {})[f"{rho:g}"] = float(np.mean(band)) if band else float("nan")
        shared, square = moments(segs, cfg.evidence_window_s)
        sets[str(path)] = {
            "role": role,
            "frames": sum(len(s) for s in segs),
            "tracks": len(segs),
            "shared_yaw_x_y": shared,
            "square_yaw_x_y": square,
            "share_within_chi2_99": covered,
            "share_within_chi2_99_by_band": by_band,
        }
    # The model's one rho must cover the largest product of any sequence and axis it is chosen on.
    largest = {r: max((max(c["shared"]) for c in per_sequence.values() if c["role"] == r), default=0.0)
               for r in ("choose", "check")}  # fmt: skip
    chosen = float(min(1.0, np.ceil(round(largest["choose"], 2) * 10) / 10))
    command = "python benchmarks/evidence_correlation.py " + " ".join(str(p) for p in records)
    command += "".join(f" --check {p}" for p in check) + f" --out {out}"
    body = {"command": command, "window_s": cfg.evidence_window_s, "max_frames": cfg.evidence_max_frames}
    body |= {"sets": sets, "per_sequence": per_sequence, "largest_shared": largest, "chosen_rho": chosen}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(body, indent=1) + "\n")
    lines = [
        f"Made by `{command}`. Frames at most {cfg.evidence_window_s:g} s apart in one track: per axis (yaw / x / y)",
        "the mean product of two frames' whitened errors (shared) and a frame's mean square (1: an exact covariance);",
        f"the share of fused errors inside their chi2(3) 99 % ellipsoid with rho 0 and {chosen:g} (up to "
        f"{cfg.evidence_max_frames} frames).",
        "",
        "| set | role | frames | shared yaw / x / y | square yaw / x / y | inside 99 %: one frame | fused, rho 0 | "
        "fused, chosen rho |",
        "| --- | --- | ---: | --- | --- | ---: | ---: | ---: |",
    ]
    for name, o in sets.items():
        c, q, cov = o["shared_yaw_x_y"], o["square_yaw_x_y"], o["share_within_chi2_99"]
        lines.append(
            f"| {name} | {o['role']} | {o['frames']} | {c[0]:.2f} / {c[1]:.2f} / {c[2]:.2f} | "
            f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} | {cov['single frame']:.3f} | {cov['rho 0']:.3f} | "
            f"{cov[f'rho {chosen:g}']:.3f} |"
        )
    lines += [
        "",
        "| sequence (at least 20 frames; alone beyond 70 m too) | role | shared yaw / x / y | square yaw / x / y |",
        "| --- | --- | --- | --- |",
    ]
    for name, o in per_sequence.items():
        c, q = o["shared"], o["square"]
        lines.append(
            f"| {name} | {o['role']} | {c[0]:.2f} / {c[1]:.2f} / {c[2]:.2f} | {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} |"
        )
    lines += [
        "",
        f"Largest shared product of a sequence: {largest['choose']:.2f} where rho is chosen, so **rho {chosen:g}**; "
        f"{largest['check']:.2f} on the held-out sets ({'within' if largest['check'] <= chosen else 'BEYOND'} it).",
    ]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    plot(sets, out.with_suffix(".png"))
    print("\n".join(lines))


def plot(sets: dict[str, dict], path: Path) -> None:
    """Per set, the share of fused errors inside their 99 % ellipsoid against the rho assumed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for name, o in sets.items():
        shares = {k: v for k, v in o["share_within_chi2_99"].items() if k.startswith("rho")}
        ax.plot([float(k.split()[1]) for k in shares], list(shares.values()), "o-", label=Path(name).stem)
    ax.axhline(0.99, color="0.6", ls=":", lw=0.8, label="nominal 0.99")
    ax.set_xlabel("rho (correlation assumed between frames)")
    ax.set_ylabel("fused errors inside chi2(3) 99 %")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    typer.run(main)
