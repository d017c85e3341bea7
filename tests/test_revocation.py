"""Issue 47, item 3: revocation that sticks. Each test reproduces a finding of the attacker's probe:

- an older signed revocation list put back re-admitted the revoked car in 2 s (no version check, also at start-up);
- the client library with the documented ``trust="ca.pub"`` accepted an answer signed by the ego's revoked key;
- ``keys revoke`` needed the private credential file, and ``revoke DIR ego`` after ``issue --force`` revoked the new
  key;
- during a rotation the old key stamping 1.9 s ahead locked the new key out (99 frames refused as "replayed").

Against the real code: the ``bb-align keys`` commands, the protocol's loaders and a real uvicorn service on
127.0.0.1."""

from __future__ import annotations

import logging
import os
import shutil
import time

import httpx
import pytest
from typer.testing import CliRunner

from bb_align.cli import app as cli
from bb_align.protocol import Credential, Limits, RevocationList, WireError, fingerprint, load_frame
from bb_align_client import AlignClient, encode_frame
from service_support import RANGE_M, free_port, moving_pair, running_service, secure_settings, wait_for

LIMITS = Limits()
CT = {"content-type": "application/msgpack"}


def keys(*args: str):
    r = CliRunner().invoke(cli, ["keys", *map(str, args)])
    return r


@pytest.fixture()
def fleet(tmp_path):
    d = tmp_path / "fleet"
    for args in (["init", d], *(["issue", d, v] for v in ("ego", "car1", "car2"))):
        assert keys(*args).exit_code == 0
    return d


@pytest.fixture(scope="module")
def pair():
    return moving_pair(1)


def _enc(car, name, seq, stamp=None, **kw):
    t = time.time() if stamp is None else stamp
    return encode_frame(car.points, car.boxes, vehicle_id=name, stamp=t, seq=seq, range_m=RANGE_M, **kw)


def _auth(fleet, **extra):
    return {
        "ca_cert": str(fleet / "ca.pub"),
        "credential": str(fleet / "ego.cred"),
        "revocations": str(fleet / "revoked.json"),
        "revocations_state": str(fleet.parent / "state" / "revocations.json"),
        **extra,
    }


def test_an_older_signed_list_is_refused_at_run_time_and_at_start_up(fleet, pair, caplog, monkeypatch):
    _, _, peer = pair[0]
    car1, car2 = Credential.load(fleet / "car1.cred"), Credential.load(fleet / "car2.cred")
    assert keys("revoke", fleet, "car2").exit_code == 0
    old = fleet.parent / "revoked-v1.json"
    shutil.copy(fleet / "revoked.json", old)  # what an attacker kept: signed by the authority, version 1
    assert keys("revoke", fleet, "car1").exit_code == 0
    assert RevocationList.load(fleet / "revoked.json").version == 2
    settings = secure_settings(False, auth=_auth(fleet))
    assert settings.startup_problem() is None
    ring = settings.auth.keyring()
    ring.trust.revocations.poll_s = 0.0  # look at the file on every check (default: every 2 s)

    def refused(name, seq, key) -> bool:
        try:
            load_frame(_enc(peer, name, seq, key=key), LIMITS, keyring=ring, now=time.time())
        except WireError as e:
            assert e.status == 401 and "revoked" in e.detail
            return True
        return False

    assert refused("car1", 1, car1) and refused("car2", 1, car2)
    tmp = fleet / "revoked.json.put-back"
    shutil.copy(old, tmp)
    os.replace(tmp, fleet / "revoked.json")  # the older list put back, atomically, while the service runs
    with caplog.at_level(logging.WARNING, "bb_align.protocol.revocations"):
        assert refused("car1", 2, car1), "an older list re-admitted car1"
    assert any("version 1 is older than version 2" in r.getMessage() for r in caplog.records)
    # A restart with the older list in place: the state file remembers version 2, so the service will not start.
    fresh = secure_settings(False, auth=_auth(fleet))
    assert "version 1 is older than version 2" in fresh.startup_problem()
    port = free_port()
    monkeypatch.setenv("BBALIGN_PORT", str(port))
    for k, v in _auth(fleet).items():
        monkeypatch.setenv(f"BBALIGN_AUTH__{k.upper()}", v)
    r = CliRunner().invoke(cli, ["serve", "--no-zenoh"])
    assert r.exit_code == 2 and "rollback" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.output


def test_revoke_names_a_key_by_fingerprint_or_certificate_never_by_a_guess(fleet, pair):
    _, _, peer = pair[0]
    old_ego = Credential.load(fleet / "ego.cred")
    assert keys("issue", fleet, "ego", "--force").exit_code == 0  # rotation: the old ego.cred is overwritten
    new_ego = Credential.load(fleet / "ego.cred")
    old_fp, new_fp = (fingerprint(c.certificate.public_key) for c in (old_ego, new_ego))
    listed = keys("list", fleet, "ego").stdout
    assert old_fp in listed and new_fp in listed
    guess = keys("revoke", fleet, "ego")  # two valid keys: which one is meant? Refused, both named
    assert guess.exit_code == 2 and old_fp[:16] in guess.stderr and new_fp[:16] in guess.stderr
    assert not (fleet / "revoked.json").exists()
    r = keys("revoke", fleet, "--fingerprint", old_fp[:12])  # no private file: the authority's register
    assert r.exit_code == 0, r.output
    rl = RevocationList.load(fleet / "revoked.json")
    assert rl.revokes(old_ego.certificate.public_key) and not rl.revokes(new_ego.certificate.public_key)
    # by certificate: a car's .cert from the register (or any .cred: only its certificate is read)
    car2_cert = next((fleet / "issued").glob("car2-*.cert"))
    assert keys("revoke", fleet, "--cert", car2_cert).exit_code == 0
    assert keys("revoke", fleet, "car1", "--fingerprint", new_fp).exit_code == 2  # names another car's key
    assert keys("revoke", fleet, "--fingerprint", "00000000").exit_code == 2  # no such key
    assert RevocationList.load(fleet / "revoked.json").version == 2
    settings = secure_settings(False, auth=_auth(fleet))
    assert settings.startup_problem() is None  # the service's own (new) key is not revoked
    ring = settings.auth.keyring()
    car2 = Credential.load(fleet / "car2.cred")
    for cred, name, ok in ((new_ego, "ego", True), (old_ego, "ego", False), (car2, "car2", False)):
        try:
            load_frame(_enc(peer, name, 1, key=cred), LIMITS, keyring=ring, now=time.time())
            assert ok, f"{name}'s revoked key was accepted"
        except WireError as e:
            assert not ok and e.status in (401, 403), e


def test_the_client_refuses_an_answer_signed_by_a_revoked_ego_key(fleet, pair):
    _, ego, peer = pair[0]
    settings = secure_settings(False, auth={"ca_cert": str(fleet / "ca.pub"), "credential": str(fleet / "ego.cred")})
    ego_cred, car1 = Credential.load(fleet / "ego.cred"), Credential.load(fleet / "car1.cred")
    with running_service(settings) as (_, url):
        wait_for(lambda: httpx.get(f"{url}/readyz").status_code == 200, what="frames accepted")
        with AlignClient(url, key=car1, trust=str(fleet / "ca.pub")) as client:  # the documented trust="ca.pub"
            t = time.time()
            assert client.align(_enc(peer, "car1", 1, t), _enc(ego, "ego", 1, t, key=ego_cred)).ego_id == "ego"
        assert keys("revoke", fleet, "ego").exit_code == 0  # revoked.json lands beside ca.pub
        kept = keys("issue", fleet, "ego")  # a revoked credential is not kept: its service would not start
        assert kept.exit_code == 2 and "revoked" in kept.stderr and kept.stdout.strip() == "false"
        with AlignClient(url, key=car1, trust=str(fleet / "ca.pub")) as client:
            t = time.time()
            with pytest.raises(WireError) as e:
                client.align(_enc(peer, "car1", 2, t), _enc(ego, "ego", 2, t, key=ego_cred))
    assert e.value.status == 401 and "revoked" in e.value.detail


def test_a_stale_key_stamping_ahead_cannot_lock_the_rotated_key_out(fleet, pair):
    _, _, peer = pair[0]
    old = Credential.load(fleet / "car1.cred")
    assert keys("issue", fleet, "car1", "--force").exit_code == 0
    new = Credential.load(fleet / "car1.cred")
    settings = secure_settings(False, auth={"ca_cert": str(fleet / "ca.pub"), "credential": str(fleet / "ego.cred")})
    with running_service(settings) as (app, url):
        wait_for(lambda: httpx.get(f"{url}/readyz").status_code == 200, what="frames accepted")
        service = app.state.service

        def post(seq, key, stamp):
            return httpx.post(f"{url}/v1/frames", content=_enc(peer, "car1", seq, stamp, key=key), headers=CT)

        t = time.time()
        ahead = [post(100 + i, old, t + 1.9 + 0.01 * i) for i in range(5)]  # the old key, 1.9 s ahead
        assert [r.status_code for r in ahead] == [202] * 5
        fresh = [_enc(peer, "car1", i, t + 0.01 * i, key=new) for i in range(5)]
        assert [httpx.post(f"{url}/v1/frames", content=f, headers=CT).status_code for f in fresh] == [202] * 5
        # Each key's window still refuses its own replays, over REST and at the Zenoh door.
        assert httpx.post(f"{url}/v1/frames", content=fresh[-1], headers=CT).status_code == 409
        assert post(101, old, t + 1.91).status_code == 409
        assert not service.submit_message("car1", fresh[2])  # the door: older than the new key's newest
        assert service.submit_message("car1", _enc(peer, "car1", 9, t + 0.1, key=new))
