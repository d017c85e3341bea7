"""Encodings (msgpack, JSON) and the loaders every message from either door goes through.

:func:`load_frame` / :func:`load_align_request`: size first, then decoding, the signature (on the raw payload
bytes, before the frame is decoded), the fields, and :func:`bb_align.protocol.validation.validate_frame`. All
failures raise :class:`WireError` with the offending field, the limit and an HTTP status; nothing else escapes.
"""

from __future__ import annotations

import hmac
import json
import math
from typing import Any

import msgpack
from pydantic import BaseModel, ValidationError

from .errors import WireError, invalid, too_large
from .identity import FRAME_DOMAIN, RESULT_DOMAIN, SIGNATURE_BYTES, Credential, IdentityError, TrustStore
from .limits import FLEET_KEY_ID, Limits, limit_env
from .models import BOX_FIELDS, JSON, MSGPACK, SCHEMA_VERSION, AlignRequest, Frame, Refusal, Result, Signed
from .signatures import MAC_BYTES, AuthError, Keyring, frame_mac, signer_key
from .validation import validate_frame


def pack(model: BaseModel) -> bytes:
    """A wire model -> msgpack bytes (PNG as bin). An envelope leaves out its absent certificate."""
    return msgpack.packb(model.model_dump(mode="python", exclude_none=isinstance(model, Signed)), use_bin_type=True)


def to_json(model: BaseModel) -> bytes:
    """A wire model -> JSON bytes (PNG as base64)."""
    return model.model_dump_json(exclude_none=isinstance(model, Signed)).encode()


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


def sign(
    payload: bytes,
    key: bytes | str | Credential,
    key_id: str = FLEET_KEY_ID,
    encoding: str | None = None,
    domain: bytes = FRAME_DOMAIN,
) -> bytes:
    """Wrap an encoded frame (or, with ``domain=RESULT_DOMAIN``, an answer) in a Signed envelope of the same
    encoding (JSON when the payload is JSON). ``key``: a vehicle's Credential (Ed25519; the key id is its vehicle
    id, ``key_id`` is ignored) or an HMAC secret named by ``key_id``."""
    encoding = encoding or (JSON if payload[:1] == b"{" else MSGPACK)
    if isinstance(key, Credential):
        env = Signed(
            key_id=key.vehicle_id,
            alg="ed25519",
            mac=key.sign(domain, payload),
            cert=key.certificate_bytes,
            payload=payload,
        )
    else:
        env = Signed(key_id=key_id, mac=frame_mac(key, key_id, payload, domain), payload=payload)
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


def _pairs(pairs) -> dict:
    """object_pairs_hook of both decoders: map keys must be strings, each once (no 'last one wins')."""
    out: dict = {}
    for k, v in pairs:
        if not isinstance(k, str):
            raise ValueError(f"map keys must be strings, got a {type(k).__name__} key")
        if k in out:
            raise ValueError(f"duplicate map key {k!r}")
        out[k] = v
    return out


def _unpack(data: bytes, encoding: str, limits: Limits) -> dict:
    """Bytes -> a plain dict, refusing oversized or undecodable messages before any model is built."""
    if len(data) > limits.max_message_bytes:
        raise too_large("message", len(data), limits.max_message_bytes, limit_env("max_message_bytes"))
    try:
        if encoding == MSGPACK:
            obj = msgpack.unpackb(
                data,
                raw=False,
                strict_map_key=True,
                max_bin_len=limits.max_message_bytes,
                max_str_len=limits.max_message_bytes,
                max_array_len=2 * limits.max_boxes + 64,
                max_map_len=64,
                max_ext_len=0,
                object_pairs_hook=_pairs,
            )
        elif encoding == JSON:
            obj = json.loads(data, object_pairs_hook=_pairs)
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
        raise invalid(loc(errs[0]) or where or "message", detail) from None
    except (RecursionError, MemoryError) as e:  # absurd nesting that the decoder let through
        raise WireError(400, "undecodable", f"{where or 'message'}: {type(e).__name__}") from None


def _precheck(obj: dict, limits: Limits, f) -> None:
    """Counts that must be refused before a model is built for them (e.g. 10^6 boxes), and non-finite box
    numbers, refused here with the box component named (the model would only say 'finite number')."""
    for name in ("boxes", "scores"):
        v = obj.get(name)
        if isinstance(v, (list, tuple)) and len(v) > limits.max_boxes:
            raise invalid(
                f(name), f"{len(v)} {name} exceed {limits.max_boxes}", limits.max_boxes, limit_env("max_boxes")
            )
    boxes = obj.get("boxes")
    for i, row in enumerate(boxes if isinstance(boxes, list) else ()):
        for j, v in enumerate(row[: len(BOX_FIELDS)] if isinstance(row, list) else ()):
            if isinstance(v, float) and not math.isfinite(v):
                what = "any finite angle in radians is taken" if BOX_FIELDS[j] == "yaw" else "numbers must be finite"
                raise invalid(f(f"boxes.{i}.{j}"), f"box {i}'s {BOX_FIELDS[j]} is {v}: {what}")


def _frame_from(
    obj: Any,
    limits: Limits,
    encoding: str,
    keyring: Keyring | None,
    now: float | None,
    where: str = "",
    inflate_png: bool = True,
) -> Frame:
    """A decoded map (a Frame, or a Signed envelope holding one) -> a checked Frame."""
    f = lambda name: f"{where}.{name}" if where else name  # noqa: E731
    if not isinstance(obj, dict):
        raise invalid(where or "message", f"must be a map (a Frame or a Signed frame), got {type(obj).__name__}")
    signer = key = None
    if _is_envelope(obj):
        env = _envelope(obj, where)
        if keyring is not None:
            try:
                signer = keyring.verify_signed(env.key_id, env.alg, env.mac, env.payload, env.cert, now)
                key = signer_key(env.alg, env.key_id, env.cert)
            except AuthError as e:
                if keyring.required or not e.unknown:
                    raise WireError(e.status, e.error, e.detail, f("mac"), env.alg) from None
        obj = _unpack(env.payload, encoding, limits)
        if _is_envelope(obj):
            raise invalid(f("payload"), "a signed payload must be a Frame, not another envelope")
    elif keyring is not None and keyring.required:
        raise WireError(
            401,
            "unauthenticated",
            "frames must be signed (a Signed envelope: ed25519 with a vehicle certificate, or hmac-sha256; see "
            "docs/security.md)",
            where or "message",
            ", ".join(keyring.algorithms),
        )
    _precheck(obj, limits, f)
    frame: Frame = _model(Frame, obj, where)
    validate_frame(frame, limits, where, now=now, inflate_png=inflate_png)
    if signer is not None:
        try:
            keyring.authorize(signer, frame.vehicle_id)
        except AuthError as e:
            raise WireError(e.status, e.error, e.detail, f("vehicle_id"), signer) from None
        frame._signer_key = key
    return frame


def _envelope(obj: dict, where: str = "") -> Signed:
    """A Signed model whose signature has the length its algorithm makes (and a certificate for ed25519)."""
    env: Signed = _model(Signed, obj, where)
    f = lambda name: f"{where}.{name}" if where else name  # noqa: E731
    want = SIGNATURE_BYTES if env.alg == "ed25519" else MAC_BYTES
    if len(env.mac) != want:
        raise invalid(f("mac"), f"{env.alg} signatures are {want} bytes, got {len(env.mac)}", want)
    if (env.cert is None) != (env.alg != "ed25519"):
        raise invalid(f("cert"), "ed25519 envelopes carry the signer's certificate; hmac-sha256 ones none")
    return env


def peek_signed(data: bytes, limits: Limits) -> Signed | None:
    """The Signed envelope of a raw message, if it is one (its payload not decoded); None for anything else.
    Cheap: what a door does before a message may take a place in an authenticated queue."""
    try:
        obj = _unpack(data, JSON if data[:1] == b"{" else MSGPACK, limits)
        return _envelope(obj) if _is_envelope(obj) else None
    except WireError:
        return None


def load_frame(
    data: bytes,
    limits: Limits,
    encoding: str = MSGPACK,
    *,
    keyring: Keyring | None = None,
    now: float | None = None,
    inflate_png: bool = True,
) -> Frame:
    """Untrusted bytes (a Frame or a Signed frame) -> a checked Frame (raises WireError, nothing else).

    ``keyring``: verify signatures (and refuse unsigned frames when it requires them); ``now``: the receiver's
    clock (time.time()) for the stamp window; without it only the absolute stamp range is checked.
    ``inflate_png=False``: the PNG's image data is not inflated here but when the frame is decoded
    (``Frame.bev_image``), for a receiver that may replace the frame unread (``check_png``)."""
    return _frame_from(_unpack(data, encoding, limits), limits, encoding, keyring, now, inflate_png=inflate_png)


def load_align_request(
    data: bytes, limits: Limits, encoding: str = MSGPACK, *, keyring: Keyring | None = None, now: float | None = None
) -> AlignRequest:
    """Untrusted bytes -> an AlignRequest holding checked Frames (raises WireError)."""
    obj = _unpack(data, encoding, limits)
    extra = sorted(set(obj) - {"schema_version", "peer", "ego"}, key=str)  # keys are str (_pairs); key=str anyway
    if extra:
        raise invalid(str(extra[0]), "Extra inputs are not permitted")
    version = obj.get("schema_version", SCHEMA_VERSION)
    if type(version) is not int or version != SCHEMA_VERSION:  # strict: True is not 1
        raise invalid("schema_version", f"Input should be {SCHEMA_VERSION}", SCHEMA_VERSION)
    if "peer" not in obj:
        raise invalid("peer", "Field required")
    peer = _frame_from(obj["peer"], limits, encoding, keyring, now, "peer")
    ego = None if obj.get("ego") is None else _frame_from(obj["ego"], limits, encoding, keyring, now, "ego")
    return AlignRequest(peer=peer, ego=ego)


class AnswerTrust:
    """What a car trusts for the service's answers: ``trust`` (fleet authorities; the answer must be signed by the
    ego's certificate, Ed25519) and/or ``fleet_key`` (HMAC-SHA256 with the shared fleet key: any fleet member
    could forge it, documented in docs/security.md). ``ego_id``: the only ego accepted (else the Result's own
    ego_id, which must be the signer's)."""

    def __init__(
        self, trust: TrustStore | None = None, fleet_key: bytes | str | None = None, ego_id: str | None = None
    ):
        if trust is None and fleet_key is None:
            raise ValueError("AnswerTrust needs a fleet authority (trust) or the fleet key")
        self.trust, self.ego_id = trust, ego_id
        self._fleet = None if fleet_key is None else (fleet_key.encode() if isinstance(fleet_key, str) else fleet_key)

    def signer(self, env: Signed, now: float | None = None) -> str:
        """The vehicle id (ed25519) or ``"fleet"`` (hmac) that signed an answer; WireError 401 otherwise."""
        if env.alg == "ed25519" and self.trust is not None:
            try:
                return self.trust.verify(RESULT_DOMAIN, env.key_id, env.payload, env.mac, env.cert or b"", now)
            except IdentityError as e:
                raise WireError(e.status, "unauthenticated", f"answer: {e.detail}", "mac", "ed25519") from None
        if env.alg == "hmac-sha256" and self._fleet is not None and env.key_id == FLEET_KEY_ID:
            if hmac.compare_digest(frame_mac(self._fleet, FLEET_KEY_ID, env.payload, RESULT_DOMAIN), env.mac):
                return FLEET_KEY_ID
            raise WireError(401, "unauthenticated", "answer: the HMAC does not match the fleet key", "mac", env.alg)
        raise WireError(401, "unauthenticated", f"answer signed with {env.alg} by {env.key_id!r}: not trusted here")


def sign_result(
    result: Result, key: bytes | str | Credential | None, encoding: str = MSGPACK, key_id: str = FLEET_KEY_ID
) -> bytes:
    """An answer as sent: the encoded Result, in a Signed envelope (RESULT_DOMAIN) when the service has a key."""
    data = to_json(result) if encoding == JSON else pack(result)
    return data if key is None else sign(data, key, key_id, encoding, RESULT_DOMAIN)


def load_answer(data: bytes, trust: AnswerTrust | None = None) -> Result | Refusal:
    """msgpack or JSON bytes (a Result or a Refusal, signed or not) -> the answer (a JSON object starts with '{',
    never a msgpack map). A Refusal is what a car's results key carries when the service refused one of its
    signed frames (a map with ``refused``). With ``trust``: the answer must be signed by the ego it names (or
    the fleet key), else WireError 401 (unsigned, forged) or 403 (signed by another vehicle than its ego_id)."""
    encoding = JSON if data[:1] == b"{" else MSGPACK
    limits = Limits()
    obj = _unpack(data, encoding, limits)
    signer = None
    if _is_envelope(obj):
        env = _envelope(obj)
        signer = None if trust is None else trust.signer(env)
        obj = _unpack(env.payload, encoding, limits)
    elif trust is not None:
        raise WireError(401, "unauthenticated", "the answer is not signed; refused (verification is on)", "result")
    answer: Result | Refusal = _model(Refusal if "refused" in obj else Result, obj)
    if trust is not None:
        if signer != FLEET_KEY_ID and answer.ego_id != signer:
            raise WireError(403, "forbidden", f"answer of {answer.ego_id!r} signed by {signer!r}", "ego_id", signer)
        if trust.ego_id is not None and answer.ego_id != trust.ego_id:
            raise WireError(403, "forbidden", f"answer from {answer.ego_id!r}, expected {trust.ego_id!r}", "ego_id")
    return answer


def load_result(data: bytes, trust: AnswerTrust | None = None) -> Result:
    """Like :func:`load_answer`, for where only a Result can come (REST answers, query replies)."""
    answer = load_answer(data, trust)
    if isinstance(answer, Refusal):
        raise invalid("refused", "expected a Result, got a Refusal")
    return answer


def peek_seq_stamp(data: bytes, limits: Limits) -> tuple[int | None, float | None]:
    """The seq and stamp a raw frame (or the frame inside a Signed envelope) claims, when they can be read, for
    telling a sender which of its frames was refused; (None, None) otherwise. Never raises."""
    return peek_frame(data, limits)[1:]


def peek_frame(data: bytes, limits: Limits) -> tuple[str | None, int | None, float | None]:
    """(vehicle_id, seq, stamp) a raw frame (or the frame inside a Signed envelope) claims, each None when it
    cannot be read: what binds an answer to the frame it answers. Never raises."""
    try:
        encoding = JSON if data[:1] == b"{" else MSGPACK
        obj = _unpack(data, encoding, limits)
        if _is_envelope(obj):
            obj = _unpack(_envelope(obj).payload, encoding, limits)
    except WireError:
        return None, None, None
    vid, seq, stamp = obj.get("vehicle_id"), obj.get("seq"), obj.get("stamp")
    seq_ok = type(seq) is int and 0 <= seq < 2**63
    stamp_ok = type(stamp) in (int, float) and math.isfinite(stamp) and stamp >= 0
    return (vid if isinstance(vid, str) else None), (seq if seq_ok else None), (float(stamp) if stamp_ok else None)
