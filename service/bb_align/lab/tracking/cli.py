"""`bb-align track`: replay swept two-car sequences through the follower the service runs; summary and figures."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from bb_align.io.defaults import DESKEW_DEFAULT, DESKEW_HELP


def register(app: typer.Typer) -> None:
    @app.command("track")
    def track_cmd(
        root: Path = typer.Argument(..., exists=True, file_okay=False, help="sequences (e.g. `bb-align sim --sweep`)"),
        json_out: Path | None = typer.Option(None, "--json", help="write the summary JSON here"),
        plots: Path | None = typer.Option(None, "--plots", file_okay=False, help="write PNG figures here"),
        records_out: Path | None = typer.Option(None, "--records", help="write every frame's record (JSON lines)"),
        odometry: bool = typer.Option(True, "--odometry/--no-odometry", help="fuse the yaml's odometry_pose"),
        gnss: bool = typer.Option(True, "--gnss/--no-gnss", help="the yaml's gnss_pose as the acquisitions' prior"),
        deskew: bool = typer.Option(DESKEW_DEFAULT, "--deskew/--no-deskew", help=DESKEW_HELP),
        limit: int | None = typer.Option(None, "--limit", min=1, help="replay at most this many sequences"),
        max_frames: int | None = typer.Option(None, "--frames", min=1, help="only the first frames of each"),
        workers: int = typer.Option(2, "--workers", min=1, help="processes (one sequence each)"),
        config: Path | None = typer.Option(None, "--config", help="an AlignConfig as JSON or YAML (track: .track)"),
    ) -> None:
        """Replay every sequence under ROOT frame by frame through the engine's tracker (acquire, then refine from
        the prediction and fuse) and measure it against the truth: accuracy by distance, wrong answers, whether
        the 3-sigma bound holds the true error, lock losses, time per tracked and per acquired frame."""
        from bb_align.io.config_file import load_align_config
        from bb_align.io.dataset import find_scenarios

        from ..sim.writer import run_pool
        from .plots import plot_by_distance, plot_sequence
        from .replay import ReplayConfig, _replay_star
        from .summary import format_summary, summarize

        try:
            cfg = ReplayConfig(
                align=load_align_config(config),
                use_odometry=odometry,
                use_gnss=gnss,
                deskew=deskew,
                max_frames=max_frames,
            )
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--config") from None
        scenarios = find_scenarios(root)[:limit]
        if not scenarios:
            typer.echo(f"no sequence folders under {root}", err=True)
            raise typer.Exit(2)
        per_sequence = run_pool(
            _replay_star, [(name, path, cfg) for name, path in scenarios], workers, "replaying", "sequence"
        )
        records = [r for seq in per_sequence for r in seq]
        summary = summarize(records)
        summary["config"] = {
            "root": str(root),
            "odometry": odometry,
            "gnss": gnss,
            "track": cfg.align.track.model_dump(),
        }
        typer.echo(format_summary(summary))
        if json_out:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps(summary, indent=2))
        if records_out:
            records_out.parent.mkdir(parents=True, exist_ok=True)
            records_out.write_text("".join(json.dumps(r) + "\n" for r in records))
        if plots:
            plots.mkdir(parents=True, exist_ok=True)
            plot_by_distance(summary, plots / "tracking_by_distance.png")
            for seq in per_sequence:
                if seq:
                    plot_sequence(seq, plots / f"track_{seq[0]['sequence'].replace('/', '_')}.png")
