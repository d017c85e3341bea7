"""Issue #13: per-vehicle identities, signed answers, replays across doors, REST hardening (findings 1, 4-7).

Every test reproduces a finding of the review (named in its docstring) against the real code: the protocol's
loaders, or a real uvicorn service on 127.0.0.1 with a real Zenoh session on loopback."""

from __future__ import annotations

import os
import stat
import time

import httpx
import msgpack
import pytest
import zenoh
from typer.testing import CliRunner

from bb_align.cli import app as cli
from bb_align.protocol import (
    AnswerTrust,
    Credential,
    FleetAuthority,
    Limits,
    Result,
    TrustStore,
    WireError,
    ZenohSettings,
    load_frame,
    load_result,
    pack,
    pack_align_request,
    poses_key,
    sign,
    sign_result,
)
from bb_align.server.settings import AuthSettings
from bb_align_client import AlignClient, FrameRefused, ServiceError, ZenohPeer, encode_frame
from service_support import FLEET_KEY, RANGE_M, free_port, moving_pair, running_service, secure_settings, wait_for

LIMITS = Limits()


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """A fleet authority and credentials for the ego and two cars, made by `bb-align keys` itself."""
    d = tmp_path_factory.mktemp("fleet")
    runner = CliRunner()
    r = runner.invoke(cli, ["keys", "init", str(d)])
    assert r.exit_code == 0, r.output
    for vid in ("ego", "car1", "car2"):
        r = runner.invoke(cli, ["keys", "issue", str(d), vid])
        assert r.exit_code == 0, r.output
    assert f"export BBALIGN_AUTH__CREDENTIAL={(d / 'car2.cred').resolve()}" in r.output
    return d


@pytest.fixture(scope="module")
def pair():
    return moving_pair(2)


def _enc(car, name, seq, stamp=None, **kw):
    t = time.time() if stamp is None else stamp
    return encode_frame(car.points, car.boxes, vehicle_id=name, stamp=t, seq=seq, range_m=RANGE_M, **kw)


def _settings(fleet, zenoh=True, align=None, **auth):
    return secure_settings(
        zenoh,
        auth={"ca_cert": str(fleet / "ca.pub"), "credential": str(fleet / "ego.cred"), **auth},
        **({} if align is None else {"align": align}),
    )


# ---- identities (finding 5) ------------------------------------------------------------------------------------
def test_keys_cli_writes_private_files_0600_and_keeps_the_authority(fleet):
    for name in ("ca.key", "ego.cred", "car1.cred"):
        assert stat.S_IMODE(os.stat(fleet / name).st_mode) == 0o600, name
    key = (fleet / "ca.key").read_bytes()
    again = CliRunner().invoke(cli, ["keys", "init", str(fleet)])  # issue 46: re-runnable, the authority kept
    assert again.exit_code == 0 and "kept" in again.stdout and (fleet / "ca.key").read_bytes() == key
    cred = Credential.load(fleet / "car1.cred")
    assert cred.vehicle_id == "car1" and "private" not in repr(cred)
    assert len(cred.certificate_bytes) < 200  # travels in every signed frame


def test_a_vehicle_signs_only_as_itself_and_no_one_else_as_the_ego(fleet, pair):
    """Finding 5: with one shared fleet key, any holder signed as the ego (cache poisoning) or as another car."""
    _, ego, peer = pair[0]
    auth = AuthSettings(
        ca_cert=fleet / "ca.pub", credential=fleet / "ego.cred", fleet_key=FLEET_KEY, fleet_ids=["car7", "old-*"]
    )
    ring = auth.keyring()
    car1, car2 = Credential.load(fleet / "car1.cred"), Credential.load(fleet / "car2.cred")
    now = time.time()

    def load(data):
        return load_frame(data, LIMITS, keyring=ring, now=now)

    assert load(_enc(peer, "car2", 1, now, key=car2)).vehicle_id == "car2"
    with pytest.raises(WireError) as e:  # car2's credential, car1's id
        load(_enc(peer, "car1", 1, now, key=car2))
    assert (e.value.status, e.value.field, e.value.limit) == (403, "vehicle_id", "car2")
    with pytest.raises(WireError) as e:  # a key id that is not the certificate's
        load(sign(pack(load(_enc(peer, "car2", 2, now, key=car2))), car2).replace(b"car2", b"car1", 1))
    assert e.value.status in (401, 403)
    with pytest.raises(WireError) as e:  # the fleet key can no longer sign as the ego ...
        load(_enc(ego, "ego", 9, now, key=FLEET_KEY))
    assert (e.value.status, e.value.error, e.value.field) == (403, "forbidden", "vehicle_id")
    with pytest.raises(WireError) as e:  # ... nor as car2, which signed for itself (finding 5: blocking car4)
        load(_enc(peer, "car2", 10**6, now + 1.9, key=FLEET_KEY))
    assert (e.value.status, e.value.error) == (403, "forbidden")
    assert load(_enc(peer, "car7", 1, now, key=FLEET_KEY)).vehicle_id == "car7"  # its reserved id space
    assert load(_enc(peer, "old-3", 1, now, key=FLEET_KEY)).vehicle_id == "old-3"
    with pytest.raises(WireError) as e:  # issue 31 F2: car1 never signed here (a restart), still not the fleet's
        load(_enc(peer, "car1", 10**6, now + 1.9, key=FLEET_KEY))
    assert (e.value.status, e.value.error) == (403, "forbidden") and "auth.fleet_ids" in e.value.detail
    in_fleet_space = FleetAuthority.load(fleet).issue("car7")  # a certificate for the fleet key's ids: refused
    with pytest.raises(WireError) as e:
        load(_enc(peer, "car7", 2, now, key=in_fleet_space))
    assert (e.value.status, e.value.error) == (403, "forbidden")
    rogue = FleetAuthority.generate("bb-align-fleet-ca")  # same name, another key: not trusted
    with pytest.raises(WireError) as e:
        load(_enc(ego, "ego", 11, now, key=rogue.issue("ego")))
    assert (e.value.status, e.value.field) == (401, "mac") and "authority signature" in e.value.detail
    second_ego = FleetAuthority.load(fleet).issue("ego")  # a genuine certificate for "ego", not the pinned key
    with pytest.raises(WireError) as e:
        load(_enc(ego, "ego", 12, now, key=second_ego))
    assert (e.value.status, e.value.error) == (403, "forbidden") and "pinned" in e.value.detail
    expired = FleetAuthority.load(fleet).issue("car1", days=1.0, not_before=now - 3 * 86400)
    with pytest.raises(WireError) as e:
        load(_enc(peer, "car1", 1, now, key=expired))
    assert e.value.status == 401 and "not valid now" in e.value.detail
    assert load(_enc(ego, "ego", 13, now, key=Credential.load(fleet / "ego.cred"))).vehicle_id == "ego"
    assert load(_enc(peer, "car1", 2, now, key=car1)).vehicle_id == "car1"


def test_settings_refuse_a_credential_for_another_id_or_without_its_authority(fleet):
    s = secure_settings(False, auth={"ca_cert": str(fleet / "ca.pub"), "credential": str(fleet / "car1.cred")})
    assert "car1" in s.startup_problem() and "ego" in s.startup_problem()
    s = secure_settings(False, auth={"credential": str(fleet / "ego.cred")})
    assert "ca_cert" in s.startup_problem()
    assert _settings(fleet, zenoh=False).startup_problem() is None


# ---- signed answers (finding 1) --------------------------------------------------------------------------------
def test_a_forged_pose_on_the_air_is_refused_and_real_answers_verify(fleet, pair):
    """Finding 1: a keyless Zenoh client published a Result on poses/ego/car2 and car2's ZenohPeer accepted it."""
    settings = _settings(fleet, fleet_key=None)
    ep = settings.zenoh.listen
    car2_cred, ego_cred = Credential.load(fleet / "car2.cred"), Credential.load(fleet / "ego.cred")
    forged = Result(ego_id="ego", peer_id="car2", peer_seq=0, peer_stamp=1.0, success=True, yaw_deg=90.0)
    car2_ep = [f"tcp/127.0.0.1:{free_port()}"]  # the attacker reaches car2 directly (peers do not relay)
    with running_service(settings):
        with (
            ZenohPeer(
                "car2", connect=ep, listen=car2_ep, key=car2_cred, trust=fleet / "ca.pub", block_when_congested=True
            ) as car2,
            ZenohPeer("ego", connect=ep, key=ego_cred, trust=fleet / "ca.pub", block_when_congested=True) as ego_car,
            zenoh.open(ZenohSettings(listen=[], connect=car2_ep).to_zenoh_config()) as attacker,
        ):
            poses = car2.poses("ego")
            assert car2.wait_for_subscriber(10) and ego_car.wait_for_subscriber(10)
            time.sleep(0.3)
            attacker.put(poses_key("bbalign", "ego", "car2"), pack(forged))  # unsigned
            car1 = Credential.load(fleet / "car1.cred")  # a genuine fleet member signing an answer as itself
            attacker.put(poses_key("bbalign", "ego", "car2"), sign_result(forged.model_copy(), car1))
            with pytest.raises(TimeoutError):  # both dropped (issue 31: an attacker cannot make get() raise)
                poses.get(timeout=2)
            assert poses.rejected == {"unverified": 1, "another_ego": 1}
            t = time.time()
            (_, ego, peer), (_, ego1, peer1) = pair
            ego_car.publish(_enc(ego, "ego", 0, t))
            wait_for(lambda: httpx.get(f"http://127.0.0.1:{settings.port}/readyz").json()["ego_frames"] >= 1)
            car2.publish(_enc(peer, "car2", 0, t))
            res = poses.get(timeout=60)  # the service's own answer: signed with ego.cred, verified
            assert res.peer_id == "car2" and res.ego_id == "ego" and res.success
            res = car2.request_align(_enc(peer1, "car2", 1, t + 0.05), "ego", timeout=60)  # a query reply
            assert res.peer_id == "car2" and res.peer_seq == 1
        with pytest.raises(ValueError, match="verify_answers=False"):
            ZenohPeer("car2", connect=ep, key=car2_cred)  # no trust anchor: refuses to take unverified poses


def test_rest_answers_are_signed_and_a_tampered_one_is_refused(fleet, pair):
    settings = _settings(fleet, zenoh=False)
    _, ego, peer = pair[0]
    trust = AnswerTrust(TrustStore.load(fleet / "ca.pub"))
    with running_service(settings) as (_, url):
        ego_cred, car1 = Credential.load(fleet / "ego.cred"), Credential.load(fleet / "car1.cred")
        with AlignClient(url, key=car1, trust=fleet / "ca.pub") as client:
            res = client.align(_enc(peer, "car1", 0), _enc(ego, "ego", 0, key=ego_cred))
            assert res.success and res.ego_id == "ego"
        t = time.time()
        body = pack_align_request(_enc(peer, "car1", 1, t, key=car1), _enc(ego, "ego", 1, t, key=ego_cred))
        r = httpx.post(f"{url}/v1/align", content=body, headers={"content-type": "application/json"})
        assert r.status_code == 400  # msgpack body declared as JSON
        r = httpx.post(f"{url}/v1/align", content=body, headers={"content-type": "application/msgpack"})
        assert r.status_code == 200 and r.json()["alg"] == "ed25519"  # a JSON Signed envelope
        assert load_result(r.content, trust).peer_seq == 1
        env = msgpack.unpackb(
            httpx.post(
                f"{url}/v1/align",
                content=pack_align_request(
                    _enc(peer, "car1", 2, t + 0.01, key=car1), _enc(ego, "ego", 2, t + 0.01, key=ego_cred)
                ),
                headers={"content-type": "application/msgpack", "accept": "application/msgpack"},
            ).content
        )
        res = msgpack.unpackb(env["payload"])
        res["yaw_deg"] = 123.0
        env["payload"] = msgpack.packb(res)
        with pytest.raises(WireError) as e:
            load_result(msgpack.packb(env), trust)
        assert e.value.status == 401 and "does not match" in e.value.detail


# ---- replays across doors, inline ego frames (finding 6) -------------------------------------------------------
def test_one_replay_window_across_doors_and_inline_ego_frames_are_the_egos(pair):
    """Finding 6: a frame taken from the Zenoh stream was accepted again by /v1/align; an inline ego frame was
    neither replay-checked nor required to carry the ego id."""
    settings = secure_settings(True)
    (_, ego, peer), (_, ego1, peer1) = pair
    with running_service(settings) as (_, url):
        with (
            ZenohPeer("car1", connect=settings.zenoh.listen, key=FLEET_KEY, block_when_congested=True) as car,
            AlignClient(url, key=FLEET_KEY) as client,
        ):
            assert car.wait_for_subscriber(10)
            t = time.time()
            on_air = _enc(peer, "car1", 5, t, key=FLEET_KEY)
            car.publish(on_air)
            wait_for(lambda: "car1" in client.peers(), what="car1 tracked")
            with pytest.raises(ServiceError) as e:  # the same signed frame, taken from the air, sent to REST
                client.align(on_air, _enc(ego, "ego", 5, t))
            assert (e.value.status, e.value.body.error) == (409, "replayed")
            with pytest.raises(ServiceError) as e:
                client.post_frame(on_air)
            assert e.value.status == 409
            with pytest.raises(ServiceError) as e:  # an inline "ego" frame that is another car's
                client.align(_enc(peer1, "car1", 6, t + 0.1), _enc(ego1, "car9", 6, t + 0.1))
            assert (e.value.status, e.value.body.field) == (422, "ego.vehicle_id")
            ego_inline = _enc(ego1, "ego", 7, t + 0.1, key=FLEET_KEY)
            assert client.align(_enc(peer1, "car1", 7, t + 0.1), ego_inline).peer_seq == 7
            with pytest.raises(ServiceError) as e:  # the inline ego frame replayed
                client.align(_enc(peer1, "car1", 8, t + 0.15), ego_inline)
            assert (e.value.status, e.value.body.error) == (409, "replayed")


# ---- REST hardening (findings 4, 7) ----------------------------------------------------------------------------
def test_rest_refuses_key_type_mixes_coercion_and_0x0_images(pair):
    """Findings 4 and 7: 82a16101c4016202 was an HTTP 500; a 0x0 PNG was 202; coercion was silent."""
    settings = secure_settings(False, limits={"check_stamp_clock": False})
    with running_service(settings) as (_, url):
        ct = {"content-type": "application/msgpack"}
        r = httpx.post(f"{url}/v1/align", content=bytes.fromhex("82a16101c4016202"), headers=ct)
        assert r.status_code == 400 and r.json()["error"] == "undecodable"
        _, _, peer = pair[0]
        frame = load_frame(_enc(peer, "car1", 1, 100.0), LIMITS)
        d = frame.model_dump(mode="python")
        tiny = {**d, "bev": {**d["bev"], "range_m": 0.001, "resolution_m": 5.0}}
        r = httpx.post(f"{url}/v1/frames", content=sign(msgpack.packb(tiny, use_bin_type=True), FLEET_KEY), headers=ct)
        assert r.status_code == 422 and r.json()["field"] == "bev.range_m" and r.json()["limit"] == 16
        r = httpx.post(
            f"{url}/v1/frames", content=sign(msgpack.packb({**d, "seq": "1"}, use_bin_type=True), FLEET_KEY), headers=ct
        )
        assert r.status_code == 422 and r.json()["field"] == "seq"


# ---- a keyless flood (finding 2) -------------------------------------------------------------------------------
def _metric_value(text: str, name: str, **labels) -> float:
    want = name + ("{" + ",".join(f'{k}="{v}"' for k, v in labels.items()) + "}" if labels else "")
    return sum(float(ln.rsplit(" ", 1)[1]) for ln in text.splitlines() if ln.startswith(want + " "))


def test_a_keyless_flood_cannot_push_signed_frames_out(fleet, pair):
    """Finding 2: 1-byte garbage at ~79k msg/s on frames/car2 cost car1 93 of ~100 frames and the ego 42/100;
    1 MB zero-MAC envelopes on frames/ego let ~11/100 ego frames in. Now the Zenoh door refuses junk before it can
    wait anywhere (never queued, never charged to car1), within its CPU budget. The flooder is its own process
    (bb_align.lab.flood), as an attacker is: one sharing this process's GIL would slow the service it attacks by
    other means than its messages."""
    from bb_align.lab.flood import FloodConfig, FloodProcess

    settings = _settings(fleet, fleet_key=FLEET_KEY)
    ep = settings.zenoh.listen
    n = 30
    (_, ego, peer), _ = pair
    ego_cred, car1_cred = Credential.load(fleet / "ego.cred"), Credential.load(fleet / "car1.cred")
    # 1-byte junk and 1 MB zero-MAC / unsigned envelopes on both the ego's and car1's own frame keys, for the
    # whole run (the lead, n frames at 10 Hz, the tail) and then it stops by itself.
    config = FloodConfig(duration_s=1.0 + 0.1 * n + 1.5, small_per_cycle=50, replays_per_cycle=0)
    with running_service(settings) as (_, url):
        with (
            ZenohPeer("ego", connect=ep, key=ego_cred, trust=fleet / "ca.pub", block_when_congested=True) as ego_car,
            ZenohPeer("car1", connect=ep, key=car1_cred, trust=fleet / "ca.pub", block_when_congested=True) as car1,
        ):
            assert ego_car.wait_for_subscriber(10) and car1.wait_for_subscriber(10)
            # A car's link to the service closed by Zenoh (a stalled link is closed after 5 s) would lose its
            # queued frames: watched, so a failure says whether the frames were lost on the air or in the service.
            link_events: list[tuple[str, str, str]] = []
            watchers = [
                car.session.info.declare_link_events_listener(
                    lambda e, name=name: link_events.append((name, str(e.kind), str(e.link.dst)))
                )
                for name, car in (("ego", ego_car), ("car1", car1))
            ]
            flooder = FloodProcess(ep[0], settings.zenoh.prefix, {"ego": None, "car1": None}, config)
            try:
                flooder.start()
                time.sleep(1.0)  # the flood is running before the first real frame
                for k in range(n):
                    t = time.time()
                    ego_car.publish(_enc(ego, "ego", k, t))
                    car1.publish(_enc(peer, "car1", k, t))
                    time.sleep(0.1)
                flooded = flooder.finish()
            finally:
                flooder.stop()

            def accepted():
                t = httpx.get(f"{url}/metrics").text
                return _metric_value(t, "bbalign_frames_received_total", door="zenoh", kind="ego"), httpx.get(
                    f"{url}/v1/peers"
                ).json().get("car1", {}).get("frames_accepted", 0)

            try:
                wait_for(lambda: accepted() == (n, n), timeout=30, what=f"all {n} ego and car1 frames accepted")
            except AssertionError as e:
                refusals = [
                    ln
                    for ln in httpx.get(f"{url}/metrics").text.splitlines()
                    if ln.startswith(
                        (
                            "bbalign_door_refused_total",
                            "bbalign_frames_rejected_total",
                            "bbalign_door_throttled",
                            "bbalign_intake_dropped",
                        )
                    )
                ]
                car1_status = httpx.get(f"{url}/v1/peers").json().get("car1")
                raise AssertionError(
                    f"{e}: (ego, car1) accepted {accepted()}, flood {flooded}, car1 {car1_status}, "
                    f"metrics {refusals}, car links opened/closed {link_events}"
                ) from None
            text = httpx.get(f"{url}/metrics").text
            status = httpx.get(f"{url}/v1/peers").json()["car1"]
            for w in watchers:
                w.undeclare()
    assert _metric_value(text, "bbalign_door_refused_total", error="undecodable") > 10 * n  # the 1-byte junk
    assert _metric_value(text, "bbalign_door_refused_total", error="unauthenticated") > 0  # the zero-MAC envelopes
    assert flooded["messages"]["byte"] > 10 * n and flooded["messages"]["zero_mac_hmac"] > 0, flooded
    assert status["intake_dropped"] == 0  # junk under car1's key is never charged to car1
    for lane in ("ego", "signed", "unverified"):  # junk never took a place in the intake
        assert _metric_value(text, "bbalign_intake_dropped_total", lane=lane) == 0
    assert _metric_value(text, "bbalign_frames_rejected_total", door="zenoh", error="undecodable") > 0


def test_a_forged_1mb_flood_never_puts_the_door_to_sleep_and_other_cars_frames_come_through(fleet, pair):
    """Issue 47's probe: 2 keyless sessions forging car1's 1 MB frames (its certificate copied from the air, a zero
    or random signature, fresh stamps) at full speed; each forgery cost the door ~2 ms outside its signature check
    (copies out of Zenoh and of the envelope), paid by sleeping ~110 ms at the door's 0.02 share, so the door slept
    the whole flood and car2's frames waited behind the forgeries in Zenoh's FIFO (p50 4.9 s; 0.47 of its
    results). Now the door drops the forgeries unread once its share is spent and never sleeps for them (its
    waits, while the drops alone spend the share, are 1 ms at most): every frame car2 sends during the flood is
    accepted within a second of the last one."""
    from bb_align.lab.flood import FloodConfig, FloodProcess

    settings = _settings(fleet)
    ep = settings.zenoh.listen
    n = 20
    (_, _, peer), _ = pair
    car1_cert = Credential.load(fleet / "car1.cred").certificate_bytes
    config = FloodConfig(
        duration_s=5.0, small_per_cycle=0, replays_per_cycle=0, kinds=["forged_frame", "forged_frame_random_sig"]
    )
    with running_service(settings) as (_, url):
        car2_cred = Credential.load(fleet / "car2.cred")
        with ZenohPeer("car2", connect=ep, key=car2_cred, trust=fleet / "ca.pub", block_when_congested=True) as car2:
            assert car2.wait_for_subscriber(10)
            flooders = [FloodProcess(ep[0], settings.zenoh.prefix, {"car1": car1_cert}, config) for _ in range(2)]
            try:
                for f in flooders:
                    f.start()
                time.sleep(1.0)  # the flood is running before car2's first frame
                for k in range(n):
                    car2.publish(_enc(peer, "car2", k))
                    time.sleep(0.05)

                def accepted():
                    return httpx.get(f"{url}/v1/peers").json().get("car2", {}).get("frames_accepted", 0)

                wait_for(lambda: accepted() == n, timeout=1.0, what=f"car2's {n} frames accepted during the flood")
                flooded = [f.finish() for f in flooders]
            finally:
                for f in flooders:
                    f.stop()
            text = httpx.get(f"{url}/metrics").text
    sent = sum(f["messages"]["forged_frame"] + f["messages"]["forged_frame_random_sig"] for f in flooded)
    assert sent > 50, flooded  # a real flood, not pushed back to a few a second
    refused = sum(_metric_value(text, "bbalign_door_refused_total", error=e) for e in ("overloaded", "unauthenticated"))
    assert _metric_value(text, "bbalign_door_refused_total", error="overloaded") > 0  # dropped unread / unchecked
    # the door's waits: at most 1 ms a refusal (before: ~110 ms a forgery, the whole flood asleep)
    assert _metric_value(text, "bbalign_door_throttled_seconds") <= 0.001 * refused + 0.01


# ---- bounded work per frame (finding 3) ------------------------------------------------------------------------
@pytest.mark.parametrize("range_m", [208.0, 225.0, 250.0])
def test_a_small_coarse_frame_cannot_make_the_engine_work_on_a_huge_image(range_m):
    """Finding 3: a signed 5-7 KB frame (100 px PNG at 5 m/px, range 208-250 m) was upscaled to ~1250 px: 1.4-4 s
    per align, and eight such shapes took the service from 363 MB to 2.85 GB (per-shape filter-bank cache)."""
    import cv2
    import numpy as np

    from bb_align.engine.bev import image_size_px
    from bb_align.engine.config import BevConfig

    settings = secure_settings(False)
    limits = settings.limits
    assert limits.engine_resolution_m == settings.align.bev.resolution_m
    assert limits.max_resampled_px == image_size_px(settings.align.bev)
    n = image_size_px(BevConfig(range_m=range_m, resolution_m=5.0))
    img = np.zeros((n, n), np.uint8)
    img[::7, ::5] = 200
    frame = {
        "schema_version": 1,
        "vehicle_id": "car1",
        "seq": 1,
        "stamp": time.time(),
        "png": cv2.imencode(".png", img)[1].tobytes(),
        "bev": {"resolution_m": 5.0, "range_m": range_m},
    }
    data = sign(msgpack.packb(frame, use_bin_type=True), FLEET_KEY)
    assert len(data) < 8000
    with pytest.raises(WireError) as e:
        load_frame(data, limits, keyring=settings.auth.keyring(), now=time.time())
    assert (e.value.status, e.value.field, e.value.limit) == (422, "bev.resolution_m", limits.max_resampled_px)
    assert load_frame(data, Limits(), now=time.time()).bev.range_m == range_m  # only the service's limits refuse


def test_the_filter_bank_cache_is_bounded_in_bytes():
    import numpy as np

    from bb_align.engine.config import MimConfig
    from bb_align.engine.loggabor import _blocks, filter_bank, maximum_index_map

    cfg = MimConfig(filter_cache_mb=40.0, threads=1)
    _blocks.cache_clear()
    filter_bank.cache_clear()
    rng = np.random.default_rng(0)
    for side in (180, 200, 220, 240, 260, 280, 300, 320):  # eight odd shapes
        maximum_index_map(rng.integers(0, 255, (side, side)).astype(np.uint8), cfg)
        assert _blocks.cache_bytes() <= 40 * 2**20
    assert _blocks.cache_bytes() > 0 and filter_bank.cache_bytes() == 0  # the full banks are not kept
    _blocks.cache_clear()


# ---- issue 14: refusals of a certified car's pub/sub frames reach that car -------------------------------------
def test_a_certified_car_hears_why_its_frame_was_refused(fleet, pair):
    """Ed25519 credentials: car1 publishes a frame stamped 812 s ago (recorded data on a live service). It passes
    the Zenoh door (signed, newer than anything of car1's) and the gate refuses it; car1 gets a Refusal signed by
    the ego's credential, verified against ca.pub by ZenohPeer and raised as FrameRefused naming the setting.
    (A byte-for-byte copy or a frame not newer than the car's last is refused at the door silently: on the air it
    is most likely somebody else's replay, docs/security.md.)"""
    settings = _settings(fleet, fleet_key=None)
    car1 = Credential.load(fleet / "car1.cred")
    with running_service(settings):
        with ZenohPeer(
            "car1", connect=settings.zenoh.listen, key=car1, trust=fleet / "ca.pub", block_when_congested=True
        ) as car:
            poses = car.poses("ego")
            assert car.wait_for_subscriber(10)
            time.sleep(0.2)
            car.publish(_enc(pair[0][2], "car1", 5, stamp=time.time() - 812.0, key=car1))
            with pytest.raises(FrameRefused) as e:
                poses.get(timeout=20)
    assert (e.value.status, e.value.body.error, e.value.body.setting) == (
        422,
        "invalid",
        "BBALIGN_LIMITS__MAX_STAMP_AGE_S",
    )
    assert e.value.peer_seq == 5 and "bb-align serve --replay" in e.value.body.detail


# ---- issue 31, F1: answers bound to what was asked ------------------------------------------------------------
def test_a_recorded_answer_or_a_rogue_queryable_never_answers_for_the_ego(fleet, pair):
    """F1: a keyless recorder re-published the ego's genuine signed answers on poses/ego/car1 and car1 took car2's
    Result, its own old Result and car2's Refusal; a rogue keyless queryable replying 1 s after the service won
    every request_align (the client took the last reply). Now car1 takes only answers for frames it sent, once,
    never backwards, and request_align asks every queryable and takes the ego's answer to this very frame."""
    import threading

    from bb_align.engine.config import AlignConfig, BevConfig, TrackConfig
    from bb_align.protocol import align_key

    # tracking off: each answer is the frame's own alignment (what it says does not matter here, only whose it is)
    align = AlignConfig(bev=BevConfig(range_m=RANGE_M), track=TrackConfig(enabled=False))
    settings = _settings(fleet, fleet_key=None, align=align)
    ep, ca = settings.zenoh.listen, fleet / "ca.pub"
    creds = {v: Credential.load(fleet / f"{v}.cred") for v in ("ego", "car1", "car2")}
    (_, ego, peer), (_, ego1, peer1) = pair
    recorded: list[tuple[str, bytes]] = []
    heard: list[tuple[str, bytes]] = []
    late: list[threading.Thread] = []

    def rogue(query):  # answers at once with car2's genuine Result and an unsigned error, and again 1 s later
        query.reply(align_key("bbalign", "ego"), recorded_answer("car2"))
        query.reply_err(msgpack.packb({"error": "overloaded", "detail": "forged"}))

        def later():
            time.sleep(1.0)
            with query:
                query.reply(align_key("bbalign", "ego"), recorded_answer("car1"))

        late.append(threading.Thread(target=later, daemon=True))
        late[-1].start()

    def recorded_answer(peer_id):
        return next(data for key, data in heard if key.endswith("/" + peer_id) and b"refused" not in data)

    car1_ep = [f"tcp/127.0.0.1:{free_port()}"]  # the attacker reaches car1 directly (peers do not relay)
    with running_service(settings) as (_, url):
        with (
            ZenohPeer("ego", connect=ep, key=creds["ego"], trust=ca, block_when_congested=True) as ego_car,
            ZenohPeer(
                "car1", connect=ep, listen=car1_ep, key=creds["car1"], trust=ca, block_when_congested=True
            ) as car1,
            ZenohPeer("car2", connect=ep, key=creds["car2"], trust=ca, block_when_congested=True) as car2,
            zenoh.open(ZenohSettings(listen=[], connect=ep + car1_ep).to_zenoh_config()) as attacker,
        ):
            tape = attacker.declare_subscriber(
                "bbalign/poses/ego/*", lambda s: recorded.append((str(s.key_expr), s.payload.to_bytes()))
            )
            poses1, poses2 = car1.poses("ego"), car2.poses("ego")
            assert all(c.wait_for_subscriber(10) for c in (ego_car, car1, car2))
            time.sleep(0.3)
            t = time.time()
            ego_car.publish(_enc(ego, "ego", 0, t))
            wait_for(lambda: httpx.get(f"{url}/readyz").json()["ego_frames"] >= 1)
            car2.publish(_enc(peer, "car2", 0, t - 812.0))  # refused by the gate: a signed Refusal for car2
            with pytest.raises(FrameRefused):
                poses2.get(timeout=30)
            car1.publish(_enc(peer, "car1", 0, t))
            car2.publish(_enc(peer, "car2", 1, t))
            assert (poses1.get(timeout=60).peer_seq, poses2.get(timeout=60).peer_seq) == (0, 1)
            wait_for(lambda: len(recorded) >= 3, what="the recorder heard three answers")
            heard.extend(recorded)
            assert len(heard) == 3
            for _, data in heard:  # car2's Refusal and Result, and car1's own Result, again on car1's key
                attacker.put(poses_key("bbalign", "ego", "car1"), data)
            with pytest.raises(TimeoutError):
                poses1.get(timeout=2)
            assert poses1.rejected == {"another_peer": 2, "backwards": 1}

            rogue_queryable = attacker.declare_queryable(align_key("bbalign", "ego"), rogue, complete=True)
            time.sleep(0.3)
            answers = [car1.request_align(_enc(peer1, "car1", k, t + 0.01 * k), "ego", timeout=30) for k in (1, 2, 3)]
            assert [(a.peer_id, a.peer_seq, a.peer_stamp) for a in answers] == [
                ("car1", k, t + 0.01 * k) for k in (1, 2, 3)
            ]  # each the ego's answer to that very frame: 0 of 3 foreign answers taken
            assert car1.rejected["not_sent"] >= 3 and car1.rejected["unsigned_error"] >= 3
            for th in late:
                th.join(5)
            rogue_queryable.undeclare()
            tape.undeclare()


def test_the_rest_client_pins_the_ego_and_the_frame_it_asked_about(fleet, pair):
    """F1: AlignClient took an answer signed by car2 claiming ego_id=car2, and any genuine answer of the ego."""
    _, _, peer = pair[0]
    car1, car2, ego_cred = (Credential.load(fleet / f"{v}.cred") for v in ("car1", "car2", "ego"))
    t = time.time()
    frame = _enc(peer, "car1", 4, t, key=car1)
    asked = Result(ego_id="ego", peer_id="car1", peer_seq=4, peer_stamp=t, success=True, yaw_deg=1.0)
    replies = {
        "car2 as its own ego": sign_result(asked.model_copy(update={"ego_id": "car2"}), car2),
        "the ego, another frame": sign_result(asked.model_copy(update={"peer_seq": 3}), ego_cred),
        "the ego, another car": sign_result(asked.model_copy(update={"peer_id": "car2"}), ego_cred),
        "the ego, this frame": sign_result(asked, ego_cred),
    }
    outcomes = {}
    for name, body in replies.items():
        client = AlignClient("http://127.0.0.1:9", key=car1, trust=fleet / "ca.pub")
        client._http = httpx.Client(  # the network, as the attacker controls it
            base_url="http://127.0.0.1:9",
            transport=httpx.MockTransport(lambda r, b=body: httpx.Response(200, content=b)),
        )
        try:
            outcomes[name] = client.align(frame).peer_seq
        except WireError as e:
            outcomes[name] = (e.status, e.field)
        client.close()
    assert outcomes == {
        "car2 as its own ego": (403, "ego_id"),
        "the ego, another frame": (409, "peer_seq"),
        "the ego, another car": (409, "peer_seq"),
        "the ego, this frame": 4,
    }


# ---- issue 31, F2/F3: identities that cannot be borrowed -------------------------------------------------------
def test_a_fleet_key_holder_cannot_lock_out_or_speak_as_a_certified_car(fleet, pair):
    """F2 (mixed mode: authority and fleet key): before car1's first frame (or after a restart) the fleet key signed
    as car1 with stamps 1.9 s ahead; its 12 frames were aligned as car1's and genuine car1 got 0 of 117 frames in
    (all 'replayed'). Now the fleet key speaks only for auth.fleet_ids: its frames are refused (403) without
    touching car1's replay window, and every genuine frame of car1 is taken."""
    settings = _settings(fleet, fleet_key=FLEET_KEY, fleet_ids=["legacy-*"])
    ep = settings.zenoh.listen
    _, _, peer = pair[0]
    with running_service(settings) as (_, url):
        with (
            ZenohPeer("car1", connect=ep, key=FLEET_KEY, block_when_congested=True, verify_answers=False) as forger,
            ZenohPeer("car1", connect=ep, key=Credential.load(fleet / "car1.cred"), trust=fleet / "ca.pub") as car1,
            AlignClient(url, key=FLEET_KEY, trust=fleet / "ca.pub") as rest,
        ):
            car1.block_when_congested = True
            assert forger.wait_for_subscriber(10) and car1.wait_for_subscriber(10)
            t0 = time.time()
            for i in range(12):  # the forger first, with stamps ahead of everything car1 will send
                forger.publish(_enc(peer, "car1", 10**6 + i, t0 + 1.9))
            with pytest.raises(ServiceError) as e:  # and over REST
                rest.post_frame(_enc(peer, "car1", 10**6 + 99, t0 + 1.9))
            assert (e.value.status, e.value.body.error) == (403, "forbidden")
            for i in range(10):
                car1.publish(_enc(peer, "car1", i, time.time()))
                time.sleep(0.05)
            wait_for(lambda: httpx.get(f"{url}/v1/peers").json().get("car1", {}).get("frames_accepted") == 10)
            text = httpx.get(f"{url}/metrics").text
            forged = _metric_value(text, "bbalign_frames_rejected_total", door="zenoh", error="forbidden")
            assert forged == 12, text
            r = httpx.post(  # the reserved id space still works for the shared key
                f"{url}/v1/frames",
                content=_enc(peer, "legacy-7", 1, time.time(), key=FLEET_KEY),
                headers={"content-type": "application/msgpack"},
            )
            assert r.status_code == 202, r.text


def test_no_certificate_is_issued_for_or_acts_as_the_fleet_key(fleet, pair):
    """F3: a certificate for the id 'fleet' was treated as the fleet key (it signed as any unseen id, and answers
    as any ego); `bb-align keys issue DIR fleet` was allowed."""
    from bb_align.protocol import Certificate
    from bb_align.protocol.identity import CERT_DOMAIN

    r = CliRunner().invoke(cli, ["keys", "issue", str(fleet), "fleet"])
    assert r.exit_code == 2 and "reserved" in r.output and not (fleet / "fleet.cred").exists()
    ca = FleetAuthority.load(fleet)  # the authority itself signing one by hand: still refused by every receiver
    own = FleetAuthority.load(fleet).issue("car9")
    unsigned = Certificate(ca.name, "fleet", own.certificate.public_key, time.time() - 60, time.time() + 3600, b"")
    cert = Certificate(**{**unsigned.__dict__, "signature": ca._key.sign(CERT_DOMAIN + unsigned.tbs())})
    rogue = Credential(cert, own._key)
    _, ego, peer = pair[0]
    ring = AuthSettings(ca_cert=fleet / "ca.pub", credential=fleet / "ego.cred").keyring()
    with pytest.raises(WireError) as e:
        load_frame(_enc(peer, "car3", 1, key=rogue), LIMITS, keyring=ring, now=time.time())
    assert (e.value.status, e.value.error) == (403, "forbidden") and "reserved" in e.value.detail
    forged = Result(ego_id="ego", peer_id="car3", peer_seq=1, peer_stamp=time.time(), success=True)
    with pytest.raises(WireError) as e:
        load_result(sign_result(forged, rogue), AnswerTrust(TrustStore.load(fleet / "ca.pub")))
    assert e.value.status == 403
    with pytest.raises(ValueError, match="reserved"):
        secure_settings(False, ego_id="fleet")


# ---- issue 31, F4: revocation and key rotation ----------------------------------------------------------------
def test_a_revoked_certificate_is_refused_and_a_rotated_key_is_taken(tmp_path, pair):
    """F4: a certificate stayed valid until it expired (365 days by default); there was no revocation."""
    runner = CliRunner()
    for args in (["init", str(tmp_path)], *(["issue", str(tmp_path), v] for v in ("ego", "car1", "car2"))):
        assert runner.invoke(cli, ["keys", *args]).exit_code == 0
    old_car2 = Credential.load(tmp_path / "car2.cred")
    r = runner.invoke(cli, ["keys", "revoke", str(tmp_path), "car2"])
    assert r.exit_code == 0 and f"BBALIGN_AUTH__REVOCATIONS={(tmp_path / 'revoked.json').resolve()}" in r.output
    assert runner.invoke(cli, ["keys", "revoke", str(tmp_path), "car8"]).exit_code == 2  # no such credential
    settings = secure_settings(
        False,
        auth={
            "ca_cert": str(tmp_path / "ca.pub"),
            "credential": str(tmp_path / "ego.cred"),
            "revocations": str(tmp_path / "revoked.json"),
            "revocations_state": str(tmp_path / "state.json"),
        },
    )
    assert settings.startup_problem() is None
    ring = settings.auth.keyring()
    ring.trust.revocations.poll_s = 0.0  # read the list again at once when it changes (default: every 2 s)
    _, _, peer = pair[0]

    def load(name, seq, key):
        return load_frame(_enc(peer, name, seq, key=key), LIMITS, keyring=ring, now=time.time())

    with pytest.raises(WireError) as e:
        load("car2", 1, old_car2)
    assert e.value.status == 401 and "revoked" in e.value.detail
    car1 = Credential.load(tmp_path / "car1.cred")
    assert load("car1", 1, car1).vehicle_id == "car1"
    assert runner.invoke(cli, ["keys", "issue", str(tmp_path), "car2", "--force"]).exit_code == 0  # rotation: a new key
    assert load("car2", 2, Credential.load(tmp_path / "car2.cred")).vehicle_id == "car2"
    time.sleep(0.01)  # a new mtime
    assert runner.invoke(cli, ["keys", "revoke", str(tmp_path), "car1"]).exit_code == 0  # while the service runs
    with pytest.raises(WireError) as e:
        load("car1", 2, car1)
    assert "revoked" in e.value.detail
    doc = (tmp_path / "revoked.json").read_text()  # a list edited by anyone but the authority
    (tmp_path / "revoked.json").write_text(doc.replace('"version": 2', '"version": 3'))
    fresh = secure_settings(False, auth=settings.auth.model_dump(exclude={"fleet_key", "rest_token"}))
    assert "does not verify" in fresh.startup_problem()


# ---- issue 31, F5: the replay window survives a restart ------------------------------------------------------
def test_frames_accepted_before_a_kill_are_refused_after_the_restart(tmp_path, pair):
    """F5: the replay window was only in memory: after kill -9 and a restart, frames signed 4.8 s earlier were
    accepted again. Now a new process refuses every frame stamped before its own start + max_stamp_lead_s."""
    from bb_align.lab.harness import start_service

    _, ego, peer = pair[0]
    ct = {"content-type": "application/msgpack"}
    outcomes, before = [], b""
    for run in range(2):
        settings = secure_settings(False)
        svc = start_service(settings, FLEET_KEY, tmp_path, timeout_s=120)
        try:
            if run == 0:  # stamped ahead within the lead, as a car whose clock is 1.9 s fast
                before = _enc(peer, "car1", 1, time.time() + 1.9, key=FLEET_KEY)
            outcomes.append(httpx.post(f"{svc.rest}/v1/frames", content=before, headers=ct).status_code)
            if run == 1:
                r = httpx.post(f"{svc.rest}/v1/frames", content=before, headers=ct)
                assert "before this service started" in r.json()["detail"]
                fresh = _enc(peer, "car1", 2, time.time() + 1.9, key=FLEET_KEY)  # started > 0.1 s ago
                outcomes.append(httpx.post(f"{svc.rest}/v1/frames", content=fresh, headers=ct).status_code)
        finally:
            if run == 0:
                svc.proc.kill()  # kill -9: nothing is saved
                svc.proc.wait(10)
            else:
                assert svc.stop() == 0
    assert outcomes == [202, 409, 202]


# ---- issue 31, F10: a per-key rate limit on REST ---------------------------------------------------------------
def test_rest_limits_each_verified_sender_and_only_after_its_signature(pair, monkeypatch):
    """F10: one key holder posting valid frames over REST had no rate limit. Now each verified sender has a token
    bucket (limits.rest_rate_hz, rest_burst; 429 past it); forged frames claiming car2 never spend car2's.
    Issue 47: each 429 still cost a full decode and signature check (one car's 8-thread flood cut other cars to
    0.17-0.23 of their results); now an empty bucket is refused first, before decoding or any signature check
    (counted with spies)."""
    import bb_align.server.app as app_module

    settings = secure_settings(False, limits={"rest_rate_hz": 0.5, "rest_burst": 5})
    _, _, peer = pair[0]
    ct = {"content-type": "application/msgpack"}
    loads, checks = [], []
    load = app_module.load_frame
    monkeypatch.setattr(app_module, "load_frame", lambda *a, **k: loads.append(1) or load(*a, **k))
    with running_service(settings) as (app, url):
        ring = app.state.service.keyring
        verify = ring.verify_signed
        ring.verify_signed = lambda *a, **k: checks.append(1) or verify(*a, **k)
        t = time.time()

        def post(name, seq, key=FLEET_KEY):
            return httpx.post(f"{url}/v1/frames", content=_enc(peer, name, seq, t + 0.001 * seq, key=key), headers=ct)

        car1 = [post("car1", i) for i in range(10)]
        passed = sum(r.status_code != 429 for r in car1)
        assert len(loads) == passed and len(checks) == 2 * passed  # the door's check and the loader's; none for a 429
        forged = [post("car2", i, key="not-the-fleet-key-0123456789") for i in range(10)]
        car2 = [post("car2", 100 + i).status_code for i in range(5)]
    codes = [r.status_code for r in car1]
    assert codes[:5] == [202] * 5 and codes.count(429) >= 4, codes  # 0.5/s: at most one more within 2 s
    refused = next(r.json() for r in car1 if r.status_code == 429)
    assert (refused["field"], refused["setting"]) == ("vehicle_id", "BBALIGN_LIMITS__REST_RATE_HZ")
    assert {r.headers.get("retry-after") for r in car1 if r.status_code == 429} == {"1"}  # when to try again
    assert all("retry-after" not in r.headers for r in car1 if r.status_code == 202)
    assert {r.status_code for r in forged} == {401} and car2 == [202] * 5
