"""The swept sequences replayed through a real service: `bb-align sim --sweep` sequences sent frame by frame to a
`bb-align serve` child process on loopback (REST /v1/align, the ego frame inline, tracking and odometry on, one
peer id per sequence), every successful answer checked against the truth and scored as `bb-align track` scores.

    bb-align sim out/sweep23 --sweep --scenarios 5 --frames 150 --seed 23
    python benchmarks/track_through_service.py out/sweep23 --json docs/tracking/through_service_seed23.json \\
        --plot docs/tracking/through_service_seed23.png

Exit 0 when no successful answer was wrong (off by more than 1 m or 1 deg), 1 otherwise.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import httpx
import typer
from tqdm import tqdm

from bb_align.lab.harness import free_port, start_service
from bb_align.lab.tracking.plots import plot_by_distance
from bb_align.lab.tracking.summary import format_summary, summarize
from bb_align.lab.tracking.through_service import replay_through_service, wrong_answers


def main(
    root: Path = typer.Argument(..., exists=True, file_okay=False),
    json_out: Path | None = typer.Option(None, "--json", help="summary, wrong answers and every record"),
    plot: Path | None = typer.Option(None, help="accuracy by distance (PNG)"),
    limit: int | None = typer.Option(None, min=1, help="at most this many sequences"),
    frames: int | None = typer.Option(None, min=1, help="only the first frames of each sequence"),
    odometry: bool = typer.Option(True, "--odometry/--no-odometry"),
    workers: int = typer.Option(2, min=1),
) -> None:
    from bb_align.server.settings import Settings

    settings = Settings(
        profile="demo",  # the sequences are stamped from 0 s: no receiver-clock window
        host="127.0.0.1",
        port=free_port(),
        workers=workers,
        zenoh={"enabled": False},
        limits={"check_stamp_clock": False, "rest_rate_hz": 1000.0, "rest_burst": 1000.0},
    )
    with tempfile.TemporaryDirectory(prefix="bbalign-through-") as tmp:
        svc = start_service(settings, None, Path(tmp))
        try:
            with httpx.Client(base_url=svc.rest, timeout=300) as http:
                records = replay_through_service(
                    http,
                    root,
                    limit=limit,
                    max_frames=frames,
                    odometry=odometry,
                    progress=lambda items, desc: tqdm(items, desc=desc),
                )
        finally:
            code = svc.stop()
    summary = summarize(records)
    wrong = wrong_answers(records)
    typer.echo(format_summary(summary))
    typer.echo(f"wrong successes: {len(wrong)}; service exit code {code}")
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        out = {"root": str(root), "odometry": odometry, "summary": summary, "wrong": wrong, "records": records}
        json_out.write_text(json.dumps(out, indent=None, default=str))
    if plot is not None:
        plot.parent.mkdir(parents=True, exist_ok=True)
        plot_by_distance(summary, plot)
    raise typer.Exit(0 if not wrong else 1)


if __name__ == "__main__":
    typer.run(main)
