"""Issue 47, item 6: private by default. Each test reproduces a finding of the attacker's probe against a real
uvicorn service on 127.0.0.1:

- ``/v1/peers``, ``/metrics`` and ``/v1/bandwidth`` gave any local caller every peer's pose and per-car series;
- ``--host 0.0.0.0`` without a token only warned;
- ``/readyz`` said ready ~0.8 s before frames were accepted (the restart floor still refused them)."""

from __future__ import annotations

import os
import time

import httpx
import pytest
from typer.testing import CliRunner

from bb_align.cli import app as cli
from bb_align.server.commands import banner
from bb_align.server.settings import Settings
from bb_align_client import AlignClient, encode_frame
from service_support import FLEET_KEY, RANGE_M, free_port, moving_pair, running_service, secure_settings, wait_for

TOKEN = "private-token-0123456789abcdef"
CT = {"content-type": "application/msgpack"}


@pytest.fixture(scope="module")
def pair():
    return moving_pair(1)


def _enc(car, name, seq, stamp=None):
    t = time.time() if stamp is None else stamp
    return encode_frame(car.points, car.boxes, vehicle_id=name, stamp=t, seq=seq, range_m=RANGE_M, key=FLEET_KEY)


def test_peers_poses_bandwidth_and_per_car_metrics_need_the_token(pair):
    _, ego, peer = pair[0]
    settings = secure_settings(False, auth={"fleet_key": FLEET_KEY, "rest_token": TOKEN})
    with running_service(settings) as (_, url):
        wait_for(lambda: httpx.get(f"{url}/readyz").status_code == 200, what="frames accepted")
        with AlignClient(url, token=TOKEN, key=FLEET_KEY) as client:
            t = time.time()
            assert client.align(_enc(peer, "car1", 1, t), _enc(ego, "ego", 1, t)).peer_id == "car1"
        bearer = {"authorization": f"Bearer {TOKEN}"}
        for route in ("/v1/peers", "/v1/bandwidth", "/metrics"):
            for headers in ({}, {"authorization": "Bearer wrong-token-0123456789"}, {"authorization": TOKEN}):
                r = httpx.get(f"{url}{route}", headers=headers)
                assert r.status_code == 401 and "car1" not in r.text, (route, headers)
        assert "car1" in httpx.get(f"{url}/v1/peers", headers=bearer).json()  # the pose is there, behind the token
        assert "car1" in httpx.get(f"{url}/v1/bandwidth", headers=bearer).text
        assert 'peer="car1"' in httpx.get(f"{url}/metrics", headers=bearer).text
        assert httpx.get(f"{url}/healthz").status_code == 200  # probes stay open, and say nothing of peers
        assert "car1" not in httpx.get(f"{url}/readyz").text


def test_serving_beyond_loopback_without_a_token_refuses_to_start_unless_insecure(monkeypatch):
    for var in [v for v in os.environ if v.startswith("BBALIGN_")]:
        monkeypatch.delenv(var)
    monkeypatch.setenv("BBALIGN_AUTH__FLEET_KEY", FLEET_KEY)
    port = free_port()
    for host in ("0.0.0.0", "192.0.2.7", "::"):  # refused before anything binds
        r = CliRunner().invoke(cli, ["serve", "--host", host, "--port", str(port), "--no-zenoh"])
        lines = r.stderr.strip().splitlines()
        assert r.exit_code == 2 and len(lines) == 1 and "--insecure" in lines[0] and "TOKEN" in lines[0], r.output
    for host in ("127.0.0.1", "localhost", "::1", "127.0.0.2"):
        assert Settings(host=host).startup_problem() is None, host
    assert Settings(host="0.0.0.0", auth={"rest_token": TOKEN, "fleet_key": FLEET_KEY}).startup_problem() is None
    insecure = Settings(host="0.0.0.0", insecure=True)
    assert insecure.startup_problem() is None  # the user said so; the banner still says it loudly
    assert "REST is reachable beyond loopback without a bearer token" in banner(insecure)


def test_readyz_says_ready_only_when_frames_stamped_now_are_accepted(pair):
    _, _, peer = pair[0]
    settings = secure_settings(False)
    with running_service(settings) as (app, url):
        table = app.state.service.peer_table
        table.not_before = time.time() + 1.5  # as just after a start: frames stamped earlier may be replays
        r = httpx.get(f"{url}/readyz")
        assert r.status_code == 503 and r.json()["frames_accepted"] is False and r.json()["workers_running"]
        refused = httpx.post(f"{url}/v1/frames", content=_enc(peer, "car1", 1), headers=CT)
        assert refused.status_code == 409 and "before this service started" in refused.json()["detail"]
        wait_for(lambda: httpx.get(f"{url}/readyz").status_code == 200, timeout=10, what="ready")
        assert httpx.post(f"{url}/v1/frames", content=_enc(peer, "car1", 2), headers=CT).status_code == 202
