"""Peer authentication: an Ed25519 signature with the sender's own certified key (bb_align.protocol.identity), or
the simpler HMAC-SHA256 with the fleet key or a per-vehicle key.

A signed frame travels in a :class:`bb_align.protocol.models.Signed` envelope: ``key_id``, ``mac`` and ``payload`` (the
frame's own encoded bytes, msgpack or JSON). The MAC covers a domain tag, the key id and the payload::

    mac = HMAC-SHA256(key, b"bb-align/frame/v1\\0" + key_id.encode() + b"\\0" + payload)

so it is checked on the raw bytes before the frame is even decoded. The key id is ``"fleet"`` for the shared
fleet key, or a vehicle id for that vehicle's own key (the frame must then carry that vehicle id). Keys are the
UTF-8 bytes of the configured secret strings. Replays (a signed frame sent again) are refused by the service's
peer table (bb_align.server.peers), which keeps the newest (stamp, seq) accepted from each sender.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable

from .identity import FRAME_DOMAIN, Certificate, IdentityError, TrustStore
from .limits import FLEET_KEY_ID

DOMAIN = b"bb-align/frame/v1\x00"
MAC_BYTES = 32


def frame_mac(key: bytes | str, key_id: str, payload: bytes, domain: bytes = DOMAIN) -> bytes:
    """The 32-byte HMAC-SHA256 of one frame payload (or, with ``identity.RESULT_DOMAIN``, one answer) under
    ``key`` announced as ``key_id``."""
    key = key.encode() if isinstance(key, str) else key
    return hmac.new(key, domain + key_id.encode() + b"\x00" + payload, hashlib.sha256).digest()


def signer_key(alg: str, key_id: str, cert: bytes | None) -> bytes | None:
    """Which key an envelope claims to be signed with, read without verifying anything: the certificate's Ed25519
    public key, or ``hmac:<key id>``; None for a certificate that does not parse. A receiver keeps one replay
    window per sender and key (a rotated key is not locked out by the old one's stamps)."""
    if alg != "ed25519":
        return b"hmac:" + key_id.encode()
    try:
        return Certificate.from_bytes(cert or b"").public_key
    except IdentityError:
        return None


class AuthError(Exception):
    """Why a frame's signature is not accepted: ``status`` 401 (unsigned, unknown key, bad MAC) or 403."""

    def __init__(self, status: int, error: str, detail: str, unknown: bool = False):
        super().__init__(detail)
        self.status, self.error, self.detail = status, error, detail
        self.unknown = unknown  # the receiver has nothing to check it with (tolerated when signing is optional)


def fleet_space(fleet_ids) -> Callable[[str], bool]:
    """Whether a vehicle id lies in the fleet key's reserved id space: ``fleet_ids`` entries are ids, or prefixes
    ending in ``*`` (``"legacy-*"``)."""
    exact = frozenset(f for f in fleet_ids if not f.endswith("*"))
    prefixes = tuple(f[:-1] for f in fleet_ids if f.endswith("*"))
    return lambda vid: vid in exact or (bool(prefixes) and vid.startswith(prefixes))


class Keyring:
    """What a receiver accepts. ``keys``: HMAC key id (``"fleet"`` or a vehicle id) -> secret; ``trust``: the fleet
    authorities whose vehicle certificates are accepted (Ed25519); ``pinned``: vehicle id -> the only public key
    that may sign as it (the ego's own identity). ``required``: unsigned frames are refused.

    The fleet HMAC key is one secret shared by every car, so it cannot tell cars apart. It never signs as a
    vehicle with an identity of its own (a pinned key, its own HMAC key). With an authority as well (mixed mode)
    the two never share an id, whatever was seen on the air and across restarts: the fleet key signs only for the
    ids of ``fleet_ids`` (its reserved id space; ids or ``prefix*``; none by default) and a certificate for an id
    in that space (or for ``"fleet"`` itself) is refused. Without an authority ``fleet_ids`` (when given) limits
    the fleet key the same way."""

    def __init__(
        self,
        keys: dict[str, bytes | str],
        required: bool = True,
        *,
        trust: TrustStore | None = None,
        pinned: dict[str, bytes] | None = None,
        fleet_ids: list[str] | None = None,
    ):
        self.required = required
        self._keys: dict[str, bytes] = {kid: k.encode() if isinstance(k, str) else bytes(k) for kid, k in keys.items()}
        self.trust = trust
        self.pinned = dict(pinned or {})
        limited = fleet_ids is not None or trust is not None
        self.fleet_ids = list(fleet_ids or [])
        self._fleet_space = fleet_space(self.fleet_ids) if limited else (lambda vid: True)

    @property
    def algorithms(self) -> list[str]:
        return (["ed25519"] if self.trust is not None else []) + (["hmac-sha256"] if self._keys else [])

    def knows(self, key_id: str, alg: str) -> bool:
        """Whether a signature under this key id and algorithm could verify here (cheap; no crypto)."""
        return (alg == "ed25519" and self.trust is not None) or (alg == "hmac-sha256" and key_id in self._keys)

    def verify_signed(self, key_id: str, alg: str, mac: bytes, payload: bytes, cert: bytes | None, now=None) -> str:
        """Verify an envelope's signature on the raw payload; returns the vehicle id the signature is bound to
        (``"fleet"`` for the fleet key: no certificate can name it). Raises AuthError."""
        if alg == "ed25519":
            if self.trust is None:
                raise AuthError(
                    401, "unauthenticated", "this receiver trusts no fleet authority (ed25519)", unknown=True
                )
            try:
                vid = self.trust.verify(FRAME_DOMAIN, key_id, payload, mac, cert or b"", now)
            except IdentityError as e:
                raise AuthError(e.status, "unauthenticated" if e.status == 401 else "forbidden", e.detail) from None
            pinned = self.pinned.get(vid)
            if pinned is not None and self.trust.certificate(cert, now)[0].public_key != pinned:
                raise AuthError(403, "forbidden", f"{vid!r} has its own pinned key; this certificate is not it")
            if FLEET_KEY_ID in self._keys and self._fleet_space(vid):
                raise AuthError(
                    403, "forbidden", f"{vid!r} is in the fleet key's id space (auth.fleet_ids): no certificate for it"
                )
            return vid
        bound = self.verify(key_id, mac, payload)
        return FLEET_KEY_ID if bound is None else bound

    def authorize(self, signer: str, vehicle_id: str) -> None:
        """May ``signer`` (a vehicle id, or ``"fleet"``) sign a frame of ``vehicle_id``? Raises AuthError 403."""
        if vehicle_id == FLEET_KEY_ID:
            raise AuthError(403, "forbidden", f"{FLEET_KEY_ID!r} names the shared key, never a vehicle")
        if signer == FLEET_KEY_ID:
            if vehicle_id in self.pinned or vehicle_id in self._keys:
                raise AuthError(
                    403, "forbidden", f"{vehicle_id!r} has its own identity: the shared fleet key cannot sign as it"
                )
            if not self._fleet_space(vehicle_id):
                raise AuthError(
                    403,
                    "forbidden",
                    f"{vehicle_id!r} is not in the fleet key's id space (auth.fleet_ids {self.fleet_ids}): with a "
                    "fleet authority, only those ids may use the shared key",
                )
        elif signer != vehicle_id:
            raise AuthError(403, "forbidden", f"signed by {signer!r} but claims vehicle id {vehicle_id!r}")

    def verify(self, key_id: str, mac: bytes, payload: bytes) -> str | None:
        """The vehicle id the key is bound to (None for the fleet key); raises AuthError when not accepted."""
        key = self._keys.get(key_id)
        if key is None:
            raise AuthError(401, "unauthenticated", f"unknown key id {key_id!r}", unknown=True)
        if not hmac.compare_digest(frame_mac(key, key_id, payload), mac):
            raise AuthError(401, "unauthenticated", "the frame's HMAC-SHA256 does not match its key")
        return None if key_id == FLEET_KEY_ID else key_id
