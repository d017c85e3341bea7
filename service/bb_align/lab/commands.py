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
    credential: Path | None = typer.Option(
        None,
        envvar="BBALIGN_AUTH__CREDENTIAL",
        show_default=False,
        help="the ego's credential (bb-align keys issue DIR ego; the variable the service reads): the ego signs "
        "with it, every other car with DIR/<car>.cred, or one issued by DIR/ca.key",
    ),
    ca_cert: Path | None = typer.Option(
        None,
        envvar="BBALIGN_AUTH__CA_CERT",
        show_default=False,
        help="the fleet authority's ca.pub: the service's answers are verified against it [DIR/ca.pub]",
    ),
    key: str | None = typer.Option(
        None,
        envvar="BBALIGN_AUTH__FLEET_KEY",
        show_default=False,
        help="the simpler option: the fleet HMAC key to sign every car's frames with (without a credential)",
    ),
    odometry: bool = typer.Option(False, help="every car sends its odometry (drifting, as in the swept sequences)"),
    odometry_jump: list[str] = typer.Option(
        [],
        metavar="CAR:FRAME:DX,DY",
        help="re-anchor CAR's odometry by (DX, DY) m from FRAME on, as a relocalisation does (implies --odometry; "
        "repeatable), e.g. ego:15:4,4",
    ),
    odometry_lie: list[str] = typer.Option(
        [],
        metavar="CAR:FRAME:DX,DY",
        help="CAR's odometry drifts by a further (DX, DY) m every frame from FRAME on: a car lying about its motion "
        "(implies --odometry; repeatable)",
    ),
) -> None:
    """Drive a simulated N-car scene through a running service over Zenoh; table of true vs recovered poses.

    Frames are signed with per-vehicle Ed25519 credentials when BBALIGN_AUTH__CREDENTIAL is set (as for `bb-align
    serve`), else with the fleet HMAC key when one is given, else not at all (a service started with --demo)."""
    from bb_align.lab.demo import demo_signers, run_demo
    from bb_align.lab.tracking.faults import OdometryFault

    try:
        faults = tuple(OdometryFault.parse(t) for t in odometry_jump)
        faults += tuple(OdometryFault.parse(t, ramp=True) for t in odometry_lie)
        signers = demo_signers(ego_id, agents, credential, ca_cert, key)
    except (OSError, ValueError) as e:
        typer.secho(f"bb-align demo: {e}", err=True, fg="red")
        raise typer.Exit(2) from None
    if not _service_listens(connect, prefix, ego_id):
        typer.secho(
            f"bb-align demo: no service takes frames on {prefix}/frames/{ego_id} via {', '.join(connect)}; start "
            "one first (`make run`, i.e. `bb-align serve --demo`), or point --connect at it",
            err=True,
            fg="red",
        )
        raise typer.Exit(1)

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
        odometry=odometry,
        faults=faults,
        **signers,
    )
    if summary["results"] == 0:
        raise typer.Exit(1)


def _service_listens(connect: list[str], prefix: str, ego_id: str, timeout_s: float = 5.0) -> bool:
    """Whether a service subscribes to the ego's frame key, checked before the scene is simulated (it takes a few
    seconds a frame, wasted when nothing listens)."""
    from bb_align_client import ZenohPeer

    with ZenohPeer(ego_id, connect=connect, prefix=prefix, verify_answers=False) as probe:
        return probe.wait_for_subscriber(timeout=timeout_s)


def register(app: typer.Typer) -> None:
    """Add ``demo``. ``soak`` (bb_align.lab.soak) is registered lazily by bb_align.cli: its module is costly."""
    app.command()(demo)
