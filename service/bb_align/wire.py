"""Wire messages between cars and the ego-side service: models, encodings, key expressions, validation.

A peer sends one :class:`Frame` per LiDAR sweep (a PNG BV height image, what is needed to map its pixels to
metres, its object boxes and optionally its reported pose). The service answers with a :class:`Result`.
Messages are msgpack maps (PNG as ``bin``); REST also takes JSON with the PNG as a base64 string.

A signed frame travels in a :class:`Signed` envelope (key id, HMAC-SHA256, the frame's encoded bytes; see
bb_align.auth).

Every message from either door (Zenoh, REST) goes through :func:`load_frame` / :func:`load_align_request`: size
first, then decoding, the signature (on the raw payload bytes, before the frame is decoded), the fields, and
:func:`validate_frame`, the single place where a frame's limits are checked: the whole PNG structure (every
chunk's checksum, IHDR, and the image data inflated under a bound) before any pixel is decoded by OpenCV, boxes,
numbers, stamps against the receiver's clock. All failures raise :class:`WireError` with the offending field, the
limit and an HTTP status; nothing else escapes.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import struct
import zlib
from typing import Annotated, Any, Literal

import msgpack
import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, PlainSerializer, ValidationError, WithJsonSchema

from .bev import BevImage, decode_png, image_size_px
from .config import BevConfig
from .geometry import rotation_rpy
from .auth import MAC_BYTES, AuthError, Keyring, frame_mac
from .settings import FLEET_KEY_ID, VEHICLE_ID_PATTERN, Limits

SCHEMA_VERSION = 1
MSGPACK = "application/msgpack"
JSON = "application/json"
BOX_FIELDS = ("x", "y", "z", "l", "w", "h", "yaw")


# ---- key expressions -----------------------------------------------------------------------------------------
def frames_key(prefix: str, vehicle_id: str) -> str:
    """Where a car publishes its frames."""
    return f"{prefix}/frames/{vehicle_id}"


def poses_key(prefix: str, ego_id: str, peer_id: str) -> str:
    """Where the ego service publishes T_ego_peer for one peer."""
    return f"{prefix}/poses/{ego_id}/{peer_id}"


def align_key(prefix: str, ego_id: str) -> str:
    """The ego service's queryable: a query carrying a peer frame is answered with a Result."""
    return f"{prefix}/align/{ego_id}"


# ---- errors ----------------------------------------------------------------------------------------------------
class WireError(ValueError):
    """A message that cannot be used. ``status``: 400 undecodable, 401 unsigned or wrongly signed, 403 signed
    with another vehicle's key, 409 replayed, 413 too large, 415 other media type, 422 invalid field."""

    def __init__(self, status: int, error: str, detail: str, field: str | None = None, limit: Any = None):
        super().__init__(f"{field}: {detail}" if field else detail)
        self.status, self.error, self.detail, self.field, self.limit = status, error, detail, field, limit

    def body(self) -> "ErrorBody":
        return ErrorBody(error=self.error, detail=self.detail, field=self.field, limit=self.limit)


def _too_large(field: str, size: int, limit: int) -> WireError:
    return WireError(413, "too_large", f"{size} bytes exceed the limit of {limit} bytes", field, limit)


def _invalid(field: str, detail: str, limit: Any = None) -> WireError:
    return WireError(422, "invalid", detail, field, limit)


# ---- models ------------------------------------------------------------------------------------------------------
def _b64_if_str(v: Any) -> Any:
    """JSON carries the PNG as a base64 string (standard or URL-safe alphabet); msgpack as raw bytes."""
    if isinstance(v, str):
        try:
            return base64.b64decode(v.replace("-", "+").replace("_", "/"), validate=True)
        except (binascii.Error, ValueError) as e:
            raise ValueError(f"not valid base64: {e}") from None
    return v


_B64_JSON = PlainSerializer(lambda b: base64.b64encode(b).decode("ascii"), return_type=str, when_used="json")
PngBytes = Annotated[
    bytes,
    BeforeValidator(_b64_if_str),
    PlainSerializer(lambda b: base64.b64encode(b).decode("ascii"), return_type=str, when_used="json"),
    WithJsonSchema({"type": "string", "contentEncoding": "base64", "contentMediaType": "image/png",
                    "description": "PNG file, 8-bit greyscale; msgpack: bin, JSON: base64 string"}),
]
Box = Annotated[list[float], Field(min_length=7, max_length=7, description="[x, y, z, l, w, h, yaw]")]


class _Wire(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class BevMeta(_Wire):
    """How the PNG's pixels map to metres (bb_align.bev): the sensor at the image centre, rows along -x,
    columns along -y; a pixel value v > 0 is a height above ground of clearance + (v-1)/254 (max - clearance)."""

    resolution_m: float = Field(gt=0.01, le=5, description="cell size, metres per pixel")
    range_m: float = Field(gt=0, le=250, description="half width of the square image, metres")
    mode: Literal["max_height", "slices"] = "max_height"
    ground_clearance_m: float = Field(0.3, ge=0, le=5)
    max_height_m: float = Field(12.0, gt=0, le=100)


class Pose(_Wire):
    """A reported pose T_world_sensor: metres and radians, R = Rz(yaw) Ry(pitch) Rx(roll)."""

    x: float
    y: float
    z: float = 0.0
    roll: float = Field(0.0, ge=-math.tau, le=math.tau)
    pitch: float = Field(0.0, ge=-math.tau, le=math.tau)
    yaw: float = Field(0.0, ge=-math.tau, le=math.tau)

    def matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = rotation_rpy(self.roll, self.pitch, self.yaw)
        T[:3, 3] = (self.x, self.y, self.z)
        return T

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> "Pose":
        T = np.asarray(T, dtype=float)
        R = T[:3, :3]
        pitch = math.asin(float(np.clip(-R[2, 0], -1.0, 1.0)))
        return cls(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3]),
                   roll=math.atan2(R[2, 1], R[2, 2]), pitch=pitch, yaw=math.atan2(R[1, 0], R[0, 0]))


class Frame(_Wire):
    """One car's LiDAR sweep as sent on the air (Zenoh ``<prefix>/frames/<vehicle_id>`` or REST)."""

    schema_version: Literal[1] = SCHEMA_VERSION
    vehicle_id: str = Field(pattern=VEHICLE_ID_PATTERN)
    seq: int = Field(0, ge=0, le=2**63 - 1, description="sender's frame counter")
    stamp: float = Field(ge=0, description="capture time, seconds (the cars' common clock)")
    png: PngBytes
    bev: BevMeta
    boxes: list[Box] = Field(default_factory=list, description="rows [x, y, z, l, w, h, yaw], sensor frame, "
                             "metres and radians; (x, y, z) is the box centre, l along the heading")
    scores: list[Annotated[float, Field(ge=0, le=1)]] | None = Field(None, description="one per box")
    pose: Pose | None = Field(None, description="reported T_world_sensor (GNSS/odometry); optional")
    num_points: int | None = Field(None, ge=0, description="points in the raw sweep (bandwidth accounting)")

    def bev_image(self, limits: Limits | None = None) -> BevImage:
        """Decode the PNG into the engine's BevImage. The PNG's structure is checked again first (cheap), so
        OpenCV never sees an unchecked file, whoever built this Frame."""
        n = image_size_px(BevConfig(range_m=self.bev.range_m, resolution_m=self.bev.resolution_m))
        check_png(self.png, n, limits or Limits(), "png")
        try:
            image = decode_png(self.png)
        except ValueError as e:
            raise _invalid("png", str(e)) from None
        if image.shape != (n, n):
            raise _invalid("png", f"decoded image is {image.shape}, the header and bev say ({n}, {n})")
        return BevImage(image=image, **self.bev.model_dump())

    def boxes_array(self) -> np.ndarray:
        return np.asarray(self.boxes, dtype=np.float64).reshape(-1, 7)


class Signed(_Wire):
    """A signed frame: the frame's own encoded bytes (msgpack, or JSON inside a JSON envelope) with an
    HMAC-SHA256 made with the key ``key_id`` names (bb_align.auth): ``"fleet"`` or the sender's vehicle id."""

    schema_version: Literal[1] = SCHEMA_VERSION
    key_id: str = Field(pattern=VEHICLE_ID_PATTERN, description=f"{FLEET_KEY_ID!r} or the sender's vehicle id")
    alg: Literal["hmac-sha256"] = "hmac-sha256"
    mac: Annotated[bytes, BeforeValidator(_b64_if_str), Field(min_length=MAC_BYTES, max_length=MAC_BYTES),
                   _B64_JSON, WithJsonSchema({"type": "string", "contentEncoding": "base64",
                                              "description": "HMAC-SHA256(key, 'bb-align/frame/v1' 0x00 key_id 0x00 "
                                                             "payload), 32 bytes; msgpack: bin, JSON: base64"})]
    payload: Annotated[bytes, BeforeValidator(_b64_if_str), Field(min_length=1), _B64_JSON,
                       WithJsonSchema({"type": "string", "contentEncoding": "base64",
                                       "description": "the encoded Frame, in the envelope's own encoding; "
                                                      "msgpack: bin, JSON: base64"})]


class AlignRequest(_Wire):
    """REST POST /v1/align: a peer frame and optionally the ego frame (else the service's cached one); each
    a Frame or a Signed frame (the service resolves envelopes: a loaded request holds Frames)."""

    schema_version: Literal[1] = SCHEMA_VERSION
    peer: Frame | Signed
    ego: Frame | Signed | None = None


class Result(_Wire):
    """T_ego_peer for one peer frame (Zenoh ``<prefix>/poses/<ego_id>/<peer_id>``, query replies, REST)."""

    schema_version: Literal[1] = SCHEMA_VERSION
    ego_id: str
    peer_id: str
    peer_seq: int
    peer_stamp: float
    ego_seq: int | None = Field(None, description="the ego frame used (None: none was available)")
    ego_stamp: float | None = None
    ego_skew_s: float | None = Field(None, description="peer_stamp - ego_stamp")
    success: bool
    reason: str | None = Field(None, description="a bb_align.FailureReason value when success is false")
    yaw_deg: float | None = Field(None, description="T_ego_peer's yaw, degrees CCW")
    tx: float | None = Field(None, description="T_ego_peer's x translation, metres")
    ty: float | None = Field(None, description="T_ego_peer's y translation, metres")
    T_ego_peer: list[Annotated[list[float], Field(min_length=4, max_length=4)]] | None = Field(
        None, min_length=4, max_length=4, description="4x4 row-major, maps peer sensor points into the ego frame")
    inliers_bv: int = 0
    inliers_box: int = 0
    matches_bv: int = 0
    box_pairs: int = 0
    confidence: float = 0.0
    stage2_applied: bool = False
    prior_used: bool = Field(False, description="roll, pitch, tz taken from the two reported poses")
    notes: list[str] = Field(default_factory=list)
    timings_ms: dict[str, float] = Field(default_factory=dict)
    latency_ms: float | None = Field(None, description="service: message received -> result ready")
    bytes_received: int = Field(0, description="size of the peer's message")
    raw_points_bytes: int | None = Field(None, description="16 B x the sender's point count")
    ratio_vs_points: float | None = Field(None, description="bytes_received / raw_points_bytes")

    def matrix(self) -> np.ndarray | None:
        return None if self.T_ego_peer is None else np.asarray(self.T_ego_peer, dtype=float)


class ErrorBody(_Wire):
    """Why a message was refused (REST error responses, Zenoh query error replies)."""

    error: Literal["too_large", "undecodable", "invalid", "unsupported_media_type", "unauthenticated",
                   "forbidden", "replayed", "overloaded", "timeout", "unavailable"]
    detail: str
    field: str | None = Field(None, description="the offending field, dotted path")
    limit: float | int | str | None = Field(None, description="the limit that was exceeded")


WIRE_MODELS: dict[str, type[BaseModel]] = {
    "frame": Frame, "signed": Signed, "align_request": AlignRequest, "result": Result, "error": ErrorBody,
}


# ---- encodings ---------------------------------------------------------------------------------------------------
def pack(model: BaseModel) -> bytes:
    """A wire model -> msgpack bytes (PNG as bin)."""
    return msgpack.packb(model.model_dump(mode="python"), use_bin_type=True)


def to_json(model: BaseModel) -> bytes:
    """A wire model -> JSON bytes (PNG as base64)."""
    return model.model_dump_json().encode()


def pack_align_request(peer: bytes, ego: bytes | None = None) -> bytes:
    """Two msgpack-encoded frames -> one msgpack AlignRequest, without decoding them (a map of pre-packed values)."""
    parts = [msgpack.packb("schema_version"), msgpack.packb(SCHEMA_VERSION), msgpack.packb("peer"), peer]
    if ego is not None:
        parts += [msgpack.packb("ego"), ego]
    return bytes([0x80 | (len(parts) // 2)]) + b"".join(parts)


def json_align_request(peer: bytes, ego: bytes | None = None) -> bytes:
    """Two JSON-encoded frames -> one JSON AlignRequest."""
    body = b'{"schema_version":%d,"peer":%s' % (SCHEMA_VERSION, peer)
    return body + (b',"ego":' + ego if ego is not None else b"") + b"}"


def sign(payload: bytes, key: bytes | str, key_id: str = FLEET_KEY_ID, encoding: str | None = None) -> bytes:
    """Wrap an encoded frame in a Signed envelope of the same encoding (JSON when the payload is JSON)."""
    encoding = encoding or (JSON if payload[:1] == b"{" else MSGPACK)
    env = Signed(key_id=key_id, mac=frame_mac(key, key_id, payload), payload=payload)
    return to_json(env) if encoding == JSON else pack(env)


def is_signed(data: bytes) -> bool:
    """Whether encoded bytes hold a Signed envelope rather than a bare Frame (cheap: looks at the keys only)."""
    try:
        obj = json.loads(data) if data[:1] == b"{" else msgpack.unpackb(data, raw=False, max_bin_len=len(data))
    except Exception:
        return False
    return _is_envelope(obj)


def _is_envelope(obj: Any) -> bool:
    return isinstance(obj, dict) and "mac" in obj and "payload" in obj


def _unpack(data: bytes, encoding: str, limits: Limits) -> dict:
    """Bytes -> a plain dict, refusing oversized or undecodable messages before any model is built."""
    if len(data) > limits.max_message_bytes:
        raise _too_large("message", len(data), limits.max_message_bytes)
    try:
        if encoding == MSGPACK:
            obj = msgpack.unpackb(
                data, raw=False, strict_map_key=True, max_bin_len=limits.max_message_bytes,
                max_str_len=limits.max_message_bytes, max_array_len=2 * limits.max_boxes + 64,
                max_map_len=64, max_ext_len=0)
        elif encoding == JSON:
            obj = json.loads(data)
        else:
            raise WireError(415, "unsupported_media_type", f"use {MSGPACK} or {JSON}", "content-type", encoding)
    except WireError:
        raise
    except Exception as e:  # msgpack/json raise many types (ExtraData, StackError, RecursionError, ...)
        raise WireError(400, "undecodable", f"not a {encoding} message: {type(e).__name__}: {e}"[:300]) from None
    if not isinstance(obj, dict):
        raise WireError(400, "undecodable", f"the message must be a map, got {type(obj).__name__}")
    return obj


def _model(cls: type[BaseModel], obj: Any, where: str = ""):
    try:
        return cls.model_validate(obj)
    except ValidationError as e:
        errs = e.errors(include_url=False, include_input=False)
        loc = lambda err: ".".join(str(p) for p in (*([where] if where else []), *err["loc"]))  # noqa: E731
        detail = "; ".join(f"{loc(err) or '(message)'}: {err['msg']}" for err in errs[:5])
        raise _invalid(loc(errs[0]) or where or "message", detail) from None
    except (RecursionError, MemoryError) as e:  # absurd nesting that the decoder let through
        raise WireError(400, "undecodable", f"{where or 'message'}: {type(e).__name__}") from None


def _precheck(obj: dict, limits: Limits, f) -> None:
    """Counts that must be refused before a model is built for them (e.g. 10^6 boxes)."""
    for name in ("boxes", "scores"):
        v = obj.get(name)
        if isinstance(v, (list, tuple)) and len(v) > limits.max_boxes:
            raise _invalid(f(name), f"{len(v)} {name} exceed {limits.max_boxes}", limits.max_boxes)


def _frame_from(obj: Any, limits: Limits, encoding: str, keyring: Keyring | None, now: float | None,
                where: str = "") -> Frame:
    """A decoded map (a Frame, or a Signed envelope holding one) -> a checked Frame."""
    f = (lambda name: f"{where}.{name}" if where else name)  # noqa: E731
    if not isinstance(obj, dict):
        raise _invalid(where or "message", f"must be a map (a Frame or a Signed frame), got {type(obj).__name__}")
    bound_to = None
    if _is_envelope(obj):
        env: Signed = _model(Signed, obj, where)
        if keyring is not None:
            try:
                bound_to = keyring.verify(env.key_id, env.mac, env.payload)
            except AuthError as e:
                if keyring.required or e.detail != f"unknown key id {env.key_id!r}":
                    raise WireError(e.status, e.error, e.detail, f("mac"), "hmac-sha256") from None
        obj = _unpack(env.payload, encoding, limits)
        if _is_envelope(obj):
            raise _invalid(f("payload"), "a signed payload must be a Frame, not another envelope")
    elif keyring is not None and keyring.required:
        raise WireError(401, "unauthenticated", "frames must be signed (a Signed envelope with an HMAC-SHA256; "
                        "see docs/security.md)", where or "message", "hmac-sha256")
    _precheck(obj, limits, f)
    frame: Frame = _model(Frame, obj, where)
    validate_frame(frame, limits, where, now=now)
    if bound_to is not None and frame.vehicle_id != bound_to:
        raise WireError(403, "forbidden", f"signed with {bound_to!r}'s key but claims vehicle id "
                        f"{frame.vehicle_id!r}", f("vehicle_id"), bound_to)
    return frame


def load_frame(data: bytes, limits: Limits, encoding: str = MSGPACK, *, keyring: Keyring | None = None,
               now: float | None = None) -> Frame:
    """Untrusted bytes (a Frame or a Signed frame) -> a checked Frame (raises WireError, nothing else).

    ``keyring``: verify signatures (and refuse unsigned frames when it requires them); ``now``: the receiver's
    clock (time.time()) for the stamp window; without it only the absolute stamp range is checked."""
    return _frame_from(_unpack(data, encoding, limits), limits, encoding, keyring, now)


def load_align_request(data: bytes, limits: Limits, encoding: str = MSGPACK, *, keyring: Keyring | None = None,
                       now: float | None = None) -> AlignRequest:
    """Untrusted bytes -> an AlignRequest holding checked Frames (raises WireError)."""
    obj = _unpack(data, encoding, limits)
    extra = sorted(set(obj) - {"schema_version", "peer", "ego"})
    if extra:
        raise _invalid(str(extra[0]), "Extra inputs are not permitted")
    if obj.get("schema_version", SCHEMA_VERSION) != SCHEMA_VERSION:
        raise _invalid("schema_version", f"Input should be {SCHEMA_VERSION}", SCHEMA_VERSION)
    if "peer" not in obj:
        raise _invalid("peer", "Field required")
    peer = _frame_from(obj["peer"], limits, encoding, keyring, now, "peer")
    ego = None if obj.get("ego") is None else _frame_from(obj["ego"], limits, encoding, keyring, now, "ego")
    return AlignRequest(peer=peer, ego=ego)


def load_result(data: bytes) -> Result:
    """msgpack or JSON bytes -> Result (a JSON object starts with '{', never a msgpack map)."""
    encoding = JSON if data[:1] == b"{" else MSGPACK
    return _model(Result, _unpack(data, encoding, Limits()))


# ---- the one validator -------------------------------------------------------------------------------------------
def validate_frame(frame: Frame, limits: Limits, where: str = "", now: float | None = None) -> None:
    """Check a decoded Frame against the limits (raises WireError). The PNG is checked chunk by chunk and its
    image data inflated under a bound; OpenCV decodes nothing here.

    Field-level rules (types, ranges, finite numbers, id format, schema version) are already enforced by the
    models; this adds the limits that depend on settings, on the receiver's clock and on the image content."""
    f = (lambda name: f"{where}.{name}" if where else name)  # noqa: E731
    if frame.stamp > limits.max_stamp_s:
        raise _invalid(f("stamp"), f"stamp {frame.stamp} s is beyond {limits.max_stamp_s} s", limits.max_stamp_s)
    if now is not None and limits.check_stamp_clock:
        if frame.stamp < now - limits.max_stamp_age_s:
            raise _invalid(f("stamp"), f"stamp is {now - frame.stamp:.3f} s before the receiver's clock, more than "
                                       f"max_stamp_age_s", limits.max_stamp_age_s)
        if frame.stamp > now + limits.max_stamp_lead_s:
            raise _invalid(f("stamp"), f"stamp is {frame.stamp - now:.3f} s after the receiver's clock, more than "
                                       f"max_stamp_lead_s", limits.max_stamp_lead_s)
    if frame.num_points is not None and frame.num_points > limits.max_points:
        raise _invalid(f("num_points"), f"{frame.num_points} points exceed {limits.max_points}", limits.max_points)
    n = image_size_px(BevConfig(range_m=frame.bev.range_m, resolution_m=frame.bev.resolution_m))
    check_png(frame.png, n, limits, f("png"))
    _check_boxes(frame, limits, f)
    if frame.pose is not None:
        for name in ("x", "y", "z"):
            if abs(getattr(frame.pose, name)) > limits.max_pose_m:
                raise _invalid(f(f"pose.{name}"), f"|{name}| exceeds {limits.max_pose_m} m", limits.max_pose_m)


def _check_boxes(frame: Frame, limits: Limits, f) -> None:
    if len(frame.boxes) > limits.max_boxes:
        raise _invalid(f("boxes"), f"{len(frame.boxes)} boxes exceed {limits.max_boxes}", limits.max_boxes)
    if frame.scores is not None and len(frame.scores) != len(frame.boxes):
        raise _invalid(f("scores"), f"{len(frame.scores)} scores for {len(frame.boxes)} boxes")
    if not frame.boxes:
        return
    b = frame.boxes_array()
    big = np.abs(b[:, :3]) > limits.max_box_distance_m
    if big.any():
        i = int(np.argwhere(big)[0, 0])
        raise _invalid(f(f"boxes.{i}"), f"box centre beyond {limits.max_box_distance_m} m",
                       limits.max_box_distance_m)
    bad = (b[:, 3:6] <= 0) | (b[:, 3:6] > limits.max_box_size_m)
    if bad.any():
        i = int(np.argwhere(bad)[0, 0])
        raise _invalid(f(f"boxes.{i}"), f"box sizes l, w, h must be in (0, {limits.max_box_size_m}] m",
                       limits.max_box_size_m)
    spin = np.abs(b[:, 6]) > math.tau
    if spin.any():
        i = int(np.argwhere(spin)[0, 0])
        raise _invalid(f(f"boxes.{i}"), "box yaw must be in [-2 pi, 2 pi] radians", round(math.tau, 6))


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_MAX_CHUNK = 2**31 - 1  # the PNG specification's largest chunk length


def check_png(data: bytes, size_px: int, limits: Limits, field: str = "png") -> None:
    """The whole PNG structure, before any decoder sees it (raises WireError 422 naming ``field``).

    Signature; every chunk inside the file with a correct CRC; IHDR first: 8-bit greyscale, not interlaced,
    square, at most ``limits.max_image_px`` and exactly ``size_px`` a side; consecutive IDAT chunks whose total
    is neither absurdly small (decoded/compressed over ``limits.max_png_ratio``) nor larger than an uncompressed
    image needs; no unknown critical chunk; IEND last, nothing after it. Then the image data is inflated with an
    output bound of the size the header implies (a decompression bomb stops there) and must fill it exactly,
    with a valid filter byte on every row."""
    if len(data) < 8 + 25 + 12 or data[:8] != _PNG_SIGNATURE:
        raise _invalid(field, "not a PNG file (bad signature or truncated)")
    pos, chunks, idat, idat_total, idat_closed, ended = 8, 0, [], 0, False, False
    width = height = 0
    while pos < len(data):
        if pos + 12 > len(data):
            raise _invalid(field, f"truncated PNG chunk at byte {pos}")
        length, ctype = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 12 + length
        if length > _MAX_CHUNK or end > len(data):
            raise _invalid(field, f"PNG chunk {ctype!r} at byte {pos} runs past the end of the file")
        body = data[pos + 8:pos + 8 + length]
        if zlib.crc32(body, zlib.crc32(ctype)) != struct.unpack(">I", data[end - 4:end])[0]:
            what = ctype.decode("latin-1") if ctype.isalpha() else repr(ctype)
            raise _invalid(field, f"PNG {what} checksum mismatch")
        chunks += 1
        if chunks > limits.max_png_chunks:
            raise _invalid(field, f"more than {limits.max_png_chunks} PNG chunks", limits.max_png_chunks)
        if chunks == 1:
            if ctype != b"IHDR" or length != 13:
                raise _invalid(field, "PNG must start with a 13-byte IHDR chunk")
            width, height = _check_ihdr(body, size_px, limits, field)
        elif ctype == b"IDAT":
            if idat_closed:
                raise _invalid(field, "PNG IDAT chunks must be consecutive")
            idat.append(body)
            idat_total += length
        elif ctype == b"IEND":
            ended = True
            pos = end
            break
        elif ctype == b"IHDR" or not ctype[:1].islower():
            raise _invalid(field, f"unexpected critical PNG chunk {ctype!r} (a greyscale PNG has IHDR, IDAT, IEND)")
        if idat and ctype != b"IDAT":
            idat_closed = True
        pos = end
    if not ended or pos != len(data):
        raise _invalid(field, "PNG must end with its IEND chunk" if not ended else "bytes after the PNG's IEND")
    _check_image_data(idat, idat_total, width, height, limits, field)


def _check_ihdr(body: bytes, size_px: int, limits: Limits, field: str) -> tuple[int, int]:
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", body)
    if width > limits.max_image_px or height > limits.max_image_px:
        raise _invalid(field, f"image {width}x{height} px exceeds {limits.max_image_px} px", limits.max_image_px)
    if depth != 8 or colour != 0:
        raise _invalid(field, f"PNG must be 8-bit greyscale (bit depth 8, colour type 0), got depth {depth}, "
                              f"colour type {colour}")
    if compression != 0 or filtering != 0 or interlace != 0:
        raise _invalid(field, f"PNG compression, filter and interlace methods must be 0 (got {compression}, "
                              f"{filtering}, {interlace})")
    if (width, height) != (size_px, size_px):
        raise _invalid(field, f"image is {width}x{height} px but bev.range_m and bev.resolution_m imply "
                              f"{size_px}x{size_px}")
    return width, height


def _check_image_data(idat: list[bytes], total: int, width: int, height: int, limits: Limits, field: str) -> None:
    expected = height * (width + 1)  # one filter byte per row, one byte per pixel
    if total == 0:
        raise _invalid(field, "PNG has no image data (IDAT)")
    if expected / total > limits.max_png_ratio:
        raise _invalid(field, f"{total} bytes of image data cannot hold a {width}x{height} image (ratio "
                              f"{expected / total:.0f} over {limits.max_png_ratio:g})", limits.max_png_ratio)
    stored_max = expected + 5 * (expected // 16383 + 1) + 6  # deflate's uncompressed blocks plus zlib framing
    if total > stored_max:
        raise _invalid(field, f"{total} bytes of image data for a {width}x{height} image, more than the "
                              f"{stored_max} an uncompressed one takes", stored_max)
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(b"".join(idat), expected + 1)  # output bound: a bomb stops here
    except zlib.error as e:
        raise _invalid(field, f"corrupt PNG image data: {e}") from None
    if len(raw) != expected or not inflater.eof or inflater.unconsumed_tail or inflater.unused_data:
        raise _invalid(field, f"PNG image data does not inflate to exactly the {expected} bytes its header "
                              f"implies", expected)
    if expected and int(np.frombuffer(raw, np.uint8)[::width + 1].max()) > 4:
        raise _invalid(field, "PNG row filter types must be 0-4")


# ---- JSON Schema files (proto_schemas/) -------------------------------------------------------------------------
def json_schemas() -> dict[str, dict]:
    """Each wire model's JSON Schema (file name stem -> schema), as committed in proto_schemas/."""
    out = {}
    for name, cls in WIRE_MODELS.items():
        schema = cls.model_json_schema()
        out[name] = {"$schema": "https://json-schema.org/draft/2020-12/schema",
                     "$id": f"bb-align/wire/v{SCHEMA_VERSION}/{name}.schema.json", **schema}
    return out


def write_json_schemas(directory) -> list:
    """Write ``<name>.schema.json`` files; returns their paths."""
    from pathlib import Path

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, schema in json_schemas().items():
        p = directory / f"{name}.schema.json"
        p.write_text(json.dumps(schema, indent=2, sort_keys=True) + "\n")
        paths.append(p)
    return paths
