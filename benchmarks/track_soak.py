"""Tracking soak with a crash: a real service, N simulated peers at 10 Hz with tracking and odometry, odometry
jumps, ``kill -9`` of the service mid-stream and a restart; every answer checked against the truth.

    python benchmarks/track_soak.py --seconds 120 --json out/soak.json --plot out/soak.png      # development
    python benchmarks/track_soak.py --seconds 1800 --json docs/tracking/soak.json --plot docs/tracking/soak.png

See bb_align.lab.tracking.soak. Exit 0 when every check passed (no wrong success, every peer answered again after
the restart), 1 otherwise.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import typer
from tqdm import tqdm

from bb_align.lab.tracking.soak import TrackSoakConfig, plot_track_soak, run_track_soak, summary_lines


def main(
    seconds: float = typer.Option(1800.0, min=10, max=7200, help="publishing time"),
    peers: int = typer.Option(8, min=1, max=16),
    rate_hz: float = typer.Option(10.0, min=1, max=20),
    kill_at: float = typer.Option(0.6, min=0.05, max=0.95, help="kill -9 the service at this share of the run"),
    frames: int = typer.Option(80, min=2, max=400, help="simulated frames per car (replayed back and forth)"),
    seed: int = typer.Option(404),
    workers: int = typer.Option(2, min=1, max=16),
    json_out: Path | None = typer.Option(None, "--json"),
    plot: Path | None = typer.Option(None),
    log_dir: Path | None = typer.Option(None, help="keep the service's logs here (default: a temporary folder)"),
    cache: Path | None = typer.Option(None, help="keep the simulated cars here between runs"),
    rows: Path | None = typer.Option(None, help="write every result (truth, error) as JSON lines"),
) -> None:
    cfg = TrackSoakConfig(
        seconds=seconds, peers=peers, rate_hz=rate_hz, kill_at=kill_at, frames=frames, seed=seed, workers=workers
    )

    def progress(items, desc):
        return tqdm(items, desc=desc, mininterval=5.0)

    with tempfile.TemporaryDirectory(prefix="bbalign-tracksoak-") as tmp:
        logs = Path(log_dir or tmp)
        logs.mkdir(parents=True, exist_ok=True)
        rep = run_track_soak(cfg, logs, progress, cache=cache, rows_out=rows)
    for line in summary_lines(rep):
        typer.echo(line)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(rep, indent=1, default=str))
        typer.echo(f"report: {json_out}")
    if plot is not None:
        plot.parent.mkdir(parents=True, exist_ok=True)
        plot_track_soak(rep, plot)
        typer.echo(f"figure: {plot}")
    raise typer.Exit(0 if all(rep["checks"].values()) else 1)


if __name__ == "__main__":
    typer.run(main)
