"""``bb-align real-pairs``: the real-pair benchmark (bb_align.lab.realpairs), registered into the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("real-pairs")
    def real_pairs(
        data: Path = typer.Argument(
            Path("../shared/data"), file_okay=False, help="folder of real scans and their reference poses"
        ),
        out: Path | None = typer.Option(
            None, file_okay=False, help="where the tables and plot go (default: out/real_pairs; --record: docs/)"
        ),
        record: bool = typer.Option(
            False, "--record", help="write into docs/real_pairs (the recorded output the docs cite)"
        ),
        group: list[str] = typer.Option(
            [], "--group", help="only these groups: far, near, no_overlap (repeatable; default: all)"
        ),
        config: Path | None = typer.Option(
            None, exists=True, dir_okay=False, help="an AlignConfig as JSON or YAML (`bb-align config --dump`)"
        ),
        quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    ) -> None:
        """Align every real pair under DATA without and with a seeded 2 m / 2 deg prior; write the per-pair table,
        the summary and a plot to OUT (docs/real_pairs.md explains the scoring)."""
        from bb_align.io.config_file import load_align_config
        from bb_align.lab import realpairs
        from bb_align.lab.recording import output_path

        out = out or output_path("docs/real_pairs", record)

        if not data.is_dir():
            raise typer.BadParameter(f"{data} is not a folder of real scans", param_hint="DATA")
        unknown = set(group) - {"far", "near", "no_overlap"}
        if unknown:
            raise typer.BadParameter(
                f"unknown group(s) {sorted(unknown)}: use far, near, no_overlap", param_hint="--group"
            )
        try:
            cfg = load_align_config(config)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--config") from None
        records = realpairs.run(data, cfg, set(group) or None, progress=not quiet)
        if not records:
            raise typer.BadParameter(f"no real pairs found under {data}", param_hint="DATA")
        command = "bb-align real-pairs " + " ".join([str(data), "--out", str(out)] + [f"--group {g}" for g in group])
        summary = realpairs.write(records, out, command)
        typer.echo(json.dumps(summary, indent=2))
        typer.echo(f"tables: {out / 'README.md'}  plot: {out / 'errors.png'}")
