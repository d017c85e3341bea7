"""Wire messages between cars and the ego-side service (pydantic models; JSON Schemas in proto_schemas/).

A peer sends one :class:`Frame` per LiDAR sweep (a PNG BV height image, what is needed to map its pixels to
metres, its object boxes and optionally its reported pose). The service answers with a :class:`Result`.
Messages are msgpack maps (PNG as ``bin``); REST also takes JSON with the PNG as a base64 string. A signed frame
travels in a :class:`Signed` envelope (key id, HMAC-SHA256, the frame's encoded bytes; see
:mod:`bb_align.protocol.signatures`).
"""

from __future__ import annotations

import base64
import binascii
import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    PrivateAttr,
    WithJsonSchema,
)

from bb_align.engine.bev import BevImage, decode_png, image_size_px
from bb_align.engine.config import BevConfig
from bb_align.engine.geometry import rotation_rpy

from .errors import invalid
from .identity import MAX_CERT_BYTES, SIGNATURE_BYTES
from .limits import FLEET_KEY_ID, VEHICLE_ID_PATTERN, Limits
from .png import check_png
from .signatures import MAC_BYTES

SCHEMA_VERSION = 1


MSGPACK = "application/msgpack"


JSON = "application/json"


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
    WithJsonSchema(
        {
            "type": "string",
            "contentEncoding": "base64",
            "contentMediaType": "image/png",
            "description": "PNG file, 8-bit greyscale; msgpack: bin, JSON: base64 string",
        }
    ),
]


def _exact_int(v: Any) -> Any:
    if isinstance(v, bool):  # Literal[1] would take true (True == 1): not on the air
        raise ValueError("must be the integer 1, not a boolean")
    return v


Version = Annotated[Literal[1], BeforeValidator(_exact_int)]


def wrap_yaw(yaw: float) -> float:
    """Radians -> [-pi, pi). math.remainder is exact (no rounding), so 7.0 and 7.0 - 2 pi give the same float:
    a dataset's yaw in [0, 2 pi) or beyond reaches the engine exactly as its wrapped twin would."""
    wrapped = math.remainder(yaw, math.tau)
    return -math.pi if wrapped >= math.pi else wrapped


def _wrap_box_yaw(box: list[float]) -> list[float]:
    return [*box[:6], wrap_yaw(box[6])]


BOX_FIELDS = ("x", "y", "z", "l", "w", "h", "yaw")  # the order of a box row (engine.boxes has the same)


BOX_DESCRIPTION = (
    "[x, y, z, l, w, h, yaw]: centre (metres, sensor frame), length along the heading, width, height, heading "
    "(yaw: any finite angle, radians, wrapped into [-pi, pi) on receipt)"
)


Box = Annotated[
    list[float],
    Field(min_length=7, max_length=7, description=BOX_DESCRIPTION),
    AfterValidator(_wrap_box_yaw),
]


class _Wire(BaseModel):
    # strict: no coercion on the air ("1" is not an int, true is not 1, bytes are not a str); ints are floats
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)


class BevMeta(_Wire):
    """How the PNG's pixels map to metres (bb_align.engine.bev): the sensor at the image centre, rows along -x,
    columns along -y; a pixel value v > 0 is a height above ground of clearance + (v-1)/254 (max - clearance)."""

    resolution_m: float = Field(gt=0.01, le=5, description="cell size, metres per pixel")
    range_m: float = Field(gt=0, le=250, description="half width of the square image, metres")
    mode: Literal["max_height", "slices"] = "max_height"
    ground_clearance_m: float = Field(0.3, ge=0, le=5, description="must be below max_height_m")
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
    def from_matrix(cls, T: np.ndarray) -> Pose:
        T = np.asarray(T, dtype=float)
        R = T[:3, :3]
        pitch = math.asin(float(np.clip(-R[2, 0], -1.0, 1.0)))
        return cls(
            x=float(T[0, 3]),
            y=float(T[1, 3]),
            z=float(T[2, 3]),
            roll=math.atan2(R[2, 1], R[2, 2]),
            pitch=pitch,
            yaw=math.atan2(R[1, 0], R[0, 0]),
        )


class Frame(_Wire):
    """One car's LiDAR sweep as sent on the air (Zenoh ``<prefix>/frames/<vehicle_id>`` or REST)."""

    schema_version: Version = SCHEMA_VERSION
    vehicle_id: str = Field(pattern=VEHICLE_ID_PATTERN)
    seq: int = Field(0, ge=0, le=2**63 - 1, description="sender's frame counter")
    stamp: float = Field(ge=0, description="capture time, seconds (the cars' common clock)")
    png: PngBytes
    bev: BevMeta
    boxes: list[Box] = Field(
        default_factory=list,
        description="rows [x, y, z, l, w, h, yaw], sensor frame, "
        "metres and radians; (x, y, z) is the box centre, l along the heading; yaw: any finite angle, radians, "
        "wrapped into [-pi, pi)",
    )
    scores: list[Annotated[float, Field(ge=0, le=1)]] | None = Field(None, description="one per box")
    pose: Pose | None = Field(None, description="reported T_world_sensor (GNSS-grade); optional")
    odometry: Pose | None = Field(
        None,
        description="the car's own odometry pose T_odom_sensor (LiDAR/wheel/IMU odometry: locally accurate, slowly "
        "drifting, in the car's own odometry frame; optional). With it on both the ego's and the peer's frames the "
        "service tracks the offset between the two odometry frames, which holds where the images are weak",
    )
    num_points: int | None = Field(None, ge=0, description="points in the raw sweep (bandwidth accounting)")
    # Which key signed it (set by the loader once the signature verified; not on the wire): the receiver keeps one
    # replay window per sender and key, so a stale key stamping ahead cannot lock a rotated key out.
    _signer_key: bytes | None = PrivateAttr(None)

    def __eq__(self, other: object) -> bool:  # what the frame says, whoever signed it
        return isinstance(other, Frame) and self.__dict__ == other.__dict__

    __hash__ = None  # lists inside: never hashable

    @property
    def signer_key(self) -> bytes | None:
        """The verified signer's key: its Ed25519 public key, or ``hmac:<key id>``; None when unsigned."""
        return self._signer_key

    def check_image(self, limits: Limits | None = None) -> int:
        """The whole PNG checked (structure, bounded inflate: ``check_png``) without decoding it; its side in
        pixels. Raises WireError 422 naming ``png``."""
        n = image_size_px(BevConfig(range_m=self.bev.range_m, resolution_m=self.bev.resolution_m))
        check_png(self.png, n, limits or Limits(), "png")
        return n

    def bev_image(self, limits: Limits | None = None) -> BevImage:
        """Decode the PNG into the engine's BevImage. The PNG's structure is checked again first (cheap), so
        OpenCV never sees an unchecked file, whoever built this Frame."""
        n = self.check_image(limits)
        try:
            image = decode_png(self.png)
        except ValueError as e:
            raise invalid("png", str(e)) from None
        if image.shape != (n, n):
            raise invalid("png", f"decoded image is {image.shape}, the header and bev say ({n}, {n})")
        return BevImage(image=image, **self.bev.model_dump())

    def boxes_array(self) -> np.ndarray:
        return np.asarray(self.boxes, dtype=np.float64).reshape(-1, 7)


class Signed(_Wire):
    """A signed frame (or a signed answer): the message's own encoded bytes (msgpack, or JSON inside a JSON
    envelope) with an Ed25519 signature by the sender's certified key (``alg: "ed25519"``, ``cert``: its vehicle
    certificate, bb_align.protocol.identity) or an HMAC-SHA256 made with the key ``key_id`` names
    (bb_align.protocol.signatures): ``"fleet"`` or the sender's vehicle id."""

    schema_version: Version = SCHEMA_VERSION
    key_id: str = Field(
        pattern=VEHICLE_ID_PATTERN,
        description=f"ed25519: the signer's vehicle id (its certificate's); hmac-sha256: {FLEET_KEY_ID!r} or the "
        "sender's vehicle id",
    )
    alg: Literal["hmac-sha256", "ed25519"] = "hmac-sha256"
    mac: Annotated[
        bytes,
        BeforeValidator(_b64_if_str),
        Field(min_length=MAC_BYTES, max_length=SIGNATURE_BYTES),
        _B64_JSON,
        WithJsonSchema(
            {
                "type": "string",
                "contentEncoding": "base64",
                "description": "hmac-sha256: HMAC-SHA256(key, domain key_id 0x00 payload), 32 bytes; ed25519: "
                "Ed25519(vehicle key, domain key_id 0x00 payload), 64 bytes. domain: 'bb-align/frame/v1' 0x00 "
                "(frames) or 'bb-align/result/v1' 0x00 (answers); msgpack: bin, JSON: base64",
            }
        ),
    ]
    cert: (
        Annotated[
            bytes,
            BeforeValidator(_b64_if_str),
            Field(max_length=MAX_CERT_BYTES),
            _B64_JSON,
            WithJsonSchema(
                {
                    "type": "string",
                    "contentEncoding": "base64",
                    "description": "ed25519: the signer's vehicle certificate (bb_align.protocol.identity), issued "
                    "by a fleet authority the receiver trusts; absent for hmac-sha256",
                }
            ),
        ]
        | None
    ) = None
    payload: Annotated[
        bytes,
        BeforeValidator(_b64_if_str),
        Field(min_length=1),
        _B64_JSON,
        WithJsonSchema(
            {
                "type": "string",
                "contentEncoding": "base64",
                "description": "the encoded Frame, in the envelope's own encoding; msgpack: bin, JSON: base64",
            }
        ),
    ]


class AlignRequest(_Wire):
    """REST POST /v1/align: a peer frame and optionally the ego frame (else the service's cached one); each
    a Frame or a Signed frame (the service resolves envelopes: a loaded request holds Frames)."""

    schema_version: Version = SCHEMA_VERSION
    peer: Frame | Signed
    ego: Frame | Signed | None = None


class Result(_Wire):
    """T_ego_peer for one peer frame (Zenoh ``<prefix>/poses/<ego_id>/<peer_id>``, query replies, REST)."""

    schema_version: Version = SCHEMA_VERSION
    ego_id: str
    peer_id: str
    peer_seq: int
    peer_stamp: float
    ego_seq: int | None = Field(None, description="the ego frame used (None: none was available)")
    ego_stamp: float | None = None
    ego_skew_s: float | None = Field(None, description="peer_stamp - ego_stamp")
    success: bool
    reason: str | None = Field(
        None,
        description="why not, when success is false: an engine reason (bb_align.engine.FailureReason, e.g. "
        "too_few_inliers_bv) or a service reason (no_ego_frame, stale_ego_frame)",
    )
    yaw_deg: float | None = Field(None, description="T_ego_peer's yaw, degrees CCW")
    tx: float | None = Field(None, description="T_ego_peer's x translation, metres")
    ty: float | None = Field(None, description="T_ego_peer's y translation, metres")
    T_ego_peer: list[Annotated[list[float], Field(min_length=4, max_length=4)]] | None = Field(
        None, min_length=4, max_length=4, description="4x4 row-major, maps peer sensor points into the ego frame"
    )
    inliers_bv: int = 0
    inliers_box: int = 0
    matches_bv: int = 0
    box_pairs: int = 0
    confidence: float = 0.0
    stage2_applied: bool = False
    covariance: list[Annotated[list[float], Field(min_length=3, max_length=3)]] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="3x3 covariance of (yaw rad, tx m, ty m) of T_ego_peer, row-major, from the dense refinement "
        "(None when not computed, e.g. no refinement or a failure before it); a success's covariance puts the truth "
        "within the engine's answer.max_error_m / max_error_deg with at least answer.confidence",
    )
    prior_used: bool = Field(False, description="roll, pitch, tz taken from the two reported poses")
    source: Literal["acquisition", "tracking", "stream", "prediction"] | None = Field(
        None,
        description="acquisition: the full two-stage method ran on this frame; tracking: the dense refinement from "
        "the track's prediction, fused with it; stream: no evidence of its own this frame (or not measured: the "
        "service was behind its frames, unmeasured_after_s), the stream's recent frames carried to it by both cars' "
        "odometry (track.stream_coast_s); prediction: no usable measurement this "
        "frame, the track's prediction, never a success (None: tracking off)",
    )
    track_state: Literal["acquiring", "tracking", "lost"] | None = Field(
        None, description="the peer's track after this frame (None: tracking off)"
    )
    track_event: str | None = Field(None, description="why the track's state changed on this frame, if it did")
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

    error: Literal[
        "too_large",
        "undecodable",
        "invalid",
        "unsupported_media_type",
        "unauthenticated",
        "forbidden",
        "replayed",
        "overloaded",
        "timeout",
        "unavailable",
    ]
    detail: str
    field: str | None = Field(None, description="the offending field, dotted path")
    limit: float | int | str | None = Field(None, description="the limit that was exceeded")
    setting: str | None = Field(
        None,
        description="the service setting that governs the refusal, as its environment variable (e.g. "
        "BBALIGN_LIMITS__MAX_STAMP_AGE_S); None when no setting does",
    )


class Refusal(_Wire):
    """A frame the ego service refused, told to its sender on the sender's results key
    (``<prefix>/poses/<ego_id>/<peer_id>``, signed like a Result) when the frame came over Zenoh pub/sub with a
    valid signature for that sender. Unauthenticated messages are never answered (no amplification)."""

    schema_version: Version = SCHEMA_VERSION
    ego_id: str
    peer_id: str = Field(description="the sender: the key's last chunk, which the frame's signature was checked for")
    peer_seq: int | None = Field(None, description="the refused frame's seq, when it could be read")
    peer_stamp: float | None = Field(None, description="the refused frame's stamp, when it could be read")
    status: int = Field(description="the HTTP status the same refusal gets over REST (409 replayed, 422 invalid, ...)")
    refused: ErrorBody


WIRE_MODELS: dict[str, type[BaseModel]] = {
    "frame": Frame,
    "signed": Signed,
    "align_request": AlignRequest,
    "result": Result,
    "error": ErrorBody,
    "refusal": Refusal,
}
