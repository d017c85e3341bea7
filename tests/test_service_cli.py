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


def test_demo_drives_a_simulated_scene_through_the_service(tmp_path, monkeypatch):
    """The secure path as a new user takes it: credentials made by `bb-align keys`, the same two variables for the
    service and the demo; default engine configuration, signed frames stamped on the clock, answers verified."""
    _clear_env(monkeypatch)
    runner = CliRunner()
    assert runner.invoke(app, ["keys", "init", str(tmp_path / "fleet")]).exit_code == 0
    out = runner.invoke(app, ["keys", "issue", str(tmp_path / "fleet"), "ego"])
    for var, value in re.findall(r"^export (\w+)=(.*)$", out.output, re.M):  # what `eval "$(...)"` would do
        monkeypatch.setenv(var, value)
    settings = secure_settings(align={}, auth={"fleet_key": None})
    settings = settings.model_copy(update={"auth": Settings().auth})  # the environment's credential, no fleet key
    assert settings.auth.credential is not None and settings.auth.fleet_key is None
    with running_service(settings):
        out = runner.invoke(
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
            ],
        )
    assert out.exit_code == 0, out.output
    report = json.loads((tmp_path / "demo.json").read_text())
    assert report["summary"]["results"] == 2 and report["summary"]["peer_frames_sent"] == 2
    for row in report["rows"]:  # each row holds the error against the simulator's true poses
        assert row["success"] and row["err"][0] < 1.0 and row["err"][1] < 1.0, (row.get("reason"), row)
    assert report["summary"]["ratio_vs_points_mean"] < 0.05
    assert (tmp_path / "demo.png").stat().st_size > 10_000
    assert "peer frames answered" in out.output


def test_demo_signers_credentials_then_the_fleet_key_then_none(tmp_path):
    from bb_align.lab.demo import demo_signers
    from bb_align.protocol import Credential

    runner = CliRunner()
    runner.invoke(app, ["keys", "init", str(tmp_path)])
    runner.invoke(app, ["keys", "issue", str(tmp_path), "ego"])
    runner.invoke(app, ["keys", "issue", str(tmp_path), "car1"])
    got = demo_signers("ego", 3, tmp_path / "ego.cred", None, FLEET_KEY)
    assert {k: v.vehicle_id for k, v in got["key"].items()} == {"ego": "ego", "car1": "car1", "car2": "car2"}
    assert got["key"]["car1"].certificate_bytes == Credential.load(tmp_path / "car1.cred").certificate_bytes
    assert got["trust"] == tmp_path / "ca.pub"  # car2 had no file: issued by ca.key, in memory only
    assert not (tmp_path / "car2.cred").exists()
    assert demo_signers("ego", 2, None, None, FLEET_KEY) == {"key": FLEET_KEY}
    assert demo_signers("ego", 2, None, None, None) == {"key": None}
    with pytest.raises(ValueError, match="ego id"):
        demo_signers("truck7", 2, tmp_path / "ego.cred", None, None)
    (tmp_path / "ca.key").unlink()
    with pytest.raises(ValueError, match="bb-align keys issue"):
        demo_signers("ego", 3, tmp_path / "ego.cred", None, None)


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


def _compose() -> dict:
    return yaml.safe_load((REPO / "docker" / "compose.yaml").read_text())["services"]


def test_compose_parses_and_its_settings_and_demo_options_are_valid(monkeypatch, tmp_path):
    services = _compose()
    assert set(services) == {"zenohd", "keys", "bb-align", "demo"}
    assert services["bb-align"]["build"]["dockerfile"] == "docker/Dockerfile"
    assert all(p.startswith("127.0.0.1:") for s in services.values() for p in s.get("ports", []))
    # The keys service's own commands, run here into a temporary directory standing for the volume.
    keys_dir = services["keys"]["volumes"][0].split(":")[1]
    script = services["keys"]["command"][0].replace("$$", "$").replace(keys_dir, str(tmp_path))
    subprocess.run(["sh", "-c", script.replace("bb-align", f"{sys.executable} -m bb_align")], check=True)
    made = {"ca.pub", "ca.key", "ego.cred", "car1.cred", "car2.cred", "issued"}  # issued/: the public register
    assert {p.name for p in tmp_path.iterdir()} == made
    _clear_env(monkeypatch)
    for k, v in services["bb-align"]["environment"].items():
        monkeypatch.setenv(k, str(v).replace(keys_dir, str(tmp_path)))
    s = Settings()
    assert s.zenoh.mode == "client" and s.zenoh.connect == ["tcp/zenohd:7447"] and s.zenoh.listen == []
    assert s.auth.required and s.auth.fleet_key is None and s.startup_problem() is None  # its own credential
    demo = services["demo"]
    assert demo["entrypoint"] == ["bb-align", "demo"]
    get_command(app).commands["demo"].make_context("demo", list(demo["command"]))  # options exist and parse
    for var in ("BBALIGN_AUTH__CA_CERT", "BBALIGN_AUTH__CREDENTIAL"):  # the variables the service reads, the same
        assert demo["environment"][var] == services["bb-align"]["environment"][var]
    agents = int(demo["command"][demo["command"].index("--agents") + 1])
    from bb_align.lab.demo import demo_signers

    got = demo_signers("ego", agents, tmp_path / "ego.cred", tmp_path / "ca.pub", None)  # every car has its own
    assert sorted(got["key"]) == ["car1", "car2", "ego"]
    assert all(v.endswith(":ro") for name in ("bb-align", "demo") for v in services[name]["volumes"])
    assert "--no-multicast-scouting" in services["zenohd"]["command"]


def test_compose_needs_no_shared_secret_healthchecks_and_start_order():
    """No fleet key to export (per-vehicle credentials are made in the volume); a healthcheck for the router, none
    inherited by the one-shot keys service or the demo (they run no server); each service starts after what it
    needs."""
    text = (REPO / "docker" / "compose.yaml").read_text()
    services = _compose()
    assert not re.findall(r"\$\{(\w+)", text) and "FLEET_KEY" not in text
    assert services["demo"]["healthcheck"] == {"disable": True} and services["keys"]["healthcheck"] == {"disable": True}
    assert services["bb-align"]["depends_on"] == {
        "keys": {"condition": "service_completed_successfully"},
        "zenohd": {"condition": "service_healthy"},
    }
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


def test_benchmark_overrides_set_nested_fields_and_name_bad_ones():
    from bb_align.engine.config import AlignConfig, with_overrides

    cfg = with_overrides(AlignConfig(), ["mim.coarse_scales=0", "acquire.top_k=8", "box.fuse=false"])
    assert (cfg.mim.coarse_scales, cfg.acquire.top_k, cfg.box.fuse) == (0, 8, False)
    assert cfg.mim.n_orient == AlignConfig().mim.n_orient  # the rest untouched
    for bad in ["mim.coarse_scales", "coarse_scales=0", "nosuch.key=1", "seed.x=1"]:
        with pytest.raises(ValueError, match="section.key=JSON"):
            with_overrides(AlignConfig(), [bad])
    with pytest.raises(ValueError, match="coarse_scales"):  # pydantic names the field and its bound
        with_overrides(AlignConfig(), ["mim.coarse_scales=99"])


def test_a_second_serve_on_a_busy_port_says_which_port_and_option_and_exits_2(monkeypatch):
    import socket

    _clear_env(monkeypatch)
    env = {k: v for k, v in os.environ.items() if not k.startswith("BBALIGN_")}
    with socket.socket() as busy:  # what a first service holds
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        cases = {
            "--port": ["--port", str(port), "--no-zenoh"],
            "--zenoh-listen": ["--port", str(free_port()), "--zenoh-listen", f"tcp/127.0.0.1:{port}"],
        }
        for option, args in cases.items():
            out = subprocess.run(
                [str(BIN), "serve", "--demo", *args], capture_output=True, text=True, timeout=60, env=env
            )
            assert out.returncode == 2, (option, out.stdout, out.stderr)
            lines = out.stderr.strip().splitlines()
            assert len(lines) == 1 and f"127.0.0.1:{port}" in lines[0] and option in lines[0], out.stderr
            assert "Traceback" not in out.stderr


def test_keys_issue_keeps_a_credential_without_force_and_prints_its_settings(tmp_path):
    """Issue 46: the secure path's `eval "$(bb-align keys issue DIR ego)"` could not run twice (exit 2, nothing
    set). Now an existing credential is kept, untouched, and its settings printed; --force makes a new key."""
    runner = CliRunner()
    assert runner.invoke(app, ["keys", "init", str(tmp_path)]).exit_code == 0
    first_run = runner.invoke(app, ["keys", "issue", str(tmp_path), "car1"])
    assert first_run.exit_code == 0
    first = (tmp_path / "car1.cred").read_bytes()
    again = runner.invoke(app, ["keys", "issue", str(tmp_path), "car1"])
    assert again.exit_code == 0 and "# kept" in again.stdout and "--force" in again.stdout
    exports = [line for line in first_run.stdout.splitlines() if line.startswith("export ")]
    assert len(exports) == 3 and exports == [ln for ln in again.stdout.splitlines() if ln.startswith("export ")]
    assert (tmp_path / "car1.cred").read_bytes() == first  # untouched
    env = runner.invoke(app, ["keys", "env", str(tmp_path), "car1"])  # only the settings of what exists
    assert env.exit_code == 0 and [ln for ln in env.stdout.splitlines() if ln.startswith("export ")] == exports
    missing = runner.invoke(app, ["keys", "env", str(tmp_path), "car9"])  # eval "$(...)" fails too: `false`
    assert missing.exit_code == 2 and missing.stdout.strip() == "false" and "car9.cred" in missing.stderr
    assert runner.invoke(app, ["keys", "init", str(tmp_path), "--force"]).exit_code == 0  # a new authority
    stale = runner.invoke(app, ["keys", "issue", str(tmp_path), "car1"])  # kept, but no longer vouched for
    assert stale.exit_code == 2 and stale.stdout.strip() == "false" and "--force" in stale.stderr
    forced = runner.invoke(app, ["keys", "issue", str(tmp_path), "car1", "--force"])
    assert forced.exit_code == 0 and (tmp_path / "car1.cred").read_bytes() != first


def test_docs_page_is_served_by_the_service_and_loads_nothing_from_outside(monkeypatch):
    _clear_env(monkeypatch)
    with running_service(Settings(profile="demo", port=free_port(), zenoh={"enabled": False})) as (_, url):
        for route in ("/docs", "/redoc"):
            r = httpx.get(f"{url}{route}")
            assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
            assert "/v1/align" in r.text and 'href="/openapi.json"' in r.text
            external = re.findall(r"""(?:src|href)\s*=\s*["'](?:https?:)?//""", r.text)
            assert external == [], external  # no CDN: blank on a vehicle network otherwise
        assert httpx.get(f"{url}/openapi.json").json()["paths"]["/v1/align"]


def test_dockerignore_keeps_the_venv_and_outputs_from_the_daemon():
    """The build context is the repository root; only what the Dockerfile copies may be sent."""
    lines = [x.strip() for x in (REPO / ".dockerignore").read_text().splitlines() if x.strip() and x[0] != "#"]
    assert lines[0] == "*"  # everything excluded, then re-included
    allowed = {x[1:].rstrip("/") for x in lines if x.startswith("!")}
    copied = set()
    for line in (REPO / "docker" / "Dockerfile").read_text().splitlines():
        if line.startswith("COPY") and "--from" not in line:
            copied.update(p.rstrip("/").removeprefix("./") for p in line.split()[1:-1])
    assert copied == allowed, (copied, allowed)
    assert ".venv" not in allowed and "out" not in allowed


def test_zenohd_in_compose_is_the_version_of_the_python_zenoh():
    from importlib.metadata import version

    image = _compose()["zenohd"]["image"]
    assert image.split(":")[1].split(".")[:2] == version("eclipse-zenoh").split(".")[:2], image


def test_demo_without_a_service_says_so_before_simulating(monkeypatch):
    _clear_env(monkeypatch)
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    out = CliRunner().invoke(app, ["demo", "--connect", endpoint, "--frames", "50"])
    assert out.exit_code == 1, out.output
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and endpoint in lines[0] and "make run" in lines[0], out.stderr
    assert "simulating" not in out.output and out.stdout == ""
