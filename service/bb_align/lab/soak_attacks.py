"""What the soak's cars send: valid signed frames and the attack mix (each attack with the error it must get).

Every car signs with its own key: its Ed25519 credential (``bb-align keys``), or the shared fleet HMAC key when the
soak targets a running service that only has one. Attacks a keyless or a misbehaving sender can make: garbage,
unsigned frames, frames signed by an untrusted key, replays byte for byte, NaN boxes, a PNG decompression bomb,
oversized messages, a car claiming to be the ego, unsigned frames under fresh junk ids.
"""

from __future__ import annotations

import struct
import zlib
from collections import defaultdict, deque

import msgpack
import numpy as np

from bb_align.protocol import Credential, FleetAuthority

ATTACKS = ("garbage", "unsigned", "bad_mac", "replay", "nan_box", "png_bomb", "spoofed_id", "junk_sender", "oversized")
# What the service must answer to each attack (bbalign_frames_rejected_total{error=...}).
EXPECTED_ERROR = {
    "garbage": "undecodable",
    "unsigned": "unauthenticated",
    "bad_mac": "unauthenticated",
    "replay": "replayed",
    "nan_box": "invalid",
    "png_bomb": "invalid",
    "spoofed_id": "invalid",  # HMAC fleet key: the frame's id differs from the key's (a credential: forbidden)
    "junk_sender": "unauthenticated",
    "oversized": "too_large",
}
SIGNED_BY_THE_CAR = ("replay", "nan_box", "png_bomb", "spoofed_id")  # attacks with the car's own genuine signature
# Signed, well-formed frames whose fault shows only when a worker decodes them (the PNG's image data is inflated
# then, not at the gate): admitted as the car's latest frame, then refused with a failed result (invalid_frame),
# or replaced unread by the car's next frame (counted as dropped, as any replaced frame).
REFUSED_AT_DECODE = ("png_bomb",)
Key = Credential | str  # a vehicle's Ed25519 credential, or an HMAC secret (the fleet key)


def expected_errors(signers: dict[str, Key]) -> dict[str, str]:
    """EXPECTED_ERROR for these signers: a car signing with its own certificate that claims the ego's id is
    refused as forbidden (the certificate names the car) before its key chunk is even compared."""
    certified = any(isinstance(k, Credential) for k in signers.values())
    return {**EXPECTED_ERROR, "spoofed_id": "forbidden" if certified else "invalid"}


def rogue_keys(signers: dict[str, Key]) -> dict[str, Key]:
    """Per vehicle, a key the service does not trust: a certificate from another authority of the same name
    (Ed25519), or another HMAC secret."""
    rogue_ca = FleetAuthority.generate("bb-align-fleet-ca")
    return {
        vid: rogue_ca.issue(vid) if isinstance(k, Credential) else "not-the-fleet-key-" + "x" * 16
        for vid, k in signers.items()
    }


def png_bomb(side: int) -> bytes:
    """A PNG whose header matches a side x side BV image but whose image data inflates to 64x more bytes."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)))

    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    idat = zlib.compress(bytes(64 * side * (side + 1)), 9)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


class Sender:
    """Builds each message (valid or an attack) and remembers what it sent. ``signers``: vehicle id -> its key."""

    def __init__(self, signers: dict[str, Key], max_message_bytes: int, rng: np.random.Generator, history: int = 16):
        from bb_align.protocol import pack, sign

        self._pack, self._sign = pack, sign
        self.signers = signers
        self.rogue = rogue_keys(signers)
        self.rng = rng
        self.max_message_bytes = max_message_bytes
        self.last_valid: dict[str, bytes] = {}
        self.history: dict[str, deque[bytes]] = defaultdict(lambda: deque(maxlen=history))  # what is on the air
        self._bombs: dict[int, bytes] = {}

    def signed(self, frame) -> bytes:
        """``frame`` signed by its own car's key (whatever it holds)."""
        return self._sign(self._pack(frame), self.signers[frame.vehicle_id])

    def valid(self, frame, stamp: float, seq: int) -> bytes:
        data = self.signed(frame.model_copy(update={"stamp": stamp, "seq": seq}))
        self.last_valid[frame.vehicle_id] = data
        self.history[frame.vehicle_id].append(data)
        return data

    def recorded(self) -> list[tuple[str, bytes]]:
        """The last valid frames of every car (vehicle id, signed bytes): what anyone in range could record."""
        return [(vid, data) for vid, frames in self.history.items() for data in frames]

    def attack(self, kind: str, frame, stamp: float, seq: int) -> tuple[str, bytes]:
        """(key chunk to publish under, payload) for one attack on behalf of ``frame``'s car."""
        vid = frame.vehicle_id
        key = self.signers[vid]
        f = frame.model_copy(update={"stamp": stamp, "seq": seq})
        if kind == "garbage":  # 0xc1 is never used by msgpack: undecodable, whatever follows
            return vid, b"\xc1" + self.rng.bytes(int(self.rng.integers(0, 2000)))
        if kind == "unsigned":
            return vid, self._pack(f)
        if kind == "bad_mac":
            return vid, self._sign(self._pack(f), self.rogue[vid])
        if kind == "replay":  # the car's last valid frame, byte for byte
            return vid, self.last_valid[vid]
        if kind == "nan_box":
            d = f.model_dump(mode="python")
            d["boxes"] = d["boxes"] or [[1.0, 1.0, 0.0, 4.0, 2.0, 1.5, 0.0]]
            d["boxes"][0][0] = float("nan")
            return vid, self._sign(msgpack.packb(d, use_bin_type=True), key)
        if kind == "png_bomb":
            side = int(round(2 * f.bev.range_m / f.bev.resolution_m))
            bomb = self._bombs.setdefault(side, png_bomb(side))
            return vid, self._sign(self._pack(f.model_copy(update={"png": bomb})), key)
        if kind == "spoofed_id":
            return vid, self._sign(self._pack(f.model_copy(update={"vehicle_id": "ego"})), key)
        if kind == "junk_sender":  # an unsigned frame under a fresh id: must not create peer state
            junk = f"junk-{int(self.rng.integers(1 << 40)):x}"
            return junk, self._pack(f.model_copy(update={"vehicle_id": junk}))
        if kind == "oversized":  # over the service's limit, under Zenoh's own reassembly bound
            return vid, b"\x00" * (self.max_message_bytes + 1024)
        raise ValueError(kind)
