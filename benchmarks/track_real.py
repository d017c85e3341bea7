"""Tracking on the real 10 Hz KITTI runs in ../shared/data (bb_align.lab.tracking.real_runs says how two cars are
made of one car's sweeps): the follower through every step, with and without odometry, with and without a
GNSS-grade reported pose (a seeded 2 m / 2 deg random walk), every answer scored against the runs' reference poses.

    python benchmarks/track_real.py --data ../shared/data --out docs/tracking/real_runs

Writes OUT.json (summary and every step), OUT.md (the table) and OUT.png (error of every answer by step, the
successful ones filled). Exit 0 when no successful answer was wrong (off by more than 1 m or 1 deg), 1 otherwise.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer
from tqdm import tqdm

from bb_align.lab.recording import RECORD_HELP, output_path
from bb_align.lab.tracking.real_runs import RUNS, folders, records, summary, track_run


def table(rows: dict[str, dict]) -> str:
    lines = [
        "| run | odometry | GNSS pose | steps | successful | wrong | worst successful error | refused (reason: steps) "
        "|",
        "| --- | --- | --- | ---: | ---: | ---: | --- | --- |",
    ]
    for key, o in rows.items():
        run, odo, gnss = key.split(" ")
        worst = f"{o['worst_m']:.2f} m / {o['worst_deg']:.2f} deg" if o["successful"] else "-"
        refused = ", ".join(f"{k}: {v}" for k, v in sorted(o.get("refused", {}).items())) or "-"
        lines.append(
            f"| {run} | {odo} | {gnss} | {o['steps']} | {o['successful']} | {o['wrong']} | {worst} | {refused} |"
        )
    return "\n".join(lines) + "\n"


def plot(all_steps: dict[str, list], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = list(dict.fromkeys(k.split(" ")[0] for k in all_steps))
    fig, axes = plt.subplots(4, len(runs), figsize=(4.2 * len(runs), 11), sharey=True, squeeze=False)
    for key, steps in all_steps.items():
        run, odo, gnss = key.split(" ")
        ax = axes[2 * (odo != "with") + (gnss != "with")][runs.index(run)]
        ax.semilogy([s.step for s in steps], [max(s.t_err_m, 1e-3) for s in steps], "-", color="0.75", lw=0.8)
        for ok, style, colour, label in ((True, "o", "tab:blue", "successful"), (False, "x", "tab:red", "refused")):
            pts = [(s.step, max(s.t_err_m, 1e-3)) for s in steps if s.success == ok]
            if pts:
                ax.semilogy(*zip(*pts), style, color=colour, ms=4, label=label)
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_title(f"{run}, {odo} odometry, {gnss} GNSS", fontsize=9)
        ax.set_xlabel("step (0.1 s)")
        ax.legend(fontsize=7, loc="upper left")
    for row in axes:
        row[0].set_ylabel("error of the answer's pose, m")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(
    data: Path = typer.Option(Path("../shared/data"), exists=True, file_okay=False),
    out: Path | None = typer.Option(
        None,
        help="OUT.json, OUT.md and OUT.png (default: out/tracking/real_runs; docs/tracking/real_runs with --record)",
    ),
    record: bool = typer.Option(False, "--record", help=RECORD_HELP),
    laps: int = typer.Option(3, min=1, max=10, help="passes over frames 0-9 (forward, back, ...)"),
) -> None:
    out = out or output_path("docs/tracking/real_runs", record)
    all_steps: dict[str, list] = {}
    jobs = [
        (run, odo, gnss)
        for run in RUNS
        if all(f.is_dir() for f in folders(data, run))
        for odo in (True, False)
        for gnss in (True, False)
    ]
    for run, odo, gnss in tqdm(jobs, desc="real runs", unit="run"):
        key = f"{run} {'with' if odo else 'without'} {'with' if gnss else 'without'}"
        all_steps[key] = track_run(data, run, laps=laps, odometry=odo, gnss=gnss)
    rows = {key: summary(steps)[key.split(" ")[0]] for key, steps in all_steps.items()}
    out.parent.mkdir(parents=True, exist_ok=True)
    command = f"python benchmarks/track_real.py --data {data} --out {out}"
    out.with_suffix(".md").write_text(f"Made by `{command}`.\n\n" + table(rows))
    body = {"command": command, "summary": rows, "steps": {k: records(v) for k, v in all_steps.items()}}
    out.with_suffix(".json").write_text(json.dumps(body, indent=1) + "\n")
    plot(all_steps, out.with_suffix(".png"))
    print(table(rows))
    raise typer.Exit(1 if any(o["wrong"] for o in rows.values()) else 0)


if __name__ == "__main__":
    typer.run(main)
