"""The wire protocol between cars and the ego-side service: models, encodings, validation, signatures, limits.

Imports no server code and none of the engine's stages (only its BV image type and PNG codec), so a sender
(``bb_align_client``) needs nothing else. Every message from either door goes through :func:`load_frame` /
:func:`load_align_request`; every refusal is a :class:`WireError` naming the field and the limit.
"""

from .codec import (
    AnswerTrust,
    is_signed,
    json_align_request,
    load_align_request,
    load_answer,
    load_frame,
    load_result,
    pack,
    pack_align_request,
    peek_frame,
    peek_seq_stamp,
    peek_signed,
    sign,
    sign_result,
    to_json,
)
from .errors import WireError
from .identity import (
    FRAME_DOMAIN,
    RESULT_DOMAIN,
    Certificate,
    Credential,
    FleetAuthority,
    IdentityError,
    TrustStore,
)
from .keys import align_key, frames_key, poses_key
from .limits import FLEET_KEY_ID, VEHICLE_ID_PATTERN, Limits, limit_env, setting_env
from .models import (
    JSON,
    MSGPACK,
    SCHEMA_VERSION,
    WIRE_MODELS,
    AlignRequest,
    BevMeta,
    ErrorBody,
    Frame,
    Pose,
    Refusal,
    Result,
    Signed,
    wrap_yaw,
)
from .png import check_png
from .revocations import RevocationList, fingerprint
from .schemas import json_schemas, write_json_schemas
from .signatures import AuthError, Keyring, frame_mac
from .validation import validate_frame
from .zenoh_config import ZenohSettings, ZenohTls

__all__ = [
    "FRAME_DOMAIN",
    "RESULT_DOMAIN",
    "AnswerTrust",
    "Certificate",
    "Credential",
    "FleetAuthority",
    "IdentityError",
    "RevocationList",
    "TrustStore",
    "sign_result",
    "FLEET_KEY_ID",
    "JSON",
    "MSGPACK",
    "SCHEMA_VERSION",
    "VEHICLE_ID_PATTERN",
    "WIRE_MODELS",
    "AlignRequest",
    "AuthError",
    "BevMeta",
    "ErrorBody",
    "Frame",
    "Keyring",
    "Limits",
    "Pose",
    "Refusal",
    "Result",
    "Signed",
    "WireError",
    "ZenohSettings",
    "ZenohTls",
    "align_key",
    "check_png",
    "frame_mac",
    "frames_key",
    "is_signed",
    "json_align_request",
    "json_schemas",
    "load_align_request",
    "load_answer",
    "load_frame",
    "load_result",
    "pack",
    "pack_align_request",
    "limit_env",
    "peek_frame",
    "peek_seq_stamp",
    "peek_signed",
    "poses_key",
    "setting_env",
    "sign",
    "to_json",
    "fingerprint",
    "validate_frame",
    "wrap_yaw",
    "write_json_schemas",
]
