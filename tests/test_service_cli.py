"""Settings from the environment, `bb-align serve` as a real process, `bb-align demo` against a live service,
and the docker files (docker cannot run here: they are parsed and checked against the code)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import httpx
import pytest
import yaml
from pydantic import ValidationError
from typer.main import get_command
from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.server.settings import Settings
from service_support import FLEET_KEY, free_port, running_service, secure_settings

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent / "bb-align"


def _clear_env(monkeypatch):
    for k in list(os.environ):
        if k.startswith("BBALIGN_"):
            monkeypatch.delenv(k)


def test_defaults_bind_loopback_only(monkeypatch):
    _clear_env(monkeypatch)
    s = Settings()
    assert s.host == "127.0.0.1" and s.port == 8000
    assert s.zenoh.listen == ["tcp/127.0.0.1:7447"] and s.zenoh.connect == [] and not s.zenoh.multicast_scouting
    assert s.zenoh.mode == "peer" and s.zenoh.prefix == "bbalign"
    assert s.profile == "vehicle" and s.auth.mode == "signed"  # secure unless the demo profile is asked for
    assert s.startup_problem() is not None and "BBALIGN_AUTH__FLEET_KEY" in s.startup_problem()
    demo = Settings(profile="demo")
    assert demo.auth.mode == "off" and demo.startup_problem() is None


def test_environment_configures_nested_fields(monkeypatch):
    _clear_env(monkeypatch)
    monkeypatch.setenv("BBALIGN_EGO_ID", "truck7")
    monkeypatch.setenv("BBALIGN_ZENOH__CONNECT", '["tcp/127.0.0.1:7000"]')
    monkeypatch.setenv("BBALIGN_ZENOH__MODE", "client")
    monkeypatch.setenv("BBALIGN_ALIGN__BEV__RANGE_M", "60")
    monkeypatch.setenv("BBALIGN_LIMITS__MAX_BOXES", "32")
    s = Settings()
    assert (s.ego_id, s.zenoh.connect, s.zenoh.mode) == ("truck7", ["tcp/127.0.0.1:7000"], "client")
    assert s.align.bev.range_m == 60 and s.limits.max_boxes == 32
    monkeypatch.setenv("BBALIGN_ZENOH__LISTEN", '["127.0.0.1:7447"]')  # no protocol
    with pytest.raises(ValidationError, match="Zenoh endpoint"):
        Settings()


def test_serve_without_a_key_refuses_to_start_and_says_how_to_fix_it(monkeypatch):
    _clear_env(monkeypatch)
    out = subprocess.run(
        [str(BIN), "serve", "--port", str(free_port()), "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"],
        capture_output=True,
        text=True,
        timeout=60,
        env={k: v for k, v in os.environ.items() if not k.startswith("BBALIGN_")},
    )
    assert out.returncode == 2
    assert "BBALIGN_AUTH__FLEET_KEY" in out.stderr and "--demo" in out.stderr


def test_banner_says_loudly_what_is_not_secured():
    from bb_align.server.commands import banner

    demo = banner(Settings(profile="demo"))
    assert "!!! AUTHENTICATION IS OFF (demo profile)" in demo
    secure = banner(Settings(auth={"fleet_key": "k" * 32, "rest_token": "t" * 32}))
    assert "frames must be signed" in secure and "bearer token required" in secure and "!!!" not in secure
    assert "k" * 32 not in secure  # secrets never print
    open_net = banner(Settings(profile="demo", host="0.0.0.0", zenoh={"listen": ["tcp/0.0.0.0:7447"]}))
    assert "NOT LOOPBACK-ONLY WITHOUT AUTHENTICATION" in open_net and "not encrypted" in open_net


def test_serve_replay_turns_on_the_replay_profile_on_top_of_the_environment(monkeypatch):
    """`bb-align serve --replay` = BBALIGN_LIMITS__REPLAY=true, merged with the other BBALIGN_LIMITS__* given in
    the environment; the banner says what it gives up."""
    from bb_align.server import commands

    _clear_env(monkeypatch)
    monkeypatch.setenv("BBALIGN_LIMITS__MAX_BOXES", "32")
    started = []
    monkeypatch.setattr(commands, "run_server", lambda settings, log_level="info": started.append(settings))
    r = CliRunner().invoke(app, ["serve", "--demo", "--replay", "--no-zenoh"])
    assert r.exit_code == 0, r.output
    (settings,) = started
    assert settings.limits.replay and not settings.limits.clock_checked and settings.limits.max_boxes == 32
    assert "replay  recorded or simulated data" in r.output and "!!! REPLAY PROFILE" in r.output
    monkeypatch.setenv("BBALIGN_LIMITS__REPLAY", "true")  # the same, from the environment
    assert Settings(profile="demo").limits.replay


def test_serve_runs_prints_where_it_listens_and_stops_on_sigint(monkeypatch):
    _clear_env(monkeypatch)
    port, zport = free_port(), free_port()
    env = {**os.environ, "BBALIGN_ALIGN__BEV__RANGE_M": "40", "BBALIGN_AUTH__FLEET_KEY": "f" * 32}
    proc = subprocess.Popen(
        [
            str(BIN),
            "serve",
            "--port",
            str(port),
            "--ego-id",
            "car0",
            "--zenoh-listen",
            f"tcp/127.0.0.1:{zport}",
            "--log-level",
            "warning",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    try:
        deadline = time.monotonic() + 30
        while True:
            assert proc.poll() is None, proc.stdout.read()
            assert time.monotonic() < deadline, "serve did not become ready"
            try:
                if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        assert httpx.get(f"http://127.0.0.1:{port}/readyz").json()["zenoh"] is True
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert f"http://127.0.0.1:{port}" in out and f"tcp/127.0.0.1:{zport}" in out and "ego id 'car0'" in out
    assert "bbalign/align/car0" in out
    assert "frames must be signed" in out and "f" * 32 not in out


def test_demo_drives_a_simulated_scene_through_the_service(tmp_path):
    # The secure path: default engine configuration, signed frames stamped on the clock, as `bb-align serve`.
    settings = secure_settings(align={})
    with running_service(settings):
        out = CliRunner().invoke(
            app,
            [
                "demo",
                "--connect",
                settings.zenoh.listen[0],
                "--frames",
                "2",
                "--distance-m",
                "20",
                "--json",
                str(tmp_path / "demo.json"),
                "--plot",
                str(tmp_path / "demo.png"),
                "--key",
                FLEET_KEY,
            ],
        )
    assert out.exit_code == 0, out.output
    report = json.loads((tmp_path / "demo.json").read_text())
    assert report["summary"]["results"] == 2 and report["summary"]["peer_frames_sent"] == 2
    for row in report["rows"]:  # each row holds the error against the simulator's true poses
        assert row["success"] and row["err"][0] < 1.0 and row["err"][1] < 1.0, row
    assert report["summary"]["ratio_vs_points_mean"] < 0.05
    assert (tmp_path / "demo.png").stat().st_size > 10_000
    assert "peer frames answered" in out.output


def _dockerfile() -> dict[str, list[str]]:
    text = (REPO / "docker" / "Dockerfile").read_text().replace("\\\n", " ")
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        m = re.match(r"^\s*([A-Z]+)\s+(.*)$", line)
        if m:
            out.setdefault(m.group(1), []).append(m.group(2).strip())
    return out


def test_dockerfile_is_slim_non_root_with_healthcheck_and_serve_entry():
    d = _dockerfile()
    assert all("slim" in f for f in d["FROM"])
    assert d["USER"] == ["bbalign"]
    assert "readyz" in d["HEALTHCHECK"][0]
    entry = json.loads(d["ENTRYPOINT"][0])
    assert entry == ["bb-align", "serve"]
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts[entry[0]] == "bb_align.cli:app" and entry[1] in get_command(app).commands


def test_compose_parses_and_its_settings_and_demo_options_are_valid(monkeypatch):
    compose = yaml.safe_load((REPO / "docker" / "compose.yaml").read_text())
    services = compose["services"]
    assert set(services) == {"zenohd", "bb-align", "demo"}
    assert services["bb-align"]["build"]["dockerfile"] == "docker/Dockerfile"
    assert all(p.startswith("127.0.0.1:") for s in services.values() for p in s.get("ports", []))
    _clear_env(monkeypatch)
    for k, v in services["bb-align"]["environment"].items():
        monkeypatch.setenv(k, str(v))
    s = Settings()
    assert s.zenoh.mode == "client" and s.zenoh.connect == ["tcp/zenohd:7447"] and s.zenoh.listen == []
    demo = services["demo"]
    assert demo["entrypoint"] == ["bb-align", "demo"]
    get_command(app).commands["demo"].make_context("demo", list(demo["command"]))  # options exist and parse
    assert s.auth.required and s.startup_problem() is None  # the container runs with a fleet key
    assert "BBALIGN_AUTH__FLEET_KEY" in demo["environment"]
    assert "--no-multicast-scouting" in services["zenohd"]["command"]


def test_compose_key_name_healthchecks_and_start_order():
    """One name for the fleet key (the one the service reads); a healthcheck for the router, none inherited by
    the demo (it runs no server); each service starts after what it needs is healthy."""
    text = (REPO / "docker" / "compose.yaml").read_text()
    services = yaml.safe_load(text)["services"]
    assert set(re.findall(r"\$\{(\w+)", text)) == {"BBALIGN_AUTH__FLEET_KEY"}
    assert "export BBALIGN_AUTH__FLEET_KEY=" in (REPO / "README.md").read_text()
    assert "BBALIGN_FLEET_KEY" not in text
    assert services["demo"]["healthcheck"] == {"disable": True}
    assert services["bb-align"]["depends_on"] == {"zenohd": {"condition": "service_healthy"}}
    assert services["demo"]["depends_on"] == {"bb-align": {"condition": "service_healthy"}}
    # the router's check: a LISTEN socket on the port it is told to listen on, read from /proc/net/tcp(6)
    check = services["zenohd"]["healthcheck"]["test"]
    assert check[0] == "CMD-SHELL"
    listen = services["zenohd"]["command"][services["zenohd"]["command"].index("--listen") + 1]
    port = int(listen.rsplit(":", 1)[1])
    pattern = re.search(r"'(.+?)'", check[1]).group(1)
    assert f":{port:04X} " in pattern
    listening_v4 = f"   0: 00000000:{port:04X} 00000000:0000 0A 00000000:00000000 00:00000000 00000000"
    listening_v6 = f"   0: {'0' * 32}:{port:04X} {'0' * 32}:0000 0A 00000000:00000000 00:00000000"
    connected = f"   1: 0100007F:{port:04X} 0100007F:B2C4 01 00000000:00000000 00:00000000 00000000"
    assert re.search(pattern, listening_v4) and re.search(pattern, listening_v6)
    assert not re.search(pattern, connected)
