"""Wire models, encodings and the shared validator (bb_align.protocol)."""

from __future__ import annotations

import json
import math
import struct
import zlib
from fractions import Fraction
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from bb_align import BevConfig, make_bev
from bb_align.protocol import (
    JSON,
    MSGPACK,
    AlignRequest,
    BevMeta,
    Frame,
    Limits,
    Pose,
    Result,
    WireError,
    json_align_request,
    json_schemas,
    load_align_request,
    load_frame,
    load_result,
    pack,
    pack_align_request,
    to_json,
)

REPO = Path(__file__).resolve().parents[1]
LIMITS = Limits()


def _image(n=100, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((n, n), np.uint8)
    img[rng.integers(0, n, 300), rng.integers(0, n, 300)] = rng.integers(1, 255, 300)
    return img


def _png(img) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def _frame(**kw) -> Frame:
    base = dict(
        vehicle_id="car-1",
        seq=3,
        stamp=12.5,
        png=_png(_image()),
        bev=BevMeta(resolution_m=0.4, range_m=20),
        boxes=[[10.0, -2.0, 0.8, 4.5, 1.9, 1.6, 0.3], [-5.0, 3.0, 0.7, 4.2, 1.8, 1.5, -2.9]],
        scores=[0.9, 0.6],
        pose=Pose(x=100.0, y=-50.0, z=1.8, roll=0.01, pitch=-0.02, yaw=1.2),
        num_points=120_000,
    )
    return Frame(**{**base, **kw})


def _fields(frame: Frame) -> dict:
    return frame.model_dump(mode="python")


def _refused(data: bytes, encoding=MSGPACK, limits=LIMITS) -> WireError:
    with pytest.raises(WireError) as e:
        load_frame(data, limits, encoding)
    return e.value


def test_msgpack_and_json_round_trips_are_lossless():
    f = _frame()
    assert load_frame(pack(f), LIMITS) == f
    assert load_frame(to_json(f), LIMITS, JSON) == f
    assert json.loads(to_json(f))["png"][:8] == "iVBORw0K"  # standard base64 of the PNG signature
    img = load_frame(pack(f), LIMITS).bev_image()
    np.testing.assert_array_equal(img.image, _image())
    assert (img.resolution_m, img.range_m) == (0.4, 20)


def test_align_request_is_built_from_encoded_frames_without_decoding_them():
    peer, ego = _frame(vehicle_id="car1"), _frame(vehicle_id="ego", stamp=12.45)
    req = load_align_request(pack_align_request(pack(peer), pack(ego)), LIMITS)
    assert req == AlignRequest(peer=peer, ego=ego)
    req = load_align_request(json_align_request(to_json(peer)), LIMITS, JSON)
    assert req.peer == peer and req.ego is None


def test_a_real_bev_frame_is_small_against_its_raw_points():
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-40, 40, (50_000, 2)), rng.uniform(-1.5, 3, 50_000)]).astype(np.float32)
    bev = make_bev(pts, BevConfig(range_m=40))
    f = _frame(png=bev.to_png(), bev=BevMeta(**bev.meta()), num_points=len(pts))
    assert len(pack(f)) < 16 * len(pts) / 10


@pytest.mark.parametrize(
    "data,status",
    [
        (b"\x93\x01\x02", 400),  # an array, not a map
        (b"\xde\xff", 400),  # truncated map
        (msgpack.packb({"a": 1}) + b"\x00", 400),  # trailing bytes
        (b"\x91" * 5000 + b"\x00", 400),  # nesting bomb
        (msgpack.packb({"vehicle_id": msgpack.ExtType(5, b"x")}), 400),  # extension types are refused
    ],
)
def test_undecodable_messages_are_400(data, status):
    assert _refused(data).status == status


def test_oversized_message_is_413_before_decoding():
    e = _refused(b"\x00" * 5000, limits=Limits(max_message_bytes=4096))
    assert (e.status, e.field, e.limit) == (413, "message", 4096)


@pytest.mark.parametrize(
    "change,field",
    [
        ({"schema_version": 2}, "schema_version"),
        ({"vehicle_id": "car/1"}, "vehicle_id"),
        ({"vehicle_id": "*"}, "vehicle_id"),
        ({"stamp": -1.0}, "stamp"),
        ({"stamp": float("nan")}, "stamp"),
        ({"boxes": [[1, 2, 3, 4, 5, 6]]}, "boxes.0"),
        ({"boxes": [[1, 2, 3, 4, 5, float("inf"), 0]]}, "boxes.0.5"),
        ({"scores": [0.5, 1.5]}, "scores.1"),
        ({"bev": {"resolution_m": 0.4, "range_m": 1000}}, "bev.range_m"),
        ({"unknown": 1}, "unknown"),
    ],
)
def test_field_errors_are_422_naming_the_field(change, field):
    e = _refused(msgpack.packb({**_fields(_frame()), **change}))
    assert (e.status, e.field) == (422, field)


@pytest.mark.parametrize(
    "frame,limits,field,limit",
    [
        (_frame(stamp=5e9), LIMITS, "stamp", LIMITS.max_stamp_s),
        (_frame(num_points=10**9), LIMITS, "num_points", LIMITS.max_points),
        (_frame(boxes=[[1, 2, 0, 4, 2, 1.5, 0]] * 3, scores=None), Limits(max_boxes=2), "boxes", 2),
        (_frame(boxes=[[1, 2, 0, 4, 2, 1.5, 0]], scores=[0.5, 0.5]), LIMITS, "scores", None),
        (_frame(boxes=[[1, 2, 0, 4, 2, 1.5, 0], [1, 2, 0, 0, 2, 1.5, 0]], scores=None), LIMITS, "boxes.1", 40.0),
        (_frame(boxes=[[900, 2, 0, 4, 2, 1.5, 0]], scores=None), LIMITS, "boxes.0", 500.0),
        (_frame(pose=Pose(x=1e8, y=0)), LIMITS, "pose.x", 1e7),
        (_frame(png=_png(_image(100)), bev=BevMeta(resolution_m=0.4, range_m=40)), LIMITS, "png", None),
        (_frame(png=_png(_image(100))), Limits(max_image_px=64), "png", 64),
    ],
)
def test_limit_errors_are_422_naming_the_field_and_limit(frame, limits, field, limit):
    e = _refused(pack(frame), limits=limits)
    assert (e.status, e.field, e.limit) == (422, field, limit)
    assert e.detail


def _with_ihdr(png: bytes, width=None, height=None, depth=None, colour=None, fix_crc=True) -> bytes:
    w, h, d, c, cm, fm, il = struct.unpack(">IIBBBBB", png[16:29])
    body = struct.pack(">IIBBBBB", width or w, height or h, depth or d, colour if colour is not None else c, cm, fm, il)
    crc = struct.pack(">I", zlib.crc32(b"IHDR" + body)) if fix_crc else png[29:33]
    return png[:16] + body + crc + png[33:]


@pytest.mark.parametrize(
    "png,words",
    [
        (b"GIF89a" + b"\x00" * 40, "signature"),
        (_png(_image())[:20], "signature"),
        (_png(np.zeros((100, 100), np.uint16)), "bit depth"),
        (_png(np.zeros((100, 100, 3), np.uint8)), "colour type"),
        (_with_ihdr(_png(_image()), width=60000, height=60000), "exceeds"),
        (_with_ihdr(_png(_image()), width=101, fix_crc=False), "checksum"),
    ],
)
def test_png_header_is_checked_before_any_pixel_is_decoded(png, words):
    e = _refused(pack(_frame(png=png)))
    assert (e.status, e.field) == (422, "png") and words in e.detail


def test_corrupt_pixels_behind_a_valid_header_are_refused_before_any_decoder_sees_them():
    png = _png(_image())
    broken = png[:40] + bytes(len(png) - 52) + png[-12:]
    e = _refused(pack(_frame(png=broken)))  # every chunk's checksum is checked, not only IHDR's
    assert (e.status, e.field) == (422, "png") and "checksum" in e.detail
    unchecked = _frame().model_copy(update={"png": broken})  # a Frame built without load_frame
    with pytest.raises(WireError) as e:
        unchecked.bev_image()
    assert (e.value.status, e.value.field) == (422, "png")


def test_align_request_errors_name_the_frame():
    bad = {**_fields(_frame()), "boxes": [[0, 0, 0, 4, 2, 1.5, 0]] * 3, "scores": None}
    data = pack_align_request(pack(_frame()), msgpack.packb(bad))
    with pytest.raises(WireError) as e:
        load_align_request(data, Limits(max_boxes=2))
    assert (e.value.field, e.value.limit) == ("ego.boxes", 2)


def test_json_png_must_be_base64():
    d = json.loads(to_json(_frame()))
    d["png"] = "not base64!"
    e = _refused(json.dumps(d).encode(), JSON)
    assert (e.status, e.field) == (422, "png")


@hsettings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_only_ever_raise_wire_errors(data):
    with pytest.raises(WireError):
        load_frame(data, LIMITS)


@hsettings(max_examples=100, deadline=None)
@given(
    st.dictionaries(
        st.sampled_from(list(Frame.model_fields) + ["x"]),
        st.one_of(
            st.none(),
            st.integers(-(2**63), 2**64 - 1),
            st.floats(),
            st.text(max_size=5),
            st.binary(max_size=40),
            st.lists(st.floats(), max_size=8),
        ),
        max_size=8,
    )
)
def test_random_maps_only_ever_raise_wire_errors(d):
    with pytest.raises(WireError):
        load_frame(msgpack.packb(d), LIMITS)


_KEYS = st.one_of(
    st.sampled_from(list(Frame.model_fields) + ["x"]),
    st.binary(max_size=8),
    st.integers(-5, 5),
    st.booleans(),
    st.none(),
    st.floats(allow_nan=False),
)


def _msgpack_map(pairs) -> bytes:
    """A msgpack map written pair by pair (keys of any type, duplicates kept: msgpack.packb(dict) cannot)."""
    return bytes([0x80 | len(pairs)]) + b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in pairs)


@hsettings(max_examples=150, deadline=None)
@given(
    st.lists(
        st.tuples(
            _KEYS, st.one_of(st.none(), st.integers(-(2**63), 2**63 - 1), st.text(max_size=4), st.binary(max_size=4))
        ),
        max_size=6,
    ),
    st.sampled_from(["frame", "align_request"]),
)
def test_maps_with_any_key_types_and_duplicate_keys_only_raise_wire_errors(pairs, kind):
    """Finding 4: a str and a bytes key (82a16101c4016202) made sorted() raise TypeError -> HTTP 500."""
    load = load_frame if kind == "frame" else load_align_request
    with pytest.raises(WireError) as e:
        load(_msgpack_map(pairs[:15]), LIMITS)
    assert e.value.status in (400, 413, 422)


def test_mixed_key_types_and_duplicate_keys_are_400_naming_the_key():
    e = _refused_request(bytes.fromhex("82a16101c4016202"))
    assert e.status == 400 and "keys must be strings" in e.detail
    good = _fields(_frame())
    dup = _msgpack_map([*good.items(), ("seq", 99)])
    e = _refused(dup)
    assert e.status == 400 and "duplicate map key 'seq'" in e.detail
    body = json.dumps(json.loads(to_json(_frame())))[:-1] + ', "seq": 99}'
    e = _refused(body.encode(), JSON)
    assert e.status == 400 and "duplicate map key 'seq'" in e.detail


def _refused_request(data: bytes) -> WireError:
    with pytest.raises(WireError) as e:
        load_align_request(data, LIMITS)
    return e.value


@pytest.mark.parametrize(
    "change, field",
    [
        ({"seq": "1"}, "seq"),
        ({"seq": True}, "seq"),
        ({"vehicle_id": b"car1"}, "vehicle_id"),
        ({"stamp": "5"}, "stamp"),
        ({"schema_version": True}, "schema_version"),
    ],
)
def test_no_coercion_on_the_air(change, field):
    """Finding 7: "1", true and bytes were coerced into the fields' types."""
    e = _refused(msgpack.packb({**_fields(_frame()), **change}, use_bin_type=True))
    assert (e.status, e.field) == (422, field)


def test_no_coercion_inside_nested_maps_and_cross_field_checks():
    d = _fields(_frame())
    e = _refused(msgpack.packb({**d, "bev": {**d["bev"], "range_m": "20"}}, use_bin_type=True))
    assert (e.status, e.field) == (422, "bev.range_m")
    e = _refused(msgpack.packb({**d, "bev": {**d["bev"], "ground_clearance_m": 5.0, "max_height_m": 4.0}}))
    assert (e.status, e.field, e.limit) == (422, "bev.ground_clearance_m", 4.0)


def test_a_0x0_image_is_refused_naming_the_limit():
    d = _fields(_frame())
    d["bev"] = {**d["bev"], "range_m": 0.001, "resolution_m": 5.0}
    e = _refused(msgpack.packb(d, use_bin_type=True))
    assert (e.status, e.field, e.limit) == (422, "bev.range_m", LIMITS.min_image_px)


def test_pose_matrix_matches_scipy_and_round_trips():
    p = Pose(x=1.0, y=-2.0, z=0.5, roll=0.1, pitch=-0.25, yaw=2.8)
    R_ref = Rotation.from_euler("ZYX", [p.yaw, p.pitch, p.roll]).as_matrix()  # intrinsic z-y'-x''
    np.testing.assert_allclose(p.matrix()[:3, :3], R_ref, atol=1e-12)
    q = Pose.from_matrix(p.matrix())
    np.testing.assert_allclose([q.x, q.y, q.z, q.roll, q.pitch, q.yaw], [1.0, -2.0, 0.5, 0.1, -0.25, 2.8], atol=1e-12)


def test_result_decodes_from_msgpack_and_json():
    r = Result(
        ego_id="ego",
        peer_id="car1",
        peer_seq=1,
        peer_stamp=0.1,
        success=True,
        yaw_deg=3.0,
        tx=1.0,
        ty=2.0,
        T_ego_peer=np.eye(4).tolist(),
    )
    assert load_result(pack(r)) == r == load_result(to_json(r))
    np.testing.assert_array_equal(r.matrix(), np.eye(4))


def test_committed_json_schemas_match_the_models():
    """proto_schemas/*.schema.json are generated (`bb-align wire-schemas`); this fails when they drift."""
    for name, schema in json_schemas().items():
        path = REPO / "proto_schemas" / f"{name}.schema.json"
        assert path.exists(), f"{path} missing: run `bb-align wire-schemas`"
        assert json.loads(path.read_text()) == schema, f"{path} is stale: run `bb-align wire-schemas`"


# ---- box yaw: any finite angle, wrapped into [-pi, pi) (issue 14) ----------------------------------------------
@given(st.floats(allow_nan=False, allow_infinity=False))
def test_any_finite_box_yaw_is_taken_and_wrapped_into_minus_pi_pi(yaw):
    """Independent truth in exact rational arithmetic: the wrapped yaw is in [-pi, pi) and a whole number of
    turns (of the float 2 pi) from the sent one, so the heading the engine sees is the sent heading."""
    box = [10.0, -2.0, 0.8, 4.5, 1.9, 1.6, yaw]
    wrapped = load_frame(msgpack.packb({**_fields(_frame()), "boxes": [box], "scores": None}), LIMITS).boxes[0][6]
    assert -math.pi <= wrapped < math.pi
    turns = (Fraction(yaw) - Fraction(wrapped)) / Fraction(math.tau)
    assert turns.denominator == 1, (yaw, wrapped, turns)


def test_a_yaw_of_7_rad_arrives_as_exactly_7_minus_2_pi():
    def sent(yaw):
        box = [10.0, -2.0, 0.8, 4.5, 1.9, 1.6, yaw]
        return load_frame(msgpack.packb({**_fields(_frame()), "boxes": [box], "scores": None}), LIMITS)

    assert sent(7.0).boxes[0][6] == 7.0 - 2 * math.pi  # bit for bit: the same engine input
    assert pack(sent(7.0)) == pack(sent(7.0 - 2 * math.pi))
    assert sent(math.pi).boxes[0][6] == -math.pi  # the half-open end
    assert sent(-7.5).boxes[0][6] == pytest.approx(-7.5 + 2 * math.pi, abs=1e-15)


@pytest.mark.parametrize("encoding", [MSGPACK, JSON])
def test_a_non_finite_yaw_is_refused_naming_the_box_component(encoding):
    d = _frame().model_dump(mode="json" if encoding == JSON else "python")
    d["boxes"][1][6] = float("nan")
    e = _refused(json.dumps(d).encode() if encoding == JSON else msgpack.packb(d), encoding)
    assert (e.status, e.field) == (422, "boxes.1.6") and "yaw" in e.detail and "nan" in e.detail


def test_the_schema_says_any_finite_yaw_is_wrapped():
    schema = json.dumps(json_schemas()["frame"])
    assert "any finite angle, radians, wrapped" in schema and "2 pi" not in schema
