"""The client library: frame encoding against the engine's own BV image, REST clients against a real server."""

from __future__ import annotations

import asyncio
import json
import math

import msgpack
import numpy as np
import pytest

from bb_align import BevConfig, make_bev
from bb_align.engine.geometry import pose_error
from bb_align.protocol import JSON, Limits, Pose, Result, load_frame, pack, to_json
from bb_align_client import AlignClient, AsyncAlignClient, ServiceError, ZenohPeer, decode_result, encode_frame
from service_support import RANGE_M, free_port, moving_pair, running_service, service_settings, true_T_ego_peer


@pytest.fixture(scope="module")
def pair():
    return moving_pair(1)


def test_encoded_frame_holds_the_engine_bev_image_boxes_and_pose(pair):
    stamp, ego, _ = pair[0]
    T = ego.T_world_sensor.copy()
    T[:3, 3] = (5.0, -3.0, 1.8)
    data = encode_frame(
        ego.points,
        ego.boxes,
        vehicle_id="car1",
        stamp=1.25,
        seq=4,
        pose=T,
        range_m=RANGE_M,
        resolution_m=0.5,
        scores=np.linspace(0.1, 0.9, len(ego.boxes)),
    )
    f = load_frame(data, Limits())
    expected = make_bev(ego.points, BevConfig(range_m=RANGE_M, resolution_m=0.5))
    np.testing.assert_array_equal(f.bev_image().image, expected.image)
    assert f.bev.model_dump() == expected.meta()
    np.testing.assert_allclose(f.boxes_array(), ego.boxes)
    np.testing.assert_allclose(f.pose.matrix(), T, atol=1e-12)
    assert (f.vehicle_id, f.seq, f.stamp, f.num_points) == ("car1", 4, 1.25, len(ego.points))
    assert f.scores[0] == pytest.approx(0.1) and len(f.scores) == len(ego.boxes)


def test_pose_forms_and_json_encoding(pair):
    _, ego, _ = pair[0]
    six = encode_frame(ego.points, vehicle_id="a", stamp=0, pose=[1, 2, 3, 0.1, 0.2, 0.3], range_m=RANGE_M)
    assert load_frame(six, Limits()).pose == Pose(x=1, y=2, z=3, roll=0.1, pitch=0.2, yaw=0.3)
    js = encode_frame(ego.points, vehicle_id="a", stamp=0, range_m=RANGE_M, encoding=JSON)
    assert js[:1] == b"{" and load_frame(js, Limits(), JSON).boxes == []
    bev = make_bev(ego.points, BevConfig(range_m=RANGE_M))
    from_image = load_frame(encode_frame(bev, vehicle_id="a", stamp=0), Limits())
    assert from_image.num_points is None and from_image.png == bev.to_png()
    with pytest.raises(ValueError, match="pose"):
        encode_frame(ego.points, vehicle_id="a", stamp=0, pose=[1, 2, 3], range_m=RANGE_M)
    with pytest.raises(ValueError, match="encoding"):
        encode_frame(ego.points, vehicle_id="a", stamp=0, encoding="xml", range_m=RANGE_M)


def test_encode_frame_takes_any_finite_yaw_wrapped_and_names_a_non_finite_one(pair):
    """Issue 14: a dataset's yaw in [0, 2 pi) or beyond goes on the air wrapped into [-pi, pi) (read from the raw
    bytes, not through the model that would wrap it again); nan is refused before anything is sent."""
    _, ego, _ = pair[0]
    boxes = ego.boxes[:2].copy()
    boxes[0, 6], boxes[1, 6] = 7.0, -math.pi
    on_air = msgpack.unpackb(encode_frame(ego.points, boxes, vehicle_id="a", stamp=0, range_m=RANGE_M))
    assert [b[6] for b in on_air["boxes"]] == [7.0 - 2 * math.pi, -math.pi]
    as_json = json.loads(encode_frame(ego.points, boxes, vehicle_id="a", stamp=0, range_m=RANGE_M, encoding=JSON))
    assert as_json["boxes"][0][6] == 7.0 - 2 * math.pi
    boxes[1, 6] = np.nan
    with pytest.raises(ValueError, match=r"boxes\[1\] yaw is nan"):
        encode_frame(ego.points, boxes, vehicle_id="a", stamp=0, range_m=RANGE_M)


def test_decode_result_reads_both_encodings():
    r = Result(ego_id="ego", peer_id="car1", peer_seq=0, peer_stamp=0.0, success=False, reason="no_ego_frame")
    assert decode_result(pack(r)) == r == decode_result(to_json(r))


def test_sync_and_async_rest_clients(pair):
    stamp, ego, peer = pair[0]
    p = encode_frame(peer.points, peer.boxes, vehicle_id="car1", stamp=stamp, range_m=RANGE_M)
    e = encode_frame(ego.points, ego.boxes, vehicle_id="ego", stamp=stamp, range_m=RANGE_M)
    with running_service(service_settings(zenoh=False)) as (_, url):
        with AlignClient(url, verify_answers=False) as client:
            res = client.align(p, e)
            assert res.success and pose_error(res.matrix(), true_T_ego_peer(ego, peer))[0] < 0.3
            assert client.post_frame(e)["kind"] == "ego"
            assert client.peers()["car1"]["last_result"]["success"]
            assert client.bandwidth()["total"]["messages"] >= 2
            bad = msgpack.unpackb(p)
            bad["vehicle_id"] = "car 1"
            with pytest.raises(ServiceError) as err:
                client.post_frame(msgpack.packb(bad))
            assert err.value.status == 422 and err.value.body.field == "vehicle_id"
            with pytest.raises(ValueError, match="same encoding"):
                client.align(p, to_json(load_frame(e, Limits())))

        async def run():
            async with AsyncAlignClient(url, verify_answers=False) as client:
                r = await client.align(p, e)
                return r, await client.peers(), await client.bandwidth()

        res, peers, bw = asyncio.run(run())
        assert res.success and pose_error(res.matrix(), true_T_ego_peer(ego, peer))[0] < 0.3
        assert "car1" in peers and bw["peers"]["car1"]["messages"] >= 2


def test_zenoh_peer_context_manager_closes_its_session():
    with ZenohPeer(
        "car1", connect=[f"tcp/127.0.0.1:{free_port()}"], verify_answers=False
    ) as car:  # nobody there: still opens
        assert car.session is not None and not car.wait_for_subscriber(0.2)
    assert car.session is None
