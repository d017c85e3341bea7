"""REST door against a real uvicorn server on 127.0.0.1 (Zenoh off here; see test_zenoh.py)."""

from __future__ import annotations

import concurrent.futures
import json
import time

import httpx
import msgpack
import numpy as np
import pytest

from bb_align.engine.geometry import pose_error
from bb_align.protocol import MSGPACK, json_align_request, load_result, pack_align_request
from bb_align_client import AlignClient, ServiceError, encode_frame
from service_support import (
    FLEET_KEY,
    RANGE_M,
    moving_pair,
    running_service,
    secure_settings,
    service_settings,
    true_T_ego_peer,
)

JSON_CT = {"content-type": "application/json"}
MSGPACK_CT = {"content-type": MSGPACK}


@pytest.fixture(scope="module")
def pair():
    return moving_pair(3)


def _enc(car, name, stamp, seq, encoding=MSGPACK):
    return encode_frame(
        car.points, car.boxes, vehicle_id=name, stamp=stamp, seq=seq, range_m=RANGE_M, encoding=encoding
    )


@pytest.fixture
def server():
    with running_service(service_settings(zenoh=False, max_ego_skew_s=0.15)) as (app, url):
        with httpx.Client(base_url=url, timeout=30) as http:
            yield app, http


def _wait_ego_frames(http, n, timeout=20.0):
    deadline = time.monotonic() + timeout
    while http.get("/readyz").json()["ego_frames"] < n:
        assert time.monotonic() < deadline, "ego frames were not prepared in time"
        time.sleep(0.05)


def test_health_ready_and_no_ego_frame_yet(server, pair):
    _, http = server
    assert http.get("/healthz").json() == {"status": "ok"}
    ready = http.get("/readyz")
    assert ready.status_code == 200 and ready.json()["zenoh"] is None and ready.json()["ego_frames"] == 0
    stamp, _, peer = pair[0]
    r = http.post("/v1/align", content=pack_align_request(_enc(peer, "car1", stamp, 0)), headers=MSGPACK_CT)
    body = r.json()
    assert r.status_code == 200 and not body["success"] and body["reason"] == "no_ego_frame"
    assert body["T_ego_peer"] is None


@pytest.mark.parametrize("encoding", [MSGPACK, "application/json"])
def test_align_with_both_frames_recovers_the_true_pose(server, pair, encoding):
    _, http = server
    stamp, ego, peer = pair[1]
    p, e = _enc(peer, "car1", stamp, 1, encoding), _enc(ego, "ego", stamp, 1, encoding)
    body = pack_align_request(p, e) if encoding == MSGPACK else json_align_request(p, e)
    r = http.post("/v1/align", content=body, headers={"content-type": encoding})
    assert r.status_code == 200, r.text
    res = load_result(r.content)
    t_err, r_err = pose_error(res.matrix(), true_T_ego_peer(ego, peer))
    assert res.success and t_err < 0.3 and r_err < 0.3
    assert (res.peer_id, res.peer_seq, res.ego_seq, res.ego_stamp) == ("car1", 1, 1, stamp)
    assert res.bytes_received == len(p) and res.raw_points_bytes == 16 * len(peer.points)


def test_cached_ego_frame_nearest_in_time_is_used(server, pair):
    _, http = server
    for seq, (stamp, ego, _) in enumerate(pair):
        r = http.post("/v1/frames", content=_enc(ego, "ego", stamp, seq), headers=MSGPACK_CT)
        assert r.status_code == 202 and r.json() == {"accepted": True, "kind": "ego", "vehicle_id": "ego", "seq": seq}
        _wait_ego_frames(http, seq + 1)  # one at a time: ego frames are latest-only too
    stamp, _, peer = pair[1]
    r = http.post("/v1/align", content=pack_align_request(_enc(peer, "car1", stamp + 0.02, 1)), headers=MSGPACK_CT)
    res = load_result(r.content)
    assert res.ego_seq == 1 and res.ego_skew_s == pytest.approx(0.02)
    t_err, r_err = pose_error(res.matrix(), true_T_ego_peer(pair[1][1], peer))
    assert res.success and t_err < 0.3 and r_err < 0.3
    # Far from every cached frame: a clear refusal naming the nearest one.
    r = http.post("/v1/align", content=pack_align_request(_enc(peer, "car1", 0.9, 9)), headers=MSGPACK_CT)
    body = r.json()
    assert body["reason"] == "stale_ego_frame" and body["ego_seq"] == 2 and body["ego_skew_s"] == pytest.approx(0.7)


def test_accept_msgpack_returns_msgpack(server, pair):
    _, http = server
    stamp, ego, peer = pair[0]
    r = http.post(
        "/v1/align",
        content=pack_align_request(_enc(peer, "car1", stamp, 0), _enc(ego, "ego", stamp, 0)),
        headers={**MSGPACK_CT, "accept": MSGPACK},
    )
    assert r.headers["content-type"] == MSGPACK and msgpack.unpackb(r.content)["peer_id"] == "car1"


def test_errors_are_typed_and_name_the_field(pair):
    with running_service(service_settings(zenoh=False, limits={"max_message_bytes": 50_000})) as (_, url):
        with httpx.Client(base_url=url, timeout=30) as http:
            stamp, _, peer = pair[0]
            good = _enc(peer, "car1", stamp, 0)
            r = http.post("/v1/frames", content=good, headers={"content-type": "text/plain"})
            assert r.status_code == 415 and r.json()["error"] == "unsupported_media_type"
            r = http.post("/v1/align", content=b"\xc1\xc1", headers=MSGPACK_CT)
            assert r.status_code == 400 and r.json()["error"] == "undecodable"
            r = http.post("/v1/frames", content=good + b"\x00" * 60_000, headers=MSGPACK_CT)
            assert r.status_code == 413 and r.json()["limit"] == 50_000
            bad = msgpack.unpackb(good)
            bad["boxes"][0][3] = -1.0
            r = http.post("/v1/frames", content=msgpack.packb(bad), headers=MSGPACK_CT)
            assert r.status_code == 422 and r.json()["field"] == "boxes.0" and r.json()["limit"] == 40.0
            d = json.loads(_enc(peer, "car1", stamp, 0, "application/json"))
            d["png"] = "%%%"
            r = http.post("/v1/align", content=json.dumps({"peer": d}), headers=JSON_CT)
            assert r.status_code == 422 and r.json()["field"] == "peer.png"


def test_peers_bandwidth_and_metrics_report_what_was_sent(server, pair):
    _, http = server
    stamp, ego, peer = pair[0]
    http.post("/v1/frames", content=_enc(ego, "ego", stamp, 0), headers=MSGPACK_CT)
    _wait_ego_frames(http, 1)
    sizes = []
    for seq in range(2):
        data = _enc(peer, "car1", stamp, seq)
        sizes.append(len(data))
        assert http.post("/v1/align", content=pack_align_request(data), headers=MSGPACK_CT).json()["success"]
    peers = http.get("/v1/peers").json()
    assert list(peers) == ["car1"] and peers["car1"]["last_result"]["peer_seq"] == 1
    bw = peers["car1"]["bandwidth"]
    assert bw["messages"] == 2 and bw["bytes"] == sum(sizes) and bw["frames_decoded"] == 2
    assert bw["ratio_vs_points"] == pytest.approx(sum(sizes) / (2 * 16 * len(peer.points)))
    total = http.get("/v1/bandwidth").json()["total"]
    assert total["messages"] == 3 and total["bytes"] > sum(sizes)
    text = http.get("/metrics").text
    assert 'bbalign_alignments_total{outcome="success",peer="car1"} 2.0' in text
    assert f'bbalign_bytes_received_total{{peer="car1"}} {float(sum(sizes))}' in text
    assert 'bbalign_frames_received_total{door="rest",kind="ego"} 1.0' in text
    assert "bbalign_result_latency_seconds_bucket" in text


def test_openapi_documents_binary_bodies_and_errors(server):
    _, http = server
    spec = http.get("/openapi.json").json()
    post = spec["paths"]["/v1/align"]["post"]
    assert set(post["requestBody"]["content"]) == {MSGPACK, "application/json"}
    assert {"400", "413", "415", "422", "503", "504"} <= set(post["responses"])
    assert MSGPACK in post["responses"]["200"]["content"]
    assert {"Frame", "AlignRequest", "Result", "ErrorBody", "BevMeta", "Pose"} <= set(spec["components"]["schemas"])
    assert "requestBody" in spec["paths"]["/v1/frames"]["post"]


def test_full_request_queue_answers_503(pair):
    settings = service_settings(zenoh=False, workers=1, max_pending_requests=1)
    with running_service(settings) as (_, url):
        stamp, ego, peer = pair[0]
        body = pack_align_request(_enc(peer, "car1", stamp, 0), _enc(ego, "ego", stamp, 0))

        def call(_):
            return httpx.post(f"{url}/v1/align", content=body, headers=MSGPACK_CT, timeout=60)

        with concurrent.futures.ThreadPoolExecutor(8) as pool:
            responses = list(pool.map(call, range(8)))
        codes = sorted(r.status_code for r in responses)
        assert set(codes) <= {200, 503} and 200 in codes and 503 in codes
        assert all(r.json()["error"] == "overloaded" for r in responses if r.status_code == 503)
        # finding 7: each refusal counted once (the service and the REST door both counted it)
        line = 'bbalign_frames_rejected_total{door="rest",error="overloaded"} '
        counted = [ln for ln in httpx.get(f"{url}/metrics").text.splitlines() if ln.startswith(line)]
        assert counted == [f"{line}{float(codes.count(503))}"]


def test_reported_poses_check_the_acquisition_and_a_false_report_fails(server, pair):
    from bb_align.engine.geometry import se2, se3_from_se2

    _, http = server
    stamp, ego, peer = pair[1]
    noisy = peer.T_world_sensor @ se3_from_se2(se2(np.radians(2.0), 1.5, -1.0))  # GNSS-grade error
    p = encode_frame(peer.points, peer.boxes, vehicle_id="car8", stamp=stamp, seq=5, range_m=RANGE_M, pose=noisy)
    e = encode_frame(
        ego.points, ego.boxes, vehicle_id="ego", stamp=stamp, seq=5, range_m=RANGE_M, pose=ego.T_world_sensor
    )
    res = load_result(http.post("/v1/align", content=pack_align_request(p, e), headers=MSGPACK_CT).content)
    assert res.source == "acquisition" and res.success and "the pose lies inside the prior's window" in res.notes
    assert pose_error(res.matrix(), true_T_ego_peer(ego, peer))[0] < 0.3
    liar = peer.T_world_sensor @ se3_from_se2(se2(np.radians(90.0), 35.0, 0.0))
    T_lie = np.linalg.inv(ego.T_world_sensor) @ liar
    # A car with no track yet: its acquisition lands far from the lie and is refused.
    p = encode_frame(peer.points, peer.boxes, vehicle_id="car7", stamp=stamp, seq=6, range_m=RANGE_M, pose=liar)
    res = load_result(http.post("/v1/align", content=pack_align_request(p, e), headers=MSGPACK_CT).content)
    assert res.source == "acquisition" and res.reason == "disagrees_with_prior"
    assert not res.success, "a false reported pose must not produce a confident pose"
    # A tracked car: the lie does not move the track (its pose comes from the images and its motion).
    p = encode_frame(peer.points, peer.boxes, vehicle_id="car8", stamp=stamp, seq=6, range_m=RANGE_M, pose=liar)
    res = load_result(http.post("/v1/align", content=pack_align_request(p, e), headers=MSGPACK_CT).content)
    assert res.source == "tracking" and res.success
    assert pose_error(res.matrix(), true_T_ego_peer(ego, peer))[0] < 0.3
    assert pose_error(res.matrix(), T_lie)[0] > 30.0


def test_peer_frame_arriving_before_its_ego_frame_still_gets_it(server, pair):
    """The ego frame of a sweep travels in another Zenoh session and may arrive after the peer's: a peer frame
    newer than every cached ego frame is prepared first and matched after. The ego frame is made to arrive
    exactly while the peer frame is being prepared (deterministic stand-in for the race)."""
    from bb_align.protocol import load_frame

    app, http = server
    service = app.state.service
    stamp0, ego0, _ = pair[0]
    stamp1, ego1, peer1 = pair[2]  # 0.2 s after the cached ego frame: beyond the 0.15 s skew
    assert stamp1 - stamp0 > service.settings.max_ego_skew_s
    http.post("/v1/frames", content=_enc(ego0, "ego", stamp0, 0), headers=MSGPACK_CT)
    _wait_ego_frames(http, 1)
    late_ego = _enc(ego1, "ego", stamp1, 1)
    original = service._prepare

    def prepare_while_the_ego_frame_lands(frame, step, bev=None):
        if step == "prepare_peer":
            service.submit_frame(load_frame(late_ego, service.settings.limits), len(late_ego))
        return original(frame, step, bev)

    service._prepare = prepare_while_the_ego_frame_lands
    try:
        r = http.post("/v1/align", content=pack_align_request(_enc(peer1, "car1", stamp1, 1)), headers=MSGPACK_CT)
    finally:
        service._prepare = original
    res = load_result(r.content)
    assert res.success and res.ego_seq == 1, (res.reason, res.ego_seq)  # seq 1: the late ego frame
    t_err, r_err = pose_error(res.matrix(), true_T_ego_peer(ego1, peer1))
    assert t_err < 0.3 and r_err < 0.3


# ---- issue 14: box yaw, inline ego bandwidth, the replay profile -----------------------------------------------
def _with_yaw(car, yaw: float) -> np.ndarray:
    boxes = car.boxes.copy()
    boxes[0, 6] = yaw
    return boxes


def test_a_yaw_of_7_rad_gives_the_engine_the_same_input_as_7_minus_2_pi(server, pair):
    """Any finite yaw is taken and wrapped: the engine's input (the boxes handed to Aligner.prepare) and the
    answer are those of the wrapped twin, bit for bit (7.0 - 2 pi is the independent truth)."""
    app, http = server
    service = app.state.service
    stamp, ego, peer = pair[1]
    seen, original = [], service.aligner.prepare

    def recording_prepare(bev, boxes=None, *args, **kw):
        seen.append(None if boxes is None else np.array(boxes, copy=True))
        return original(bev, boxes, *args, **kw)

    service.aligner.prepare = recording_prepare
    answers = []
    try:
        for seq, yaw in enumerate((7.0, 7.0 - 2 * np.pi)):
            p = encode_frame(
                peer.points, _with_yaw(peer, yaw), vehicle_id=f"yaw{seq}", stamp=stamp, seq=seq, range_m=RANGE_M
            )  # two cars, each acquired afresh (one car's second frame would be tracked from its first)
            body = pack_align_request(p, _enc(ego, "ego", stamp, seq))
            r = http.post("/v1/align", content=body, headers=MSGPACK_CT)
            assert r.status_code == 200, r.text
            answers.append(load_result(r.content))
    finally:
        service.aligner.prepare = original
    peer_inputs = [
        b for b in seen if b is not None and len(b) == len(peer.boxes) and np.allclose(b[1:], peer.boxes[1:])
    ]
    assert len(peer_inputs) == 2
    assert peer_inputs[0][0, 6] == 7.0 - 2 * np.pi and np.array_equal(peer_inputs[0], peer_inputs[1])
    assert answers[0].success == answers[1].success
    np.testing.assert_allclose(answers[0].matrix(), answers[1].matrix(), atol=1e-9)


def test_a_nan_yaw_over_rest_is_422_naming_the_field(server, pair):
    _, http = server
    stamp, _, peer = pair[0]
    d = msgpack.unpackb(_enc(peer, "car1", stamp, 0))
    d["boxes"][0][6] = float("nan")
    r = http.post("/v1/align", content=pack_align_request(msgpack.packb(d)), headers=MSGPACK_CT)
    assert r.status_code == 422 and r.json()["field"] == "peer.boxes.0.6" and "yaw is nan" in r.json()["detail"]


def test_an_inline_ego_frame_counts_in_bandwidth(server, pair):
    """The bytes counted grow by the inline ego frame's size (under the ego id), besides the peer frame's."""
    _, http = server
    stamp, ego, peer = pair[0]
    p, e = _enc(peer, "car1", stamp, 0), _enc(ego, "ego", stamp, 0)
    before = http.get("/v1/bandwidth").json()
    assert http.post("/v1/align", content=pack_align_request(p, e), headers=MSGPACK_CT).status_code == 200
    after = http.get("/v1/bandwidth").json()
    assert after["total"]["bytes"] - before["total"]["bytes"] == len(p) + len(e)
    assert after["total"]["messages"] - before["total"]["messages"] == 2
    ego_bw = after["peers"]["ego"]
    assert (ego_bw["bytes"], ego_bw["messages"], ego_bw["frames_decoded"]) == (len(e), 1, 1)
    assert ego_bw["raw_points_bytes"] == 16 * len(ego.points)


def _signed(car, name, stamp, seq):
    return encode_frame(car.points, car.boxes, vehicle_id=name, stamp=stamp, seq=seq, range_m=RANGE_M, key=FLEET_KEY)


def test_the_replay_profile_accepts_a_recording_played_twice(pair):
    """Frames stamped from 0 s (a recording, decades before the receiver's clock), signed, sent twice in a row
    through /v1/align with the ego inline: both passes accepted and aligned to the true pose."""
    settings = secure_settings(zenoh=False, limits={"replay": True})
    assert not settings.limits.clock_checked
    with running_service(settings) as (_, url):
        with AlignClient(url, key=FLEET_KEY) as client:
            for _ in range(2):
                for seq, (stamp, ego, peer) in enumerate(pair[:2]):
                    res = client.align(_signed(peer, "car1", stamp, seq), _signed(ego, "ego", stamp, seq))
                    assert (res.peer_seq, res.ego_seq) == (seq, seq)
                    assert res.success and pose_error(res.matrix(), true_T_ego_peer(ego, peer))[0] < 0.3
            assert client.peers()["car1"]["sequence_restarts"] == 1


def test_without_the_replay_profile_old_stamps_and_a_second_pass_are_refused_naming_the_setting(pair):
    stamp, ego, _ = pair[0]
    with running_service(secure_settings(zenoh=False)) as (_, url):
        with AlignClient(url, key=FLEET_KEY) as client:
            with pytest.raises(ServiceError) as e:
                client.post_frame(_signed(ego, "ego", stamp, 0))
    body = e.value.body
    assert (e.value.status, body.field, body.setting) == (422, "stamp", "BBALIGN_LIMITS__MAX_STAMP_AGE_S")
    assert "BBALIGN_LIMITS__REPLAY=true" in body.detail and "bb-align serve --replay" in body.detail
    # stamps not checked against the clock, but replays still refused: the second pass is a replay
    with running_service(secure_settings(zenoh=False, limits={"check_stamp_clock": False})) as (_, url):
        with AlignClient(url, key=FLEET_KEY) as client:
            for seq, (stamp, ego, _) in enumerate(pair[:2]):
                assert client.post_frame(_signed(ego, "ego", stamp, seq))["accepted"]
            with pytest.raises(ServiceError) as e:
                client.post_frame(_signed(pair[0][1], "ego", pair[0][0], 0))
    body = e.value.body
    assert (e.value.status, body.error, body.setting) == (409, "replayed", "BBALIGN_LIMITS__REPLAY")
    assert "bb-align serve --replay" in body.detail


def test_a_tracks_cross_check_runs_beside_it_and_the_frames_meanwhile_are_tracked(pair):
    """With odometry, the periodic cross-check is a job of its own: the frame that makes it due is answered by the
    refinement (not by a 0.3 s acquisition), the acquisition then runs and agrees, and the track goes on."""
    from bb_align.engine.config import BevConfig, TrackConfig
    from bb_align.engine.pipeline import AlignConfig

    # max_sigma_m: no acquisition forced by a growing uncertainty, so only the periodic cross-check runs one.
    align = AlignConfig(bev=BevConfig(range_m=RANGE_M), track=TrackConfig(crosscheck_s=0.3, max_sigma_m=100.0))
    with running_service(service_settings(zenoh=False, max_ego_skew_s=0.15, align=align)) as (_, url):
        with httpx.Client(base_url=url, timeout=30) as http:

            def align_at(k, seq, peer_id="car1", odometry=True):  # frame k; odometry: the cars' true poses
                stamp, ego, peer = pair[k]
                frames = [
                    encode_frame(
                        car.points,
                        car.boxes,
                        vehicle_id=name,
                        stamp=seq * 0.2,
                        seq=seq,
                        range_m=RANGE_M,
                        odometry=car.T_world_sensor if odometry else None,
                    )
                    for car, name in ((peer, peer_id), (ego, "ego"))
                ]
                content = pack_align_request(*frames)
                res = load_result(http.post("/v1/align", content=content, headers=MSGPACK_CT).content)
                return res, true_T_ego_peer(ego, peer)

            def crosschecks() -> float:
                for line in http.get("/metrics").text.splitlines():
                    if line.startswith('bbalign_engine_seconds_count{step="crosscheck"}'):
                        return float(line.split()[-1])
                return 0.0

            res, T_true = align_at(0, 0)
            assert res.source == "acquisition" and res.success
            res, T_true = align_at(1, 2)  # 0.4 s on: the cross-check is due, and left to its own job
            assert res.source == "tracking" and res.success and pose_error(res.matrix(), T_true)[0] < 0.3
            deadline = time.monotonic() + 30
            while crosschecks() < 1:
                assert time.monotonic() < deadline, "the cross-check never ran"
                time.sleep(0.05)
            res, T_true = align_at(2, 3)
            assert res.source == "tracking" and res.success and res.track_event is None  # it agreed
            assert pose_error(res.matrix(), T_true)[0] < 0.3
            assert crosschecks() == 1  # one per crosscheck_s, not one per frame
            # Without odometry there is no constant offset to fuse a late acquisition into: it runs in the step.
            assert align_at(0, 4, "car2", odometry=False)[0].source == "acquisition"
            assert align_at(1, 6, "car2", odometry=False)[0].source == "acquisition"
            assert crosschecks() == 1
