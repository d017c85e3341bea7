"""Per-vehicle identities: Ed25519 keys with compact certificates from a fleet authority (CA).

Why a certificate of our own and not X.509: a vehicle certificate travels in every signed message (as IEEE
1609.2 / ETSI TS 103 097 certificates do), so it must be small (147 bytes here, against 300-600 for a minimal
X.509 Ed25519 certificate) and cheap to parse on a receiver that parses whatever anyone sends (a fixed msgpack
array of five fields, no ASN.1). It holds exactly what the receiver checks::

    certificate = msgpack [1, issuer, vehicle_id, public_key (32 B), not_before, not_after, ca_signature (64 B)]
    ca_signature = Ed25519(ca_key, "bb-align/cert/v1" 0x00 + msgpack [1, issuer, vehicle_id, public_key,
                                                                       not_before, not_after])

A message signature is Ed25519 over a domain tag, the key id (the signer's vehicle id) and the payload's exact
bytes, so it is checked before the payload is decoded; frames and results use different tags, so one is never
accepted as the other::

    signature = Ed25519(vehicle_key, domain + key_id + 0x00 + payload)   domain: FRAME_DOMAIN or RESULT_DOMAIN

Files (``bb-align keys``): ``ca.pub`` (the authority's name and public key: what services and cars trust),
``ca.key`` (its private key: keep offline), ``<vehicle_id>.cred`` (a vehicle's certificate and private key).
All are small JSON documents with base64 fields; private ones are written with mode 0600.
"""

from __future__ import annotations

import base64
import json
import os
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import msgpack
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.hazmat.primitives.serialization import Encoding, NoEncryption, PrivateFormat, PublicFormat

from .limits import FLEET_KEY_ID, VEHICLE_ID_PATTERN

CERT_DOMAIN = b"bb-align/cert/v1\x00"
FRAME_DOMAIN = b"bb-align/frame/v1\x00"  # the same tag as the HMAC's (signatures.DOMAIN)
RESULT_DOMAIN = b"bb-align/result/v1\x00"
REVOCATION_DOMAIN = b"bb-align/revoked/v1\x00"
SIGNATURE_BYTES = 64
MAX_CERT_BYTES = 512  # a certificate is ~150 bytes; anything longer is refused before it is parsed

_ID = __import__("re").compile(VEHICLE_ID_PATTERN)


class IdentityError(Exception):
    """A certificate or signature that is not accepted: ``status`` 401 (unknown issuer, bad signature, expired)
    or 403 (a valid identity used for another vehicle id)."""

    def __init__(self, status: int, detail: str):
        super().__init__(detail)
        self.status, self.detail = status, detail


def _raw_public(key: Ed25519PublicKey) -> bytes:
    return key.public_bytes(Encoding.Raw, PublicFormat.Raw)


def _raw_private(key: Ed25519PrivateKey) -> bytes:
    return key.private_bytes(Encoding.Raw, PrivateFormat.Raw, NoEncryption())


def _b64(b: bytes) -> str:
    return base64.b64encode(b).decode("ascii")


@dataclass(frozen=True)
class Certificate:
    issuer: str
    vehicle_id: str
    public_key: bytes  # raw Ed25519, 32 bytes
    not_before: float
    not_after: float
    signature: bytes  # the issuer's Ed25519 signature over CERT_DOMAIN + tbs()

    def tbs(self) -> bytes:
        """The signed part."""
        return msgpack.packb([1, self.issuer, self.vehicle_id, self.public_key, self.not_before, self.not_after])

    def to_bytes(self) -> bytes:
        fields = [1, self.issuer, self.vehicle_id, self.public_key, self.not_before, self.not_after, self.signature]
        return msgpack.packb(fields, use_bin_type=True)

    @classmethod
    def from_bytes(cls, data: bytes) -> Certificate:
        """Parse (not verify) a certificate; IdentityError 401 for anything malformed."""
        if len(data) > MAX_CERT_BYTES:
            raise IdentityError(401, f"certificate of {len(data)} bytes, more than {MAX_CERT_BYTES}")
        try:
            v = msgpack.unpackb(data, raw=False, max_bin_len=128, max_str_len=128, max_array_len=8, max_map_len=0)
        except Exception as e:
            raise IdentityError(401, f"undecodable certificate: {type(e).__name__}") from None
        ok = (
            isinstance(v, list)
            and len(v) == 7
            and v[0] == 1
            and type(v[0]) is int
            and all(isinstance(x, str) for x in v[1:3])
            and isinstance(v[3], bytes)
            and len(v[3]) == 32
            and all(type(x) in (int, float) for x in v[4:6])
            and isinstance(v[6], bytes)
            and len(v[6]) == SIGNATURE_BYTES
        )
        if not ok or not _ID.match(v[2]):
            raise IdentityError(401, "malformed certificate (see bb_align.protocol.identity)")
        return cls(v[1], v[2], v[3], float(v[4]), float(v[5]), v[6])


class FleetAuthority:
    """The fleet's certificate authority: issues vehicle certificates (``bb-align keys init/issue``)."""

    def __init__(self, name: str, private_key: Ed25519PrivateKey):
        self.name, self._key = name, private_key

    @classmethod
    def generate(cls, name: str = "bb-align-fleet-ca") -> FleetAuthority:
        return cls(name, Ed25519PrivateKey.generate())

    @property
    def public_key(self) -> bytes:
        return _raw_public(self._key.public_key())

    def issue(
        self, vehicle_id: str, public_key: bytes | None = None, days: float = 365.0, not_before: float | None = None
    ) -> Credential | Certificate:
        """A certificate for ``vehicle_id``: for the given public key (returns the Certificate), or for a fresh key
        pair (returns the whole Credential)."""
        if not _ID.match(vehicle_id):
            raise ValueError(f"{vehicle_id!r} is not a vehicle id ({VEHICLE_ID_PATTERN})")
        if vehicle_id == FLEET_KEY_ID:
            raise ValueError(f"{FLEET_KEY_ID!r} is reserved for the shared fleet key; no certificate may name it")
        private = None
        if public_key is None:
            private = Ed25519PrivateKey.generate()
            public_key = _raw_public(private.public_key())
        start = time.time() - 60.0 if not_before is None else not_before
        unsigned = Certificate(self.name, vehicle_id, public_key, start, start + days * 86400.0, b"\0" * 64)
        cert = Certificate(**{**unsigned.__dict__, "signature": self._key.sign(CERT_DOMAIN + unsigned.tbs())})
        return cert if private is None else Credential(cert, private)

    def save(self, directory: Path) -> tuple[Path, Path]:
        """``ca.pub`` (share it) and ``ca.key`` (mode 0600, keep it offline)."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        pub = directory / "ca.pub"
        pub.write_text(json.dumps({"kind": "bb-align-ca", "name": self.name, "public_key": _b64(self.public_key)}))
        key = directory / "ca.key"
        _write_private(
            key, {"kind": "bb-align-ca-key", "name": self.name, "private_key": _b64(_raw_private(self._key))}
        )
        return pub, key

    @classmethod
    def load(cls, directory: Path) -> FleetAuthority:
        doc = _read(Path(directory) / "ca.key", "bb-align-ca-key")
        return cls(doc["name"], Ed25519PrivateKey.from_private_bytes(base64.b64decode(doc["private_key"])))

    def revoke(self, revoke: dict[bytes, str], previous=None):
        """A new revocation list (``revocations.RevocationList``): ``previous``'s entries (or none) and the keys of
        ``revoke`` (SHA-256 fingerprint -> vehicle id), its version one more than ``previous``'s, signed."""
        from .revocations import RevocationList

        if previous is not None and previous.issuer != self.name:
            raise ValueError(f"the revocation list was issued by {previous.issuer!r}, not by {self.name!r}")
        now = time.time()
        entries = dict(previous.entries) if previous is not None else {}
        for fp, vid in revoke.items():
            entries.setdefault(fp, (vid, now))
        version = 1 if previous is None else previous.version + 1
        unsigned = RevocationList(self.name, version, now, entries, b"")
        return RevocationList(self.name, version, now, entries, self._key.sign(REVOCATION_DOMAIN + unsigned.tbs()))


class Credential:
    """A vehicle's own identity: its certificate and private key. Signs frames (and, for the ego, answers)."""

    def __init__(self, certificate: Certificate, private_key: Ed25519PrivateKey):
        if _raw_public(private_key.public_key()) != certificate.public_key:
            raise ValueError("the private key does not match the certificate")
        self.certificate, self._key = certificate, private_key
        self.certificate_bytes = certificate.to_bytes()

    @property
    def vehicle_id(self) -> str:
        return self.certificate.vehicle_id

    def sign(self, domain: bytes, payload: bytes) -> bytes:
        return self._key.sign(domain + self.vehicle_id.encode() + b"\x00" + payload)

    def save(self, path: Path) -> Path:
        doc = {
            "kind": "bb-align-credential",
            "vehicle_id": self.vehicle_id,
            "certificate": _b64(self.certificate_bytes),
            "private_key": _b64(_raw_private(self._key)),
        }
        _write_private(Path(path), doc)
        return Path(path)

    @classmethod
    def load(cls, path: Path | str) -> Credential:
        doc = _read(Path(path), "bb-align-credential")
        cert = Certificate.from_bytes(base64.b64decode(doc["certificate"]))
        return cls(cert, Ed25519PrivateKey.from_private_bytes(base64.b64decode(doc["private_key"])))

    def __repr__(self) -> str:  # never the private key
        return f"Credential({self.vehicle_id!r}, issuer={self.certificate.issuer!r})"


class TrustStore:
    """What a receiver trusts: fleet authorities (name -> public key). Verifies certificates (each distinct
    certificate once: the verified ones are cached, bounded) and the signatures made with them."""

    def __init__(self, authorities: dict[str, bytes], cache_size: int = 1024):
        self._cas = {name: Ed25519PublicKey.from_public_bytes(k) for name, k in authorities.items()}
        self._cache: OrderedDict[bytes, tuple[Certificate, Ed25519PublicKey]] = OrderedDict()
        self._cache_size = cache_size
        self._lock = threading.Lock()
        self.revocations = None  # revocations.RevocationsInForce once use_revocations is called

    def use_revocations(self, path: Path | str, state: Path | None = None) -> int:
        """Refuse every key the authority's list at ``path`` revokes (``bb-align keys revoke``); the file is read
        again when it changes (every ``revocations.poll_s``), and an older version than one already verified is
        refused (``state``: where the highest version verified is kept across restarts). Returns the list's
        version; ValueError when it is not signed by a trusted authority or is older than one verified before."""
        from .revocations import RevocationsInForce

        self.revocations = RevocationsInForce(path, self.verify_revocations, state)
        return self.revocations.version

    def verify_revocations(self, rl) -> None:
        ca = self._cas.get(rl.issuer)
        if ca is None:
            raise ValueError(f"revocation list issued by {rl.issuer!r}, not a trusted fleet authority")
        try:
            ca.verify(rl.signature, REVOCATION_DOMAIN + rl.tbs())
        except InvalidSignature:
            raise ValueError("the revocation list's authority signature does not verify") from None

    @classmethod
    def load(cls, *paths: Path | str) -> TrustStore:
        """From ``ca.pub`` files (``bb-align keys init``)."""
        docs = [_read(Path(p), "bb-align-ca") for p in paths]
        return cls({d["name"]: base64.b64decode(d["public_key"]) for d in docs})

    def certificate(self, data: bytes, now: float | None = None) -> tuple[Certificate, Ed25519PublicKey]:
        """A verified certificate and its public key; IdentityError 401 when not issued by a trusted authority
        or outside its validity window."""
        with self._lock:
            hit = self._cache.get(data)
            if hit is not None:
                self._cache.move_to_end(data)
        if hit is None:
            cert = Certificate.from_bytes(data)
            ca = self._cas.get(cert.issuer)
            if ca is None:
                raise IdentityError(401, f"certificate issued by {cert.issuer!r}, not a trusted fleet authority")
            try:
                ca.verify(cert.signature, CERT_DOMAIN + cert.tbs())
            except InvalidSignature:
                raise IdentityError(401, "the certificate's authority signature does not verify") from None
            hit = (cert, Ed25519PublicKey.from_public_bytes(cert.public_key))
            with self._lock:
                self._cache[data] = hit
                while len(self._cache) > self._cache_size:
                    self._cache.popitem(last=False)
        cert = hit[0]
        now = time.time() if now is None else now
        if not cert.not_before <= now <= cert.not_after:
            raise IdentityError(401, f"certificate of {cert.vehicle_id!r} is not valid now (expired or not yet)")
        if cert.vehicle_id == FLEET_KEY_ID:  # the shared fleet key's id: a certificate can never speak as it
            raise IdentityError(403, f"a certificate for the reserved id {FLEET_KEY_ID!r} is never accepted")
        if self.revocations is not None and self.revocations.revoked(cert.public_key):
            raise IdentityError(401, f"certificate of {cert.vehicle_id!r} is revoked by its authority")
        return hit

    def verify(self, domain: bytes, key_id: str, payload: bytes, signature: bytes, cert: bytes, now=None) -> str:
        """The vehicle id that signed ``payload`` (IdentityError otherwise). ``key_id`` must be the certificate's."""
        certificate, public = self.certificate(cert, now)
        if key_id != certificate.vehicle_id:
            raise IdentityError(
                403, f"key id {key_id!r} with the certificate of {certificate.vehicle_id!r}: one signs only as itself"
            )
        try:
            public.verify(signature, domain + key_id.encode() + b"\x00" + payload)
        except InvalidSignature:
            raise IdentityError(401, "the Ed25519 signature does not match the message") from None
        return certificate.vehicle_id


def _write_private(path: Path, doc: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(doc, f)


def _read(path: Path, kind: str) -> dict:
    doc = json.loads(Path(path).read_text())
    if not isinstance(doc, dict) or doc.get("kind") != kind:
        raise ValueError(f"{path} is not a {kind} file (bb-align keys)")
    return doc
