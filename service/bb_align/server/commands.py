"""``bb-align serve`` and ``bb-align wire-schemas`` (registered into the main CLI; ``bb-align keys``: keys_cli)."""

from __future__ import annotations

import os
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
    replay: bool = typer.Option(
        False,
        "--replay",
        help="recorded or simulated data (= BBALIGN_LIMITS__REPLAY=true): stamps are not checked against this "
        "machine's clock and a sender whose (stamp, seq) goes back starts a new pass; replay protection is OFF",
    ),
    insecure: bool = typer.Option(
        False,
        "--insecure",
        help="allow REST beyond loopback (--host) without a bearer token (= BBALIGN_INSECURE=true); otherwise the "
        "service refuses to start that way",
    ),
    log_level: str = typer.Option("info", help="uvicorn log level"),
) -> None:
    """Run the ego-side service: REST and Zenoh doors, ego-frame cache, engine workers (env: BBALIGN_*).

    Frames must be signed (Ed25519 vehicle certificates or HMAC, docs/security.md) unless --demo. --replay is for
    recorded or simulated data (stamps on their own clock, a recording played more than once). SIGTERM/SIGINT:
    stop taking messages, finish or answer what was accepted, close Zenoh, exit 0."""
    zenoh = {k: v for k, v in (("listen", zenoh_listen), ("connect", zenoh_connect), ("mode", zenoh_mode)) if v}
    zenoh |= {"enabled": False} if no_zenoh else {}
    given = {
        k: v for k, v in (("ego_id", ego_id), ("host", host), ("port", port), ("workers", workers)) if v is not None
    }
    given |= ({"profile": "demo"} if demo else {}) | ({"insecure": True} if insecure else {})
    if replay:  # merged with BBALIGN_LIMITS__* from the environment (pydantic-settings merges nested values)
        given["limits"] = {"replay": True}
    given |= {"zenoh": zenoh} if zenoh else {}
    settings = _settings_or_exit(given)
    typer.echo(banner(settings))
    run_server(settings, log_level)


def _settings_or_exit(given: dict):
    """The service's settings from the options ``given`` and the environment, or exit 2 with one line naming the
    problem (an environment variable named as such, "did you mean" for a typo; a port in use)."""
    from pydantic import ValidationError

    from bb_align.engine.config import describe_errors

    from .settings import Settings

    settings = None
    try:
        settings = Settings(**given)
        problem = _unknown_variable(os.environ)
    except ValidationError as e:
        problem = describe_errors(e, Settings, ENV_PREFIX, os.environ)
    if problem is None:
        problem = settings.startup_problem() or busy_port(settings)
    if problem is not None:
        typer.secho(f"bb-align serve: {problem}", err=True, fg="red")
        raise typer.Exit(2)
    return settings


ENV_PREFIX = "BBALIGN_"


def _unknown_variable(environ) -> str | None:
    """A BBALIGN_* variable that names no setting (pydantic-settings ignores those at the top level), with the
    nearest valid name; None when all are known. Nested ones (``__``) are checked by the settings' validation."""
    from bb_align.engine.config import nearest_setting

    from .settings import Settings

    for var in sorted(environ):
        if not var.upper().startswith(ENV_PREFIX):
            continue
        top = var[len(ENV_PREFIX) :].split("__")[0].lower()
        if top not in Settings.model_fields:
            near = nearest_setting(Settings, (top,))
            hint = f" (did you mean {ENV_PREFIX}{near[0].upper()}?)" if near else ""
            return f"{var}: no such setting{hint}"
    return None


def _listen_addresses(settings) -> list[tuple[str, int, str]]:
    """(host, port, how to change it) of every TCP port the service will listen on."""
    out = [(settings.host, settings.port, "--port or BBALIGN_PORT")]
    if settings.zenoh.enabled:
        for endpoint in settings.zenoh.listen:
            proto, _, address = endpoint.partition("/")
            host, _, port = address.split("#")[0].rpartition(":")
            if proto in ("tcp", "tls") and port.isdigit():
                out.append((host.strip("[]"), int(port), "--zenoh-listen or BBALIGN_ZENOH__LISTEN"))
    return out


def busy_port(settings) -> str | None:
    """A line naming a port the service cannot listen on, and the option that moves it; None when all are free.
    Checked before starting, so a second service on the same ports stops here with one clear line."""
    import socket

    for host, port, option in _listen_addresses(settings):
        if port == 0:
            continue
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn and Zenoh do: TIME_WAIT is free
            try:
                s.bind((host, port))
            except OSError as e:
                what = "REST" if option.startswith("--port") else "Zenoh"
                return (
                    f"cannot listen on {host}:{port} for {what} ({e.strerror}; another bb-align serve?): "
                    f"choose another port with {option}"
                )
    return None


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
    if a.required:
        keys = (
            ([f"Ed25519 vehicle certificates from {a.ca_cert}"] if a.ca_cert is not None else [])
            + (["HMAC fleet key"] if a.fleet_key is not None else [])
            + [f"{len(a.peer_keys)} HMAC peer key(s)"] * bool(a.peer_keys)
        )
        lines.append(f"  auth    frames must be signed ({', '.join(keys)}); replays refused")
        signer, key_id = a.answer_key()
        how = "unsigned" if signer is None else ("Ed25519, " if key_id != "fleet" else "HMAC fleet key, ") + key_id
        lines.append(f"  answers signed: {how}")
    if settings.limits.replay:
        lines.append(
            "  replay  recorded or simulated data: stamps not checked against this clock; a sender going back "
            "starts a new pass"
        )
    for warning in settings.security_warnings():
        lines.append(f"  !!! {warning}")
    return "\n".join(lines)


def run_server(settings, log_level: str = "info") -> None:
    """uvicorn on the settings' host and port. SIGTERM or SIGINT drains gracefully and returns (exit code 0)."""
    import logging

    import uvicorn

    from .allocator import configure_malloc
    from .app import create_app

    # before any thread (Zenoh's, the workers): glibc limits only the arenas it has not made yet
    malloc = configure_malloc(settings.malloc_arena_max, settings.malloc_mmap_threshold_kb)

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
    logging.getLogger("bb_align.server").info("glibc malloc: %s", malloc or "defaults")
    _Server(config).run()


def wire_schemas(
    out: Path = typer.Option(Path("proto_schemas"), help="directory for the <model>.schema.json files"),
) -> None:
    """Write the wire models' JSON Schema files (proto_schemas/)."""
    from bb_align.protocol import write_json_schemas

    for p in write_json_schemas(out):
        typer.echo(str(p))


def register(app: typer.Typer) -> None:
    from .keys_cli import keys_app

    app.command()(serve)
    app.command("wire-schemas")(wire_schemas)
    app.add_typer(keys_app, name="keys")
