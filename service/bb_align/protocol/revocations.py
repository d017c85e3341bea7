"""The fleet authority's revocation list: signed, versioned, never rolled back; and its register of issued
certificates, so that a key can be revoked by what names it (a fingerprint, a certificate) without its private file.

A list names revoked keys by fingerprint (SHA-256 of the raw Ed25519 public key), and carries a version that
grows by one with every list the authority signs::

    revoked.json = {kind, issuer, version, issued_at, revoked: [{fingerprint, vehicle_id, revoked_at}], signature}
    signature    = Ed25519(ca_key, "bb-align/revoked/v1" 0x00 + msgpack [2, issuer, version, issued_at, rows])

A receiver enforces the newest list it has verified (:class:`RevocationsInForce`): a list with a lower version than
the one in force is refused (the older signed list put back by someone who can write the file), at run time and,
through a small state file holding the highest version this receiver ever verified, at start-up.

``bb-align keys issue`` records each certificate it issues in ``DIR/issued/<vehicle_id>-<fingerprint16>.cert``
(public: no private key), so ``bb-align keys revoke DIR car2`` finds car2's certificates even after its
credential file was replaced (``issue --force``), and refuses to guess when car2 has more than one.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import msgpack

from .identity import Certificate, _b64, _read

log = logging.getLogger("bb_align.protocol.revocations")

FINGERPRINT_HEX = 64


def fingerprint(public_key: bytes) -> str:
    """A key's fingerprint: SHA-256 of the raw public key, hex (what ``bb-align keys list`` prints)."""
    return hashlib.sha256(public_key).hexdigest()


@dataclass(frozen=True)
class RevocationList:
    """Keys the authority has revoked, by fingerprint (a vehicle's new key, issued for the same id, stays valid:
    that is key rotation). ``version`` grows with every list signed; file ``revoked.json``."""

    issuer: str
    version: int
    issued_at: float
    entries: dict  # fingerprint (32 raw bytes) -> (vehicle id, revoked at)
    signature: bytes

    def tbs(self) -> bytes:
        rows = sorted([fp, vid, at] for fp, (vid, at) in self.entries.items())
        return msgpack.packb([2, self.issuer, self.version, self.issued_at, rows], use_bin_type=True)

    def revokes(self, public_key: bytes) -> bool:
        return hashlib.sha256(public_key).digest() in self.entries

    def save(self, path: Path) -> Path:
        doc = {
            "kind": "bb-align-revocations",
            "issuer": self.issuer,
            "version": self.version,
            "issued_at": self.issued_at,
            "revoked": [
                {"fingerprint": fp.hex(), "vehicle_id": vid, "revoked_at": at}
                for fp, (vid, at) in sorted(self.entries.items(), key=lambda kv: kv[1][1])
            ],
            "signature": _b64(self.signature),
        }
        _write_atomic(Path(path), json.dumps(doc, indent=1))  # a service reading it never sees half a file
        return Path(path)

    @classmethod
    def load(cls, path: Path | str) -> RevocationList:
        """Read (not verify) a revocation list; ValueError when it is not one."""
        doc = _read(Path(path), "bb-align-revocations")
        if "version" not in doc:
            raise ValueError(
                f"{path}: a revocation list without a version (written by an older bb-align): sign a new one with "
                "bb-align keys revoke"
            )
        try:
            entries = {
                bytes.fromhex(e["fingerprint"]): (str(e["vehicle_id"]), float(e["revoked_at"])) for e in doc["revoked"]
            }
            if type(doc["version"]) is not int or doc["version"] < 1:
                raise ValueError(f"version {doc['version']!r} is not a positive integer")
            if any(len(fp) != 32 for fp in entries):
                raise ValueError("a fingerprint is not 64 hex digits")
            return cls(
                str(doc["issuer"]), doc["version"], float(doc["issued_at"]), entries, base64.b64decode(doc["signature"])
            )
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{path}: malformed revocation list ({type(e).__name__}: {e})") from None


class RevocationsInForce:
    """The revocation list a receiver enforces: read from ``path`` and verified with ``verify`` (raises
    ValueError), read again when the file changes (looked at every ``poll_s``), never replaced by an older
    version. ``state``: a file holding the highest version this receiver ever verified, so that an older list is
    refused at start-up too (None: in memory only, e.g. a car's client library)."""

    def __init__(self, path: Path | str, verify: Callable[[RevocationList], None], state: Path | None = None):
        self.path, self.state, self._verify = Path(path), state, verify
        self.poll_s = 2.0
        self.floor = _read_state(state)  # the highest version verified before (0: none)
        self.current: RevocationList | None = None
        self._seen: tuple[float, int, int] | None = None  # (mtime, size, inode) of the file last read
        self._checked = 0.0
        self._reload()  # start-up: ValueError for a forged, malformed or rolled-back list

    @property
    def version(self) -> int:
        return 0 if self.current is None else self.current.version

    def revoked(self, public_key: bytes) -> bool:
        self._poll()
        current = self.current
        return current is not None and current.revokes(public_key)

    def _reload(self) -> None:
        st = self.path.stat()
        seen = (st.st_mtime, st.st_size, st.st_ino)
        if seen == self._seen:
            return
        rl = RevocationList.load(self.path)
        self._verify(rl)
        in_force = max(self.version, self.floor)
        if rl.version < in_force:
            self._seen = seen  # judged: not read again until the file changes
            raise ValueError(
                f"{self.path}: revocation list version {rl.version} is older than version {in_force} already "
                f"verified{'' if self.state is None else f' (recorded in {self.state})'}: refused as a rollback"
            )
        started = self.current is not None
        self.current, self._seen = rl, seen
        if self.state is not None and rl.version > self.floor:
            self.floor = rl.version
            try:
                _write_atomic(self.state, json.dumps({"kind": "bb-align-revocations-seen", "version": rl.version}))
            except OSError as e:
                why = f"{self.state}: cannot record revocation list version {rl.version} ({e.strerror or e})"
                if not started:  # at start-up: refuse rather than run without the rollback check across restarts
                    raise ValueError(why + "; choose another file (auth.revocations_state)") from None
                log.warning("%s: an older list will be refused until this process stops", why)

    def _poll(self) -> None:
        now = time.monotonic()
        if now - self._checked < self.poll_s:
            return
        self._checked = now
        try:
            self._reload()
        except (OSError, ValueError) as e:  # a broken, forged or older file: the list in force stays
            log.warning("revocation list not taken, version %d stays in force: %s", self.version, e)


def _read_state(state: Path | None) -> int:
    if state is None or not state.exists():
        return 0
    try:
        version = json.loads(state.read_text())["version"]
        if type(version) is not int:
            raise TypeError("version is not an integer")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{state}: unreadable revocation state ({type(e).__name__}: {e})") from None
    return version


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


# ---- the authority's register of issued certificates -----------------------------------------------------------
def record_issued(directory: Path, certificate: Certificate) -> Path:
    """Keep a public copy of an issued certificate: ``DIR/issued/<vehicle_id>-<fingerprint16>.cert``."""
    fp = fingerprint(certificate.public_key)
    path = Path(directory) / "issued" / f"{certificate.vehicle_id}-{fp[:16]}.cert"
    doc = {
        "kind": "bb-align-certificate",
        "vehicle_id": certificate.vehicle_id,
        "fingerprint": fp,
        "certificate": _b64(certificate.to_bytes()),
    }
    _write_atomic(path, json.dumps(doc))
    return path


def load_certificate(path: Path | str) -> Certificate:
    """The certificate of a ``.cert`` file, or of a ``.cred`` file (its private key is not read)."""
    doc = json.loads(Path(path).read_text())
    if not isinstance(doc, dict) or doc.get("kind") not in ("bb-align-certificate", "bb-align-credential"):
        raise ValueError(f"{path} is not a certificate or credential file (bb-align keys)")
    return Certificate.from_bytes(base64.b64decode(doc["certificate"]))


def issued_certificates(directory: Path) -> list[Certificate]:
    """Every certificate the authority in ``directory`` recorded, oldest first."""
    found = [load_certificate(p) for p in sorted((Path(directory) / "issued").glob("*.cert"))]
    return sorted(found, key=lambda c: c.not_before)
