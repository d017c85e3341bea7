"""``bb-align bench``: engine vs baseline stage timings, accuracy cross-check, memory, and service throughput."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import typer

DEFAULT_BOUNDS = Path("docs/stage_bounds.json")  # benchmarks/stage_bounds.py --record writes it (a checkout's docs)


def _progress(items, label: str):
    from tqdm import tqdm

    return tqdm(list(items), desc=label, file=sys.stderr, leave=False, dynamic_ncols=True)


def bench(
    json_out: Path | None = typer.Option(None, "--json", help="write the full report as JSON here"),
    runs: int | None = typer.Option(None, min=1, help="timed passes over the workload [10; --quick 3]"),
    quick: bool = typer.Option(False, "--quick", help="2 pairs, 3 runs, short service runs (1 and 4 peers)"),
    plot: Path | None = typer.Option(None, "--plot", help="write the stage-breakdown figure (PNG) here"),
    markdown: Path | None = typer.Option(
        None, "--markdown", help="also write the printed report (Markdown tables) here"
    ),
    no_service: bool = typer.Option(False, "--no-service", help="skip the service throughput part"),
    data: Path | None = typer.Option(
        None,
        "--data",
        exists=True,
        file_okay=False,
        help="real scans in the OPV2V/V2V4Real layout instead of the simulator",
    ),
    max_pairs: int = typer.Option(12, min=1, help="with --data: at most this many ego/peer pairs"),
    baseline_runs: int = typer.Option(1, min=1, help="timed passes of the (slow) baseline"),
    warmup: int = typer.Option(1, min=0, help="untimed engine passes first"),
    peers: str | None = typer.Option(None, help="service runs: comma-separated peer counts [1,4,8; --quick 1,4]"),
    service_seconds: float | None = typer.Option(None, min=1.0, help="measured seconds per service run [10]"),
    rate_hz: float = typer.Option(10.0, min=0.5, max=50.0, help="frame rate of the ego and every peer"),
    workers: int = typer.Option(2, min=1, max=16, help="service engine worker threads"),
    pose_sigma_m: float = typer.Option(2.0, min=0.0, help="service runs: reported-pose noise, metres (1 sigma)"),
    pose_sigma_deg: float = typer.Option(2.0, min=0.0, help="service runs: reported-pose yaw noise, degrees"),
    no_pose: bool = typer.Option(False, "--no-pose", help="service runs: frames carry no reported pose"),
    range_m: float | None = typer.Option(None, help="BV half width R in metres [config default, 80]"),
    resolution_m: float | None = typer.Option(None, help="BV cell size in metres [config default, 0.4]"),
    bounds: Path | None = typer.Option(
        None,
        "--bounds",
        help="print the hot path's stages beside these lower bounds (benchmarks/stage_bounds.py --record's JSON) "
        "[docs/stage_bounds.json when it exists here]",
    ),
    engine_threads: int | None = typer.Option(
        None,
        min=1,
        max=16,
        help="threads inside one engine call (MIM orientations, descriptor keypoints, "
        "matching queries, pose vote, dense verification) [config default, 2]; 1 times the engine on one core",
    ),
) -> None:
    """Time the engine per stage against the in-benchmark baseline (same inputs, same run), check they agree,
    and measure the service's sustained throughput with 1, 4 and 8 peers over Zenoh on loopback."""
    from bb_align.engine.config import AlignConfig

    from .run import run_benchmark
    from .workload import data_workload, sim_workload

    config = AlignConfig()
    bev_over = {k: v for k, v in (("range_m", range_m), ("resolution_m", resolution_m)) if v is not None}
    if bev_over:
        try:
            config = config.model_copy(update={"bev": type(config.bev)(**{**config.bev.model_dump(), **bev_over})})
        except ValueError as e:
            raise typer.BadParameter(str(e)) from None
    if engine_threads is not None:
        config = config.model_copy(
            update={
                "mim": config.mim.model_copy(update={"threads": engine_threads}),
                "features": config.features.model_copy(update={"threads": engine_threads}),
                "match": config.match.model_copy(update={"threads": engine_threads}),
                "acquire": config.acquire.model_copy(update={"threads": engine_threads}),
            }
        )
    runs = runs or (3 if quick else 10)
    if peers is None:
        peer_counts = [1, 4] if quick else [1, 4, 8]
    else:
        try:
            peer_counts = sorted({int(p) for p in peers.split(",") if p.strip()})
        except ValueError:
            raise typer.BadParameter(f"--peers must be comma-separated integers, got {peers!r}") from None
        if not peer_counts or min(peer_counts) < 1 or max(peer_counts) > 32:
            raise typer.BadParameter(f"--peers counts must be within 1..32, got {peers!r}")
    seconds = service_seconds or (3.0 if quick else 10.0)
    from .markdown import load_bounds

    bounds_path = bounds if bounds is not None else DEFAULT_BOUNDS
    stage_bounds = None
    if bounds is not None or bounds_path.is_file():
        try:
            stage_bounds = load_bounds(bounds_path)
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--bounds") from None

    typer.echo("building the workload ...", err=True)
    if data is not None:
        workload = data_workload(
            data, config, max_pairs=2 if quick else max_pairs, progress=lambda it: _progress(it, "workload")
        )
    else:
        workload = sim_workload(config, quick=quick, progress=lambda it: _progress(it, "workload"))
    report = run_benchmark(workload, config, runs=runs, warmup=warmup, baseline_runs=baseline_runs, progress=_progress)
    report["service"] = None
    report["bounds"] = stage_bounds
    if not no_service:
        from .throughput import ServiceBenchConfig, measure_service

        sb = ServiceBenchConfig(
            peer_counts=peer_counts,
            seconds=seconds,
            rate_hz=rate_hz,
            workers=workers,
            frames=3 if quick else 6,
            send_pose=not no_pose,
            pose_sigma_m=pose_sigma_m,
            pose_sigma_deg=pose_sigma_deg,
        )
        report["service"] = measure_service(sb, config, progress=_progress)
    report["command"] = "bb-align " + " ".join(sys.argv[1:])
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(report, indent=1, default=float))
    if plot is not None:
        from .plot import plot_report

        plot_report(report, plot)
    from .markdown import report_markdown

    tables = report_markdown(report)  # one report: printed here, and the same text in --markdown's file
    if markdown is not None:
        markdown.parent.mkdir(parents=True, exist_ok=True)
        markdown.write_text(tables)
    typer.echo(tables)
    if json_out is not None:
        typer.echo(f"report: {json_out}")
    if plot is not None:
        typer.echo(f"plot: {plot}")
    if markdown is not None:
        typer.echo(f"markdown: {markdown}")


def register(app: typer.Typer) -> None:
    app.command("bench")(bench)
