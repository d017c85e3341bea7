"""``bb-align serve`` and ``bb-align wire-schemas`` (registered into the main CLI)."""

from __future__ import annotations

from pathlib import Path

import typer


def serve(
    ego_id: str | None = typer.Option(None, help="vehicle id of this car's own frames [env BBALIGN_EGO_ID]"),
    host: str | None = typer.Option(None, help="REST bind address [127.0.0.1]"),
    port: int | None = typer.Option(None, help="REST port [8000]"),
    zenoh_listen: list[str] | None = typer.Option(
        None, "--zenoh-listen", metavar="ENDPOINT", help="Zenoh endpoint to listen on (repeatable) [tcp/127.0.0.1:7447]"
    ),
    zenoh_connect: list[str] | None = typer.Option(
        None, "--zenoh-connect", metavar="ENDPOINT", help="Zenoh router/peer to connect to (repeatable)"
    ),
    zenoh_mode: str | None = typer.Option(None, help="peer | client | router [peer]"),
    no_zenoh: bool = typer.Option(False, "--no-zenoh", help="REST only"),
    workers: int | None = typer.Option(None, help="engine worker threads [2]"),
    demo: bool = typer.Option(
        False,
        "--demo",
        help="the embedded demo profile: authentication OFF "
        "(= BBALIGN_PROFILE=demo); otherwise frames must be signed (BBALIGN_AUTH__FLEET_KEY)",
    ),
    log_level: str = typer.Option("info", help="uvicorn log level"),
) -> None:
    """Run the ego-side service: REST and Zenoh doors, ego-frame cache, engine workers (env: BBALIGN_*).

    Frames must be signed (HMAC-SHA256, docs/security.md) unless --demo. SIGTERM/SIGINT: stop taking messages,
    finish or answer what was accepted, close Zenoh, exit 0."""
    from pydantic import ValidationError

    from .settings import Settings

    zenoh = {k: v for k, v in (("listen", zenoh_listen), ("connect", zenoh_connect), ("mode", zenoh_mode)) if v}
    if no_zenoh:
        zenoh["enabled"] = False
    given = {
        k: v for k, v in (("ego_id", ego_id), ("host", host), ("port", port), ("workers", workers)) if v is not None
    }
    if demo:
        given["profile"] = "demo"
    try:
        settings = Settings(**given, **({"zenoh": zenoh} if zenoh else {}))
    except ValidationError as e:
        raise typer.BadParameter(str(e)) from None
    problem = settings.startup_problem()
    if problem is not None:
        typer.secho(f"bb-align serve: {problem}", err=True, fg="red")
        raise typer.Exit(2)
    typer.echo(banner(settings))
    run_server(settings, log_level)


def banner(settings) -> str:
    """Where the service listens, and loudly what is not secured."""
    z, a = settings.zenoh, settings.auth
    lines = [
        f"bb-align serve: ego id {settings.ego_id!r}, profile {settings.profile!r}",
        f"  REST    http://{settings.host}:{settings.port}  (docs /docs, /metrics, /readyz)"
        + ("; bearer token required" if a.rest_token is not None else ""),
    ]
    if z.enabled:
        p = z.prefix
        lines += [
            f"  Zenoh   {z.mode} listening on {', '.join(z.listen) or 'nothing'}; connect "
            f"{', '.join(z.connect) or 'nothing'}; multicast scouting {'on' if z.multicast_scouting else 'off'}",
            f"  keys    {p}/frames/<vehicle_id> in, {p}/poses/{settings.ego_id}/<peer_id> out, "
            f"queryable {p}/align/{settings.ego_id}",
        ]
    else:
        lines.append("  Zenoh   disabled")
    if a.mode == "hmac":
        keys = (["fleet key"] if a.fleet_key is not None else []) + [f"{len(a.peer_keys)} peer key(s)"] * bool(
            a.peer_keys
        )
        lines.append(f"  auth    frames must be signed (HMAC-SHA256: {', '.join(keys)}); replays refused")
    for warning in settings.security_warnings():
        lines.append(f"  !!! {warning}")
    return "\n".join(lines)


def run_server(settings, log_level: str = "info") -> None:
    """uvicorn on the settings' host and port. SIGTERM or SIGINT drains gracefully and returns (exit code 0)."""
    import uvicorn

    from .app import create_app

    class _Server(uvicorn.Server):
        def handle_exit(self, sig, frame) -> None:  # drain, then exit 0 instead of re-raising the signal
            super().handle_exit(sig, frame)
            self._captured_signals.clear()

    config = uvicorn.Config(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=log_level,
        timeout_graceful_shutdown=int(settings.shutdown_timeout_s),
    )
    _Server(config).run()


def wire_schemas(
    out: Path = typer.Option(Path("proto_schemas"), help="directory for the <model>.schema.json files"),
) -> None:
    """Write the wire models' JSON Schema files (proto_schemas/)."""
    from bb_align.protocol import write_json_schemas

    for p in write_json_schemas(out):
        typer.echo(str(p))


def register(app: typer.Typer) -> None:
    app.command()(serve)
    app.command("wire-schemas")(wire_schemas)
