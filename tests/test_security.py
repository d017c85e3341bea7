"""Hostile input and authentication (issue 6): the shared validator against crafted attacks and fuzzing, frame
signatures and replays, the REST bearer token, a 100 MB body, and schemathesis against the REST OpenAPI schema.
Everything networked runs on 127.0.0.1."""

from __future__ import annotations

import hashlib
import hmac
import json
import socket
import struct
import time
import tracemalloc
import zlib

import cv2
import httpx
import msgpack
import numpy as np
import pytest
import schemathesis  # noqa: E402
from hypothesis import HealthCheck, given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from bb_align.protocol import (
    JSON,
    MSGPACK,
    BevMeta,
    Frame,
    Limits,
    WireError,
    check_png,
    load_align_request,
    load_frame,
    pack,
    pack_align_request,
    sign,
    to_json,
)
from bb_align.protocol.signatures import DOMAIN
from bb_align.server.settings import AuthSettings
from bb_align_client import AlignClient, ServiceError, ZenohPeer, encode_frame, sign_frame
from service_support import (
    FLEET_KEY,
    RANGE_M,
    free_port,
    moving_pair,
    running_service,
    secure_settings,
    service_settings,
    wait_for,
)

LIMITS = Limits()
KEYRING = AuthSettings(fleet_key=FLEET_KEY, peer_keys={"car3": "car3-own-key-0123456789"}).keyring()
N = 100  # image side of the hand-made frames (range 20 m, 0.4 m cells)


def _png(img: np.ndarray) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def _image(seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((N, N), np.uint8)
    img[rng.integers(0, N, 300), rng.integers(0, N, 300)] = rng.integers(1, 255, 300)
    return img


def _frame(**kw) -> Frame:
    base = dict(
        vehicle_id="car1",
        seq=1,
        stamp=100.0,
        png=_png(_image()),
        bev=BevMeta(resolution_m=0.4, range_m=20),
        boxes=[[10.0, -2.0, 0.8, 4.5, 1.9, 1.6, 0.3]],
    )
    return Frame(**{**base, **kw})


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)))


def _make_png(idat: bytes, side=N, interlace=0, extra: bytes = b"", tail: bytes = b"") -> bytes:
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, interlace)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + extra + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"") + tail


def _refused(data: bytes, encoding=MSGPACK, limits=LIMITS, **kw) -> WireError:
    with pytest.raises(WireError) as e:
        load_frame(data, limits, encoding, **kw)
    return e.value


# ---- crafted attacks on the validator ------------------------------------------------------------------------
def test_png_bomb_is_refused_without_inflating_it():
    """Image data inflating to 100 MB behind a header of the largest allowed size (1024 px): the validator stops
    inflating at the 1 MB the header implies. Behind a 100 px header the same data is refused by its size."""
    idat = zlib.compress(bytes(100 * 2**20), 9)
    side = LIMITS.max_image_px
    frame = _frame(png=_make_png(idat, side=side), bev=BevMeta(resolution_m=0.4, range_m=side * 0.4 / 2))
    tracemalloc.start()
    e = _refused(pack(frame))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert (e.status, e.field, e.limit) == (422, "png", side * (side + 1)) and "inflate" in e.detail
    assert peak < 8 * 2**20, f"the validator allocated {peak} bytes"
    e = _refused(pack(_frame(png=_make_png(idat))))
    assert (e.status, e.field) == (422, "png") and "more than" in e.detail


_ROWS = bytes(np.column_stack([np.zeros(N, np.uint8), _image()]).tobytes())  # filter byte 0 + pixels per row


@pytest.mark.parametrize(
    "png,words",
    [
        (_make_png(zlib.compress(bytes(N * (N + 1)))), "ratio"),  # an empty image: ~500:1, over the 100 configured
        (_make_png(zlib.compress(bytes(N * (N + 1)), 0) + bytes(60_000)), "more than"),  # IDAT padded with junk
        (_make_png(zlib.compress(_ROWS)[:-8]), "inflate"),  # truncated stream
        (_make_png(zlib.compress(bytes(N * (N + 1)), 0), interlace=1), "interlace"),
        (_make_png(zlib.compress(bytes(N * (N + 1)), 0), extra=_chunk(b"PLTE", b"\x00" * 3)), "critical"),
        (_make_png(zlib.compress(bytes(N * (N + 1)), 0), tail=b"junk"), "after the PNG"),
        (_make_png(zlib.compress(bytes(N * (N + 1)), 0)).replace(b"IEND", b"IENX"), "checksum"),
        (_make_png(zlib.compress(b"\x07" * (N * (N + 1)), 0)), "filter"),
    ],
)
def test_malformed_png_structures_are_refused_before_decoding(png, words):
    e = _refused(pack(_frame(png=png)), limits=Limits(max_png_ratio=100))
    assert (e.status, e.field) == (422, "png") and words in e.detail, e.detail


def test_a_plain_stored_png_passes_and_decodes_to_its_pixels():
    rows = bytes(N * (N + 1))  # filter 0, all pixels 0
    frame = load_frame(pack(_frame(png=_make_png(zlib.compress(rows, 0)))), LIMITS)
    assert frame.bev_image().image.shape == (N, N) and frame.bev_image().image.max() == 0


@pytest.mark.parametrize("encoding", [MSGPACK, JSON])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_nan_and_inf_boxes_are_refused_naming_the_number(encoding, value):
    d = _frame().model_dump(mode="json" if encoding == JSON else "python")
    d["boxes"][0][2] = value
    data = json.dumps(d).encode() if encoding == JSON else msgpack.packb(d)  # Python's JSON writes NaN/Infinity
    e = _refused(data, encoding)
    assert (e.status, e.field) == (422, "boxes.0.2")


def test_a_million_boxes_are_refused_by_size_then_by_count():
    box = [1.0, 1.0, 0.0, 4.0, 2.0, 1.5, 0.0]
    d = {**_frame().model_dump(mode="json"), "boxes": [box] * 10**6}
    body = json.dumps(d).encode()
    e = _refused(body, JSON)
    assert (e.status, e.field, e.limit) == (413, "message", LIMITS.max_message_bytes)
    big = Limits(max_message_bytes=len(body) + 1)  # even when the size is allowed, no model is built for them
    e = _refused(body, JSON, limits=big)
    assert (e.status, e.field, e.limit) == (422, "boxes", LIMITS.max_boxes)
    e = _refused(
        msgpack.packb({**_frame().model_dump(mode="python"), "boxes": [box] * 10**6}),
        limits=Limits(max_message_bytes=64 * 2**20),
    )
    assert e.status == 400 and "max_array_len" in e.detail


def test_stamps_far_from_the_receivers_clock_are_refused():
    now = 1_750_000_000.0
    data = pack(_frame(stamp=now - 31))
    e = _refused(data, now=now)
    assert (e.status, e.field, e.limit) == (422, "stamp", LIMITS.max_stamp_age_s) and "before" in e.detail
    e = _refused(pack(_frame(stamp=now + 3)), now=now)
    assert (e.field, e.limit) == ("stamp", LIMITS.max_stamp_lead_s) and "after" in e.detail
    assert load_frame(pack(_frame(stamp=now - 1)), LIMITS, now=now).stamp == now - 1
    assert load_frame(data, Limits(check_stamp_clock=False), now=now)  # replays of recorded data


@pytest.mark.parametrize(
    "change,field",
    [
        ({"schema_version": 7}, "schema_version"),
        ({"vehicle_id": "car\u00e91"}, "vehicle_id"),
        ({"vehicle_id": "x" * 65}, "vehicle_id"),
        ({"seq": -1}, "seq"),
        ({"seq": 2**63}, "seq"),
        ({"boxes": [[1, 2, 0, 4, 2, 1.5, float("nan")]]}, "boxes.0.6"),  # any finite yaw is taken, not nan
        ({"bev": {"resolution_m": 0.4, "range_m": 20, "max_height_m": float("inf")}}, "bev.max_height_m"),
    ],
)
def test_field_limits_name_the_field(change, field):
    e = _refused(msgpack.packb({**_frame().model_dump(mode="python"), **change}))
    assert (e.status, e.field) == (422, field)


# ---- signatures ------------------------------------------------------------------------------------------------
def test_signed_frame_verifies_against_an_independent_hmac():
    payload = pack(_frame())
    env = msgpack.unpackb(sign(payload, FLEET_KEY))
    expected = hmac.new(FLEET_KEY.encode(), b"bb-align/frame/v1\x00fleet\x00" + payload, hashlib.sha256).digest()
    assert DOMAIN == b"bb-align/frame/v1\x00" and env["mac"] == expected and env["payload"] == payload
    assert load_frame(sign(payload, FLEET_KEY), LIMITS, keyring=KEYRING) == _frame()
    js = sign(to_json(_frame()), FLEET_KEY)  # JSON envelope around a JSON frame
    assert js[:1] == b"{" and load_frame(js, LIMITS, JSON, keyring=KEYRING) == _frame()


def test_unsigned_wrongly_signed_and_tampered_frames_are_401():
    payload = pack(_frame())
    e = _refused(payload, keyring=KEYRING)
    assert (e.status, e.error) == (401, "unauthenticated") and "signed" in e.detail
    e = _refused(sign(payload, "another-key-0123456789abcdef"), keyring=KEYRING)
    assert (e.status, e.field, e.limit) == (401, "mac", "hmac-sha256")
    env = msgpack.unpackb(sign(payload, FLEET_KEY))
    env["payload"] = env["payload"][:-1] + bytes([env["payload"][-1] ^ 1])
    assert _refused(msgpack.packb(env), keyring=KEYRING).status == 401
    e = _refused(sign(payload, FLEET_KEY, key_id="car9"), keyring=KEYRING)
    assert e.status == 401 and "unknown key id" in e.detail


def test_a_peer_key_only_signs_for_its_own_vehicle():
    own = "car3-own-key-0123456789"
    assert load_frame(sign(pack(_frame(vehicle_id="car3")), own, "car3"), LIMITS, keyring=KEYRING).vehicle_id == "car3"
    e = _refused(sign(pack(_frame(vehicle_id="ego")), own, "car3"), keyring=KEYRING)
    assert (e.status, e.error, e.field, e.limit) == (403, "forbidden", "vehicle_id", "car3")
    # and the shared fleet key cannot sign as a car that has a key of its own (finding 5)
    e = _refused(sign(pack(_frame(vehicle_id="car3")), FLEET_KEY), keyring=KEYRING)
    assert (e.status, e.error, e.field, e.limit) == (403, "forbidden", "vehicle_id", "fleet")


def test_align_request_frames_are_each_verified():
    good, bad = sign(pack(_frame()), FLEET_KEY), pack(_frame(vehicle_id="ego"))
    req = load_align_request(pack_align_request(good, good), LIMITS, keyring=KEYRING)
    assert req.peer == _frame() == req.ego
    with pytest.raises(WireError) as e:
        load_align_request(pack_align_request(good, bad), LIMITS, keyring=KEYRING)
    assert (e.value.status, e.value.field) == (401, "ego")


def test_demo_keyring_accepts_unsigned_and_unverifiable_frames():
    demo = AuthSettings(mode="off").keyring()
    assert load_frame(pack(_frame()), LIMITS, keyring=demo) == _frame()
    assert load_frame(sign(pack(_frame()), FLEET_KEY), LIMITS, keyring=demo) == _frame()


# ---- fuzzing: nothing but WireError escapes, and what passes decodes ---------------------------------------------
_PNG = _png(_image())


@hsettings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(st.tuples(st.integers(0, len(_PNG) - 1), st.integers(0, 255)), max_size=6),
    st.integers(0, len(_PNG)),
    st.binary(max_size=64),
)
def test_mutated_pngs_are_refused_or_decode_to_the_declared_size(flips, cut, junk):
    png = bytearray(_PNG)
    for i, v in flips:
        png[i] = v
    png = bytes(png[:cut]) + junk
    try:
        check_png(png, N, LIMITS)
    except WireError as e:
        assert e.status == 422 and e.field == "png"
        return
    assert _frame(png=png).bev_image().image.shape == (N, N)  # what passes, OpenCV decodes as promised


_FIELD_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**64), 2**64),
    st.floats(),
    st.text(max_size=8),
    st.binary(max_size=64),
    st.lists(st.floats(), max_size=9),
    st.lists(st.lists(st.floats(), max_size=8), max_size=4),
    st.dictionaries(st.text(max_size=12), st.floats(), max_size=4),
)


@hsettings(max_examples=200, deadline=None)
@given(
    st.dictionaries(st.sampled_from(list(Frame.model_fields)), _FIELD_VALUES, max_size=10),
    st.sampled_from([MSGPACK, JSON]),
    st.booleans(),
)
def test_fuzzed_frames_and_envelopes_only_raise_wire_errors(fields, encoding, signed):
    base = _frame().model_dump(mode="json" if encoding == JSON else "python")
    d = {**base, **fields}
    try:
        data = (
            json.dumps(d, default=lambda b: b.hex()).encode()
            if encoding == JSON
            else msgpack.packb(d, use_bin_type=True)
        )
    except (ValueError, OverflowError, TypeError):
        return  # not encodable at all
    if signed:
        data = sign(data, FLEET_KEY, encoding=encoding)
    try:
        frame = load_frame(data, LIMITS, encoding, keyring=KEYRING)
    except WireError as e:
        assert e.status in (400, 401, 403, 413, 422) and e.detail
        return
    assert signed and frame.bev_image().image.shape == (N, N)


@hsettings(max_examples=200, deadline=None)
@given(st.binary(max_size=400), st.sampled_from([MSGPACK, JSON]))
def test_fuzzed_envelope_payloads_only_raise_wire_errors(payload, encoding):
    data = msgpack.packb(
        {
            "key_id": "fleet",
            "mac": hmac.new(FLEET_KEY.encode(), DOMAIN + b"fleet\x00" + payload, hashlib.sha256).digest(),
            "payload": payload,
        }
    )
    with pytest.raises(WireError):
        load_frame(data, LIMITS, keyring=KEYRING)
    with pytest.raises(WireError):
        load_align_request(pack_align_request(data), LIMITS, keyring=KEYRING)


# ---- the service: signatures, replays, bearer token, a 100 MB body ----------------------------------------------
@pytest.fixture(scope="module")
def pair():
    return moving_pair(1)


def _enc(car, name, seq, stamp=None, **kw):
    """A frame stamped now (the secure profile checks stamps against the clock) or at ``stamp``."""
    return encode_frame(
        car.points,
        car.boxes,
        vehicle_id=name,
        stamp=time.time() if stamp is None else stamp,
        seq=seq,
        range_m=RANGE_M,
        **kw,
    )


def _metric(url: str, name: str, headers=None) -> float:
    for line in httpx.get(f"{url}/metrics", headers=headers).text.splitlines():
        if line.startswith(name + " ") or line.startswith(name + "{") and line.rsplit(" ", 1)[0] == name:
            return float(line.rsplit(" ", 1)[1])
    return 0.0


def test_rest_requires_signed_fresh_frames_and_the_bearer_token(pair):
    _, ego, peer = pair[0]
    settings = secure_settings(
        zenoh=False,
        auth={"fleet_key": FLEET_KEY, "rest_token": "r" * 32, "peer_keys": {"car3": "car3-own-key-0123456789"}},
    )
    with running_service(settings) as (_, url):
        assert httpx.get(f"{url}/healthz").status_code == 200  # probes stay open
        r = httpx.get(f"{url}/v1/peers")
        assert r.status_code == 401 and r.json()["field"] == "authorization"
        assert httpx.get(f"{url}/metrics").status_code == 401
        for route in ("/docs", "/redoc", "/openapi.json"):  # finding 7: the schema and docs are behind the token too
            assert httpx.get(f"{url}{route}").status_code == 401, route
            assert httpx.get(f"{url}{route}", headers={"authorization": "Bearer " + "r" * 32}).status_code == 200
        auth = {"authorization": "Bearer " + "r" * 32}
        with AlignClient(url, token="r" * 32, verify_answers=False) as client:  # no key: frames go unsigned
            with pytest.raises(ServiceError) as e:
                client.post_frame(_enc(peer, "car1", 0))
            assert (e.value.status, e.value.body.error) == (401, "unauthenticated")
        with AlignClient(url, token="r" * 32, key=FLEET_KEY) as client:
            p0, e0 = _enc(peer, "car1", 0), _enc(ego, "ego", 0)
            res = client.align(p0, e0)
            assert res.success and res.peer_id == "car1"
            with pytest.raises(ServiceError) as e:  # the same signed peer frame again
                client.align(p0, e0)
            assert (e.value.status, e.value.body.error, e.value.body.field) == (409, "replayed", "stamp")
            with pytest.raises(ServiceError) as e:
                client.post_frame(_enc(peer, "car1", 1, key="car3-own-key-0123456789", key_id="car2"))
            assert e.value.status == 401
            assert client.post_frame(_enc(peer, "car3", 2, key="car3-own-key-0123456789", key_id="car3"))["accepted"]
            with pytest.raises(ServiceError) as e:  # car3's key cannot speak for the ego car
                client.post_frame(_enc(ego, "ego", 3, key="car3-own-key-0123456789", key_id="car3"))
            assert (e.value.status, e.value.body.error) == (403, "forbidden")
            with pytest.raises(ServiceError) as e:  # nor can the fleet key speak for car3, which has its own key
                client.post_frame(_enc(peer, "car3", 5))
            assert (e.value.status, e.value.body.error) == (403, "forbidden")
            with pytest.raises(ServiceError) as e:
                client.post_frame(_enc(peer, "car1", 4, stamp=time.time() - 3600))
            assert (e.value.status, e.value.body.field) == (422, "stamp")
        text = httpx.get(f"{url}/metrics", headers=auth).text
        for error, n in (("unauthenticated", 2), ("replayed", 1), ("forbidden", 2), ("invalid", 1)):
            assert f'bbalign_frames_rejected_total{{door="rest",error="{error}"}} {float(n)}' in text, error


def test_a_100_mb_body_is_refused_by_size_without_being_read():
    with running_service(service_settings(zenoh=False)) as (_, url):
        sent = 0

        def body():  # streamed, no content-length
            nonlocal sent
            for _ in range(100):
                sent += 2**20
                yield bytes(2**20)

        r = httpx.post(f"{url}/v1/frames", content=body(), headers={"content-type": MSGPACK}, timeout=30)
        assert r.status_code == 413 and r.json()["limit"] == LIMITS.max_message_bytes
        assert sent < 40 * 2**20, f"the client got to send {sent} bytes"
        with socket.create_connection(("127.0.0.1", int(url.rsplit(":", 1)[1])), timeout=10) as s:
            s.sendall(
                b"POST /v1/align HTTP/1.1\r\nhost: 127.0.0.1\r\ncontent-type: application/msgpack\r\n"
                b"content-length: 104857600\r\n\r\n"
            )  # declared, never sent
            head = b""
            while chunk := s.recv(4096):  # the service answers and closes
                head += chunk
        assert head.startswith(b"HTTP/1.1 413") and b'"too_large"' in head
        assert httpx.get(f"{url}/readyz").status_code == 200  # still serving


def test_zenoh_door_drops_and_counts_unsigned_frames_and_answers_bad_queries(pair):
    _, ego, peer = pair[0]
    settings = secure_settings(limits={"max_peers": 2})
    with running_service(settings) as (app, url):
        service = app.state.service
        with (
            ZenohPeer("car1", connect=settings.zenoh.listen, block_when_congested=True, verify_answers=False) as plain,
            ZenohPeer("car1", connect=settings.zenoh.listen, key=FLEET_KEY, block_when_congested=True) as car,
            ZenohPeer("ego", connect=settings.zenoh.listen, key=FLEET_KEY, block_when_congested=True) as ego_car,
        ):
            poses = car.poses("ego")
            assert car.wait_for_subscriber(10) and plain.wait_for_subscriber(10)
            time.sleep(0.2)
            raw = plain.session
            for i in range(20):  # junk ids, unsigned: never tracked, never queued
                raw.put(f"bbalign/frames/junk{i}", _enc(peer, f"junk{i}", i))
            plain.publish(_enc(peer, "car1", 0))
            wait_for(
                lambda: _metric(url, 'bbalign_frames_rejected_total{door="zenoh",error="unauthenticated"}') == 21,
                what="21 refusals",
            )
            assert len(service.peer_table) == 0 and service.scheduler.senders() == 0
            t0 = time.time()  # the ego and peer frames below are stamped within max_ego_skew_s of each other
            ego_car.publish(_enc(ego, "ego", 1, t0))
            wait_for(lambda: len(service.cache) == 1, what="the ego frame")
            frame = _enc(peer, "car1", 1, t0, key=FLEET_KEY)
            car.publish(frame)
            res = poses.get(timeout=30)
            assert res.peer_seq == 1 and res.success
            raw.put("bbalign/frames/car1", frame)  # replayed byte for byte
            wait_for(
                lambda: _metric(url, 'bbalign_frames_rejected_total{door="zenoh",error="replayed"}') == 1,
                what="the replay refusal",
            )
            with pytest.raises(ServiceError) as e:
                plain.request_align(_enc(peer, "car1", 2), ego_id="ego", timeout=20)
            assert e.value.status is None and e.value.body.error == "unauthenticated"
            with pytest.raises(ServiceError) as e:
                plain.request_align(sign_frame(_enc(peer, "car1", 3), "wrong-key-0123456789abcdef"), "ego", 20)
            assert e.value.body.error == "unauthenticated" and e.value.body.field == "mac"
            res = car.request_align(_enc(peer, "car1", 4, t0 + 0.01), ego_id="ego", timeout=30)
            assert res.peer_seq == 4 and res.success
        peers = httpx.get(f"{url}/v1/peers").json()
        assert list(peers) == ["car1"] and peers["car1"]["frames_accepted"] == 1 and peers["car1"]["results"] == 2


def test_peer_table_is_bounded_and_forgets_idle_peers(pair):
    _, _, peer = pair[0]
    settings = secure_settings(zenoh=False, limits={"max_peers": 1, "peer_idle_s": 1.0, "max_stamp_age_s": 1.0})
    with running_service(settings) as (app, url):
        with AlignClient(url, key=FLEET_KEY) as client:
            client.post_frame(_enc(peer, "car1", 0))
            with pytest.raises(ServiceError) as e:
                client.post_frame(_enc(peer, "car2", 0))
            assert (e.value.status, e.value.body.error, e.value.body.limit) == (503, "overloaded", 1)
            wait_for(
                lambda: (
                    app.state.service.peers().get("car1", None) is None
                    or app.state.service.peers()["car1"].results == 1
                ),
                what="car1's result",
            )
            time.sleep(1.2)  # car1 goes idle
            assert client.post_frame(_enc(peer, "car2", 1))["accepted"]
            assert list(client.peers()) == ["car2"]
            wait_for(lambda: app.state.service.scheduler.pending() == 0, what="car2's frame")
        text = httpx.get(f"{url}/metrics").text
        assert 'peer="car1"' not in text.split("bbalign_frames_rejected")[0]  # its labels left with it
        assert "bbalign_peers_tracked 1.0" in text


# ---- schemathesis against the OpenAPI schema ------------------------------------------------------------------
schemathesis.openapi.media_type(MSGPACK, st.binary(max_size=4000))  # raw msgpack bodies: any bytes


def test_openapi_fuzzing_finds_no_5xx_and_no_undocumented_response():
    """Every documented operation, ~30 schema-driven examples each (valid-shaped and invalid bodies), against a real
    server: no 5xx, every status code and response body as documented."""
    from schemathesis import GenerationMode
    from schemathesis.checks import not_a_server_error
    from schemathesis.specs.openapi.checks import response_schema_conformance, status_code_conformance

    settings = service_settings(zenoh=False, limits={"max_message_bytes": 200_000})
    seen: dict[str, set[int]] = {}
    with running_service(settings) as (_, url):
        schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
        for result in schema.get_all_operations():
            op = result.ok()
            cases = op.as_strategy(generation_mode=GenerationMode.POSITIVE)
            if op.body:
                cases = cases | op.as_strategy(generation_mode=GenerationMode.NEGATIVE)

            @given(cases)
            @hsettings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck), database=None)
            def fuzz(case):  # run right below, within this iteration: `op` is this operation
                response = case.call(timeout=60)
                seen.setdefault(f"{op.method.upper()} {op.path}", set()).add(response.status_code)  # noqa: B023
                case.validate_response(
                    response, checks=[not_a_server_error, status_code_conformance, response_schema_conformance]
                )

            fuzz()
        assert httpx.get(f"{url}/readyz").status_code == 200  # still serving
    assert {"POST /v1/align", "POST /v1/frames", "GET /v1/peers", "GET /metrics"} <= set(seen)
    assert seen["POST /v1/frames"] & {400, 422} and not any(c >= 500 for cs in seen.values() for c in cs), seen


# ---- Zenoh over mutual TLS --------------------------------------------------------------------------------------
def _openssl(*args: str, cwd) -> None:
    import subprocess

    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


@pytest.fixture(scope="module")
def certificates(tmp_path_factory):
    """A throw-away CA, a service certificate for localhost and a car's client certificate (openssl CLI)."""
    import shutil

    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed (needed to make test certificates)")
    d = tmp_path_factory.mktemp("pki")
    _openssl(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-days",
        "2",
        "-subj",
        "/CN=bb-align test CA",
        cwd=d,
    )
    (d / "san.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for name in ("service", "car1"):
        _openssl(
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            f"{name}.key",
            "-out",
            f"{name}.csr",
            "-subj",
            f"/CN={name}",
            cwd=d,
        )
        _openssl(
            "x509",
            "-req",
            "-in",
            f"{name}.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-out",
            f"{name}.pem",
            "-days",
            "2",
            "-extfile",
            "san.cnf",
            cwd=d,
        )
    return d


def test_zenoh_mutual_tls_admits_a_car_with_a_certificate_and_no_other(pair, certificates):
    d = certificates
    ep = f"tls/localhost:{free_port()}"
    tls = {"root_ca_certificate": str(d / "ca.pem"), "mtls": True}
    settings = secure_settings(
        zenoh_config={
            "listen": [ep],
            "tls": {**tls, "certificate": str(d / "service.pem"), "private_key": str(d / "service.key")},
        }
    )
    assert not settings.security_warnings()  # signed frames, loopback, TLS: nothing to shout about
    _, ego, peer = pair[0]
    with running_service(settings) as (app, url):
        car_tls = {**tls, "certificate": str(d / "car1.pem"), "private_key": str(d / "car1.key")}
        with (
            ZenohPeer("car1", connect=[ep], key=FLEET_KEY, tls=car_tls, block_when_congested=True) as car,
            ZenohPeer(
                "intruder",
                connect=[ep],
                key=FLEET_KEY,
                tls={"root_ca_certificate": str(d / "ca.pem")},
                block_when_congested=True,
            ) as intruder,
        ):
            assert car.wait_for_subscriber(10)
            assert not intruder.wait_for_subscriber(2.0)  # no client certificate: the link is refused
            t0 = time.time()
            with AlignClient(url, key=FLEET_KEY) as client:
                client.post_frame(_enc(ego, "ego", 0, t0))
            wait_for(lambda: len(app.state.service.cache) == 1, what="the ego frame")
            res = car.request_align(_enc(peer, "car1", 0, t0), "ego", timeout=30)
            assert res.success and res.peer_id == "car1"
            intruder.publish(_enc(peer, "intruder", 0, t0))
        assert "intruder" not in httpx.get(f"{url}/v1/peers").json()
