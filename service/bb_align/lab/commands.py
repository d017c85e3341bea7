"""``bb-align demo`` and ``bb-align soak``: a running service driven by simulated cars (registered into the CLI)."""

from __future__ import annotations

from pathlib import Path

import typer


def demo(
    connect: list[str] = typer.Option(
        ["tcp/127.0.0.1:7447"], "--connect", metavar="ENDPOINT", help="the service's Zenoh endpoint (repeatable)"
    ),
    ego_id: str = typer.Option("ego", help="the service's ego id (the simulated agent 0 publishes under it)"),
    agents: int = typer.Option(2, min=2, max=8, help="cars in the scene (agent 0 is the ego)"),
    frames: int = typer.Option(10, min=1, max=500, help="frames to drive"),
    seed: int = typer.Option(0, help="scene seed"),
    distance_m: float | None = typer.Option(30.0, help="spacing between the cars (None: drawn)"),
    rate_hz: float = typer.Option(0.0, min=0, help="publish rate; 0: wait for each frame's results first"),
    timeout_s: float = typer.Option(30.0, min=0.1, help="longest wait for one frame's results"),
    prefix: str = typer.Option("bbalign", help="Zenoh key prefix"),
    range_m: float | None = typer.Option(None, help="BV half width sent by the cars (default: engine's)"),
    json_out: Path | None = typer.Option(None, "--json", help="also write every row and the summary as JSON"),
    plot: Path | None = typer.Option(None, help="write a PNG of the errors and latencies per frame"),
    key: str | None = typer.Option(
        None,
        envvar="BBALIGN_AUTH__FLEET_KEY",
        show_default=False,
        help="fleet key to sign the frames with (a service not in --demo needs it)",
    ),
) -> None:
    """Drive a simulated N-car scene through a running service over Zenoh; table of true vs recovered poses."""
    from bb_align.lab.demo import run_demo

    summary = run_demo(
        connect=connect,
        ego_id=ego_id,
        n_agents=agents,
        n_frames=frames,
        seed=seed,
        distance_m=distance_m,
        rate_hz=rate_hz,
        timeout_s=timeout_s,
        prefix=prefix,
        range_m=range_m,
        json_out=json_out,
        plot=plot,
        key=key,
    )
    if summary["results"] == 0:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    from .soak import soak

    app.command()(demo)
    app.command()(soak)
