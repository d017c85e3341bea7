"""Peer authentication: HMAC-SHA256 over each frame's bytes, with the fleet key or the sender's own key.

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

from .limits import FLEET_KEY_ID

DOMAIN = b"bb-align/frame/v1\x00"
MAC_BYTES = 32


def frame_mac(key: bytes | str, key_id: str, payload: bytes) -> bytes:
    """The 32-byte HMAC-SHA256 of one frame payload under ``key`` announced as ``key_id``."""
    key = key.encode() if isinstance(key, str) else key
    return hmac.new(key, DOMAIN + key_id.encode() + b"\x00" + payload, hashlib.sha256).digest()


class AuthError(Exception):
    """Why a frame's signature is not accepted: ``status`` 401 (unsigned, unknown key, bad MAC) or 403."""

    def __init__(self, status: int, error: str, detail: str):
        super().__init__(detail)
        self.status, self.error, self.detail = status, error, detail


class Keyring:
    """The keys a receiver accepts: key id (``"fleet"`` or a vehicle id) -> secret. ``required``: unsigned frames
    are refused."""

    def __init__(self, keys: dict[str, bytes | str], required: bool = True):
        self.required = required
        self._keys: dict[str, bytes] = {kid: k.encode() if isinstance(k, str) else bytes(k) for kid, k in keys.items()}

    def verify(self, key_id: str, mac: bytes, payload: bytes) -> str | None:
        """The vehicle id the key is bound to (None for the fleet key); raises AuthError when not accepted."""
        key = self._keys.get(key_id)
        if key is None:
            raise AuthError(401, "unauthenticated", f"unknown key id {key_id!r}")
        if not hmac.compare_digest(frame_mac(key, key_id, payload), mac):
            raise AuthError(401, "unauthenticated", "the frame's HMAC-SHA256 does not match its key")
        return None if key_id == FLEET_KEY_ID else key_id
