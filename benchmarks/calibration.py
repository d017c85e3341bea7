"""Are the answers' covariances honest? The share of true errors within k sigma, by range band, on every set
that records an answer's covariance and its true error:

    python benchmarks/calibration.py --out docs/calibration \
        --single "sim, no prior=docs/accuracy/pairs.jsonl" --single "sim, prior=docs/accuracy_prior/pairs.jsonl" \
        --real docs/real_pairs/records.jsonl --tracked "sim sweeps=out/sweep7373.jsonl" \
        --runs docs/tracking/real_runs.json

k sigma in three dimensions: the squared Mahalanobis distance of the error (yaw rad, tx m, ty m) under the answer's
covariance within k^2; an honest covariance has 19.9 / 73.9 / 97.1 % of its errors within 1 / 2 / 3 sigma
(chi2 with 3 degrees of freedom). More than that: pessimistic (the answer is better than it says); less:
over-confident. Two tables: the successful answers (what the promise is about), and every answer with a covariance,
refused ones too; poses farther than 5 m or 5 deg from the truth are left out of both (another mode: what the
answer rule and the rivals are for, not the covariance's spread). The real single pairs record only the 1-sigma
along and across the street and in yaw (their correlations are left out), and
the real references carry their own error (KITTI 00's about 0.5 m along the street): read those rows with that.
Writes OUT.md, OUT.json and OUT.png.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer
from scipy import stats

from bb_align.lab.recording import RECORD_HELP, output_path

KS = (1, 2, 3)
NOMINAL = [float(stats.chi2.cdf(k * k, 3)) for k in KS]
BANDS = ((0.0, 40.0), (40.0, 70.0), (70.0, 1e9))
FAR_OFF_M, FAR_OFF_DEG = 5.0, 5.0


def _band(d: float) -> str:
    lo, hi = next(b for b in BANDS if b[0] <= d < b[1])
    return f"{lo:g}-{hi:g} m" if hi < 1e9 else f"{lo:g}+ m"


def _far_off(r: dict) -> bool:
    """Another mode than the truth's (or no pose at all): not the covariance's to cover."""
    t, y = r.get("t_err_m"), r.get("r_err_deg")
    return t is None or y is None or t > FAR_OFF_M or y > FAR_OFF_DEG


def _d2(err, cov) -> float | None:
    e, C = np.asarray(err, float), np.asarray(cov, float)
    if not np.all(np.isfinite(C)) or np.linalg.eigvalsh(C).min() <= 0 or np.any(np.diag(C) > 1e4):
        return None
    return float(e @ np.linalg.solve(C, e))


def records(path: Path, err_key: str) -> list[tuple[float, float, bool]]:
    """(distance, d2, success) of every answer with a covariance in JSON lines: `bb-align eval --records`
    (``err_key`` error_params) or `bb-align track --records` (err)."""
    out = []
    for line in path.read_text().splitlines():
        r = json.loads(line)
        if r.get("covariance") is None or _far_off(r):
            continue
        if (d2 := _d2(r[err_key], r["covariance"])) is not None:
            out.append((r["distance_m"], d2, bool(r["success"])))
    return out


def real_pairs(path: Path) -> dict[str, list[tuple[float, float, bool]]]:
    """(distance, d2) per prior path from `bb-align real-pairs` records (along / across / yaw sigmas)."""
    out: dict[str, list] = {}
    for line in path.read_text().splitlines():
        r = json.loads(line)
        if r.get("sigma_along_m") is None or _far_off(r):
            continue
        d2 = (
            (r["along_err_m"] / r["sigma_along_m"]) ** 2
            + (r["across_err_m"] / r["sigma_across_m"]) ** 2
            + (r["r_err_deg"] / r["sigma_yaw_deg"]) ** 2
        )
        name = "real pairs, " + ("prior" if r["prior"] else "no prior")
        out.setdefault(name, []).append((r["distance_m"], d2, bool(r["success"])))
    return out


def runs(path: Path) -> dict[str, list[tuple[float, float, bool]]]:
    """(distance, d2) per run row of benchmarks/track_real.py's OUT.json."""
    out: dict[str, list] = {}
    for key, steps in json.loads(path.read_text())["steps"].items():
        run, odo, gnss = key.split(" ")
        name = f"real runs tracked, {odo} odometry, {gnss} GNSS"
        for s in steps:
            if s.get("covariance") is None or _far_off(s):
                continue
            if (d2 := _d2(s["err"], s["covariance"])) is not None:
                out.setdefault(name, []).append((s["distance_m"], d2, bool(s["success"])))
    return out


def table(sets: dict[str, list[tuple[float, float, bool]]], successful: bool) -> tuple[list[str], dict]:
    """Per set and band: the share of errors within 1 / 2 / 3 sigma (only successful answers, or every one)."""
    body: dict = {}
    lines = [
        "| set | band | answers | within 1 sigma | within 2 sigma | within 3 sigma | median d2 |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
        "| (honest) | | | {:.3f} | {:.3f} | {:.3f} | 2.37 |".format(*NOMINAL),
    ]
    for name, pts in sets.items():
        for lo, hi in BANDS:
            d2 = [d for dist, d, ok in pts if lo <= dist < hi and (ok or not successful)]
            if not d2:
                continue
            shares = [float(np.mean([x <= k * k for x in d2])) for k in KS]
            band = _band(lo)
            body.setdefault(name, {})[band] = {"answers": len(d2), "within": shares, "median_d2": float(np.median(d2))}
            lines.append(
                f"| {name} | {band} | {len(d2)} | {shares[0]:.3f} | {shares[1]:.3f} | {shares[2]:.3f} | "
                f"{np.median(d2):.2f} |"
            )
    return lines, body


def _named(spec: str) -> tuple[str, Path]:
    name, sep, path = spec.partition("=")
    if not sep:
        raise typer.BadParameter(f"{spec!r}: expected NAME=PATH")
    return name, Path(path)


def main(
    out: Path | None = typer.Option(
        None, help="OUT.md, OUT.json and OUT.png (default: out/calibration; docs/calibration with --record)"
    ),
    record: bool = typer.Option(False, "--record", help=RECORD_HELP),
    single_sets: list[str] = typer.Option([], "--single", help="NAME=eval records (JSON lines)"),
    real: Path | None = typer.Option(None, help="bb-align real-pairs records.jsonl"),
    tracked_sets: list[str] = typer.Option([], "--tracked", help="NAME=bb-align track --records file"),
    runs_json: Path | None = typer.Option(None, "--runs", help="benchmarks/track_real.py OUT.json"),
) -> None:
    out = out or output_path("docs/calibration", record)
    sets: dict[str, list] = {}
    for spec in single_sets:
        name, path = _named(spec)
        sets[f"{name} (single pairs)"] = records(path, "error_params")
    if real is not None:
        sets |= real_pairs(real)
    for spec in tracked_sets:
        name, path = _named(spec)
        sets[f"{name} (tracked)"] = records(path, "err")
    if runs_json is not None:
        sets |= runs(runs_json)
    ok_lines, ok_body = table(sets, successful=True)
    all_lines, all_body = table(sets, successful=False)
    out.parent.mkdir(parents=True, exist_ok=True)
    body = {"nominal": NOMINAL, "successful": ok_body, "every_answer": all_body}
    out.with_suffix(".json").write_text(json.dumps(body, indent=1) + "\n")
    command = "python benchmarks/calibration.py " + " ".join(
        [f"--single '{x}'" for x in single_sets]
        + ([f"--real {real}"] if real else [])
        + [f"--tracked '{x}'" for x in tracked_sets]
        + ([f"--runs {runs_json}"] if runs_json else [])
    )
    lines = [
        "# Are the covariances honest?",
        "",
        f"Made by `{command}`.",
        "",
        "The share of answers whose true error lies within k sigma of the answer's own covariance (the squared",
        "Mahalanobis distance of (yaw, tx, ty) within k^2), by range band. An honest covariance has 19.9 / 73.9 /",
        "97.1 % within 1 / 2 / 3 sigma (chi2, 3 dof) and a median d2 of 2.37; more is pessimistic (the answer is",
        "better than it says), less is over-confident. Poses farther than 5 m or 5 deg from the truth (another mode)",
        "are left out. The real single pairs give only the along / across / yaw sigmas, and their references carry",
        "their own error (KITTI 00 about 0.5 m along the street). What `success` promises: README, docs/tracking.md.",
        "",
        "![calibration](calibration.png)",
        "",
        "## Successful answers",
        "",
        *ok_lines,
        "",
        "## Every answer with a covariance, refused ones too",
        "",
        *all_lines,
    ]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    plot(sets, out.with_suffix(".png"))
    print("\n".join(lines))


def plot(sets: dict[str, list], path: Path) -> None:
    """The cumulative share of successful answers' errors within k sigma against the honest chi2(3) curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = np.linspace(0, 4, 200)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.plot(k, stats.chi2.cdf(k**2, 3), "k--", lw=1.2, label="honest (chi2, 3 dof)")
    for name, pts in sets.items():
        d = np.sqrt([x for _, x, ok in pts if ok])
        if len(d):
            ax.plot(k, [np.mean(d <= v) for v in k], lw=1, label=f"{name} ({len(d)})")
    ax.set_xlabel("k (Mahalanobis distance of the true error, sigmas)")
    ax.set_ylabel("share of successful answers within k sigma")
    ax.legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    typer.run(main)
