"""The Zenoh door's check of a raw stream message, run on the Zenoh callback thread before the message may wait
for the gate (authentication on).

Every message the door lets through costs the gate a full check, and every message the door queues takes a place
that authenticated frames need; a keyless flood must therefore cost as little as possible and be stopped here.
The door refuses only what the gate would certainly refuse, cheapest test first:

0. (the Zenoh stream) while the door's share for refusals is spent (``DoorShare``), a large message under a key
   chunk refused lately or never accepted is dropped before it is even copied out of Zenoh;
1. not a msgpack map (one byte looked at: 1-byte garbage and most junk end here);
2. not a Signed envelope, one this receiver has no key for, or one whose payload is not a map (a frame is one):
   read first from the envelope's top-level headers alone (``envelope_spans``: no value is copied, so a 1 MB
   message costs about what 1 byte does), else decoded under the message limits; no crypto;
3. a payload that is not a frame (no readable stamp and seq): refused before its signature is checked, since the
   gate refuses it whoever signed it (a compromised car's junk, and a keyless sender's, costs no MAC);
4. a byte-for-byte copy of a message verified here recently (a replay of a frame still on its way to the gate):
   refused without a signature check;
5. a payload whose (stamp, seq) is not newer than the newest frame accepted from the claimed sender with the key
   the envelope names (a replay of an older frame): read without trusting it, since a frame that old is refused
   whoever signed it;
6. a stamp outside the receiver's clock window (``max_stamp_age_s`` / ``max_stamp_lead_s``; not in the replay
   profile): an hour-old recording costs no signature check. On the stream, one such frame per sender a second
   (``StaleProbe``) still has its signature checked, so that a genuine car with a wrong clock hears why (a signed
   Refusal); every other is refused unsigned, unanswered;
7. a copy of an envelope whose signature failed here lately (same key, signature, stamp, seq and payload);
8. the signature on the raw payload (Ed25519 with the cached certificate, or HMAC) under the door's
   ``SignatureBudget``: failed checks spend CPU-seconds from a token bucket; while it is empty only senders that
   verified lately and failed no check lately are checked, anything else is refused (503, never a pause; decided
   from the envelope's headers at step 2, before its payload is copied); then the signer may sign for the key
   chunk it came under.

The same checks guard the Zenoh query door (``Door.query``, its own budget) and, from step 4 on, the REST door.

A message that passes goes to the ego's lane (signed by the ego) or the signed lane, one signed by a genuine
vehicle for another's key chunk to the unverified lane (the gate names the error). The gate checks everything
again; the door only decides what may wait for it.
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

import msgpack

from bb_align.protocol import WireError, limit_env, peek_signed
from bb_align.protocol.limits import FLEET_KEY_ID
from bb_align.protocol.models import Signed
from bb_align.protocol.signatures import AuthError, Keyring, signer_key
from bb_align.protocol.validation import _check_stamp_clock

from .scheduler import EGO, SIGNED, UNVERIFIED_LANE

# msgpack map headers: fixmap 0x80-0x8f, map16 0xde, map32 0xdf (a Signed envelope is a map)
_MAP_FIRST_BYTES = frozenset(range(0x80, 0x90)) | {0xDE, 0xDF}
_PAYLOAD_KEYS = 16  # a frame has fewer top-level fields; more and the peek gives up (the gate decides)
_ENVELOPE_KEYS = 8  # a Signed envelope has 6 fields at most; more and envelope_spans gives up (full decode)
_STR_HEADERS = frozenset(range(0xA0, 0xC0)) | {0xD9, 0xDA, 0xDB}
_BIN_HEADERS = frozenset({0xC4, 0xC5, 0xC6})
_FIXED_WIDTH = {0xC0: 0, 0xC2: 0, 0xC3: 0, 0xCA: 4, 0xCB: 8, 0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}
_FIXED_WIDTH |= {0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8}  # nil, bools, floats, unsigned and signed ints
_LENGTH_WIDTH = {0xD9: 1, 0xDA: 2, 0xDB: 4, 0xC4: 1, 0xC5: 2, 0xC6: 4}  # str8/16/32, bin8/16/32
_DEFAULT_ALG = Signed.model_fields["alg"].default  # an envelope without `alg` is the model's default


def _undecodable(detail: str) -> WireError:
    return WireError(400, "undecodable", detail)


def _not_signed() -> WireError:
    return WireError(401, "unauthenticated", "not a Signed frame (refused at the door)", "message")


def _no_key(key_id: str, alg: str) -> WireError:
    return WireError(401, "unauthenticated", f"no key for {key_id!r} ({alg})", "mac", alg)


def _not_a_frame() -> WireError:
    return _undecodable("the signed payload is not a frame (no readable stamp and seq)")


def stamp_and_seq(payload: bytes) -> tuple[float, int] | None:
    """(stamp, seq) of an encoded frame, read without building it (the other fields are skipped, not copied);
    None when the payload is not a map holding both as numbers."""
    claimed = frame_claim(payload)
    return None if claimed is None else claimed[:2]


def frame_claim(payload: bytes) -> tuple[float, int, str | None] | None:
    """(stamp, seq, vehicle_id or None) an encoded frame claims, read from its headers without building it or
    copying its image (``_skip`` walks over the other values; a 1 MB frame costs what a small one does); None when
    the payload is not a map holding stamp and seq as numbers."""
    try:
        n, i = _map_header(payload, 0)
        if n > _PAYLOAD_KEYS:
            return None
        found: dict[str, object] = {}
        for _ in range(n):
            key = _scalar(payload, i) if payload[i] in _STR_HEADERS else None
            if key is None:
                return None
            name, i = bytes(payload[key[0] : key[1]]), key[1]
            end = _skip(payload, i, 0)
            if end is None:
                return None
            if name in (b"stamp", b"seq", b"vehicle_id"):
                found[name.decode()] = msgpack.unpackb(payload[i:end], raw=False)
            i = end
    except Exception:  # msgpack raises several types on odd input; a truncated one raises IndexError here
        return None
    stamp, seq = found.get("stamp"), found.get("seq")
    if type(stamp) not in (int, float) or type(seq) is not int:
        return None
    vid = found.get("vehicle_id")
    return float(stamp), seq, (vid if isinstance(vid, str) else None)


_MAX_DEPTH = 8  # a frame nests a few levels (boxes, pose); deeper and frame_claim gives up (the gate decides)
_EXT_FIXED = {0xD4: 1, 0xD5: 2, 0xD6: 4, 0xD7: 8, 0xD8: 16}  # fixext 1-16 (a type byte, then the data)
_EXT_LENGTH = {0xC7: 1, 0xC8: 2, 0xC9: 4}  # ext 8/16/32


def _map_header(data: bytes, i: int) -> tuple[int, int]:
    """(entries, index after the header) of the msgpack map at ``i``; ValueError when it is not one."""
    b = data[i]
    if 0x80 <= b <= 0x8F:
        return b - 0x80, i + 1
    if b in (0xDE, 0xDF):
        w = 2 if b == 0xDE else 4
        return int.from_bytes(data[i + 1 : i + 1 + w], "big"), i + 1 + w
    raise ValueError("not a map")


def _skip(data: bytes, i: int, depth: int) -> int | None:
    """The index after the msgpack value at ``i``, found from headers alone (nothing copied); None when it runs
    past the end or nests deeper than ``_MAX_DEPTH``."""
    b = data[i]
    if 0x80 <= b <= 0x8F or 0x90 <= b <= 0x9F or b in (0xDC, 0xDD, 0xDE, 0xDF):
        if depth >= _MAX_DEPTH:
            return None
        if 0x80 <= b <= 0x8F or b in (0xDE, 0xDF):
            n, i = _map_header(data, i)
            n *= 2
        elif 0x90 <= b <= 0x9F:
            n, i = b - 0x90, i + 1
        else:
            w = 2 if b == 0xDC else 4
            n, i = int.from_bytes(data[i + 1 : i + 1 + w], "big"), i + 1 + w
        if n > len(data) - i:  # each value takes a byte at least
            return None
        for _ in range(n):
            i = _skip(data, i, depth + 1)
            if i is None:
                return None
        return i
    if b in _EXT_FIXED:
        end = i + 2 + _EXT_FIXED[b]
    elif b in _EXT_LENGTH:
        w = _EXT_LENGTH[b]
        end = i + 2 + w + int.from_bytes(data[i + 1 : i + 1 + w], "big")
    else:
        span = _scalar(data, i)
        if span is None:
            return None
        end = span[1]
    return end if end <= len(data) else None


def request_peer(data: bytes) -> bytes | None:
    """The raw ``peer`` value of a msgpack AlignRequest (a Signed envelope, itself a map), sliced out without
    decoding it; None when the body is not a small map holding one."""
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=len(data) + 1)
    unpacker.feed(data)
    try:
        n = unpacker.read_map_header()
        if n > 4:
            return None
        for _ in range(n):
            key = unpacker.unpack()
            start = unpacker.tell()
            unpacker.skip()
            if key == "peer":
                return data[start : unpacker.tell()]
    except Exception:  # msgpack raises several types on truncated or odd input
        return None
    return None


def _scalar(data: bytes, i: int) -> tuple[int, int] | None:
    """(start, end) of the contents of the msgpack scalar whose header is at ``i`` (a str's or bin's bytes, a
    number's); None for a map, an array, an extension or a value running past the end."""
    b = data[i]
    if b <= 0x7F or b >= 0xE0:  # positive and negative fixints: the header is the value
        return i + 1, i + 1
    if 0xA0 <= b <= 0xBF:  # fixstr
        start, n = i + 1, b - 0xA0
    elif b in _FIXED_WIDTH:
        start, n = i + 1, _FIXED_WIDTH[b]
    elif b in _LENGTH_WIDTH:
        start = i + 1 + _LENGTH_WIDTH[b]
        n = int.from_bytes(data[i + 1 : start], "big")
    else:
        return None
    return (start, start + n) if start + n <= len(data) else None


def envelope_spans(data: bytes) -> dict[bytes, tuple[int, int, int]] | None:
    """The top-level map of a raw message read from its headers alone, no value copied: key (its UTF-8 bytes) ->
    (header byte, start, end) of its value's contents. None when this small reader cannot tell (not a map, more
    than an envelope's fields, a key that is not a string, a nested value, a key twice, truncated or trailing
    bytes): the caller then decodes the message in full, so the reader only ever makes a refusal cheaper."""
    b, size = data[0], len(data)
    if 0x80 <= b <= 0x8F:
        n, i = b - 0x80, 1
    elif b in (0xDE, 0xDF):
        i = 3 if b == 0xDE else 5
        n = int.from_bytes(data[1:i], "big")
    else:
        return None
    if n > _ENVELOPE_KEYS:
        return None
    spans: dict[bytes, tuple[int, int, int]] = {}
    for _ in range(n):
        key = _scalar(data, i) if i < size and data[i] in _STR_HEADERS else None
        value = _scalar(data, key[1]) if key is not None and key[1] < size else None
        if value is None:
            return None
        name = data[key[0] : key[1]]
        if name in spans:
            return None
        spans[name] = (data[key[1]], *value)
        i = value[1]
    return spans if i == size else None


class RecentSignatures:
    """Messages verified at the door lately: (key id, signature) -> digest of the payload, bounded (oldest
    forgotten). An exact copy is a replay; anything else with the same signature must still be verified.
    ``failed``/``add_failed``: the same for envelopes whose check failed, keyed also by the claimed (stamp, seq)
    and the payload's length, so the digest (a pass over the payload) is computed only for a likely copy: a
    zero-signature forgery with a new stamp costs no digest, its byte-for-byte copy no second check."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._seen: OrderedDict[tuple[str, bytes], bytes] = OrderedDict()
        self._failed: OrderedDict[tuple, bytes] = OrderedDict()
        self._lock = threading.Lock()

    def failed(self, key_id: str, mac: bytes, claimed: tuple, payload: bytes) -> bool:
        with self._lock:
            digest = self._failed.get((key_id, mac, claimed, len(payload)))
        return digest is not None and digest == self._digest(payload)

    def add_failed(self, key_id: str, mac: bytes, claimed: tuple, payload: bytes) -> None:
        key, digest = (key_id, mac, claimed, len(payload)), self._digest(payload)
        with self._lock:
            self._failed[key] = digest
            self._failed.move_to_end(key)
            while len(self._failed) > self.capacity:
                self._failed.popitem(last=False)

    @staticmethod
    def _digest(payload: bytes) -> bytes:
        return hashlib.blake2b(payload, digest_size=16).digest()

    def is_copy(self, key_id: str, mac: bytes, payload: bytes) -> bool:
        with self._lock:
            digest = self._seen.get((key_id, mac))
        return digest is not None and digest == self._digest(payload)

    def add(self, key_id: str, mac: bytes, payload: bytes) -> None:
        digest = self._digest(payload)
        with self._lock:
            self._seen[(key_id, mac)] = digest
            self._seen.move_to_end((key_id, mac))
            while len(self._seen) > self.capacity:
                self._seen.popitem(last=False)


class _RecentVerdicts:
    """Senders (key chunks, claimed signers) by when one of their messages last passed and last failed, each table
    bounded (the least recent out): a sender is trusted when it passed lately and failed in none of the last
    ``suspect_s``. What both door buckets let through once they are spent."""

    def __init__(self, suspect_s: float, max_senders: int):
        self.suspect_s, self.max_senders = suspect_s, max_senders
        self._good: OrderedDict[str, float] = OrderedDict()  # sender -> when a message of it last passed
        self._bad: OrderedDict[str, float] = OrderedDict()  # sender -> when a message of it last failed

    def trusted(self, sender: str, now: float) -> bool:
        bad = self._bad.get(sender)
        return sender in self._good and (bad is None or now - bad > self.suspect_s)

    def note(self, sender: str, passed: bool, now: float) -> None:
        table = self._good if passed else self._bad
        table[sender] = now
        table.move_to_end(sender)
        while len(table) > self.max_senders:
            table.popitem(last=False)


class DoorShare:
    """At most ``share`` of one core for what the Zenoh door refuses, without holding up the messages it accepts
    for it: a token bucket of the door thread's CPU-seconds (``share`` a second, ``burst_s`` at once), charged for
    every message refused (its cost outside the signature check, which has its own ``SignatureBudget``) or dropped.

    ``admit(sender, nbytes)`` is asked before a message is copied out of Zenoh (``sender``: its key chunk, not
    yet trusted; ``nbytes``: its size, known without a copy). While the bucket holds CPU time every message is
    read. While it is spent, a message of ``large_bytes`` or more under a key chunk refused lately (``suspect_s``)
    or never accepted is dropped unread, at some 15 us whatever its size; everything else is read: messages of
    chunks accepted lately and refused in none of the last ``suspect_s``, and small messages (copied out in a few
    us: a genuine car's frame, a replayed one, 1-byte junk). Copying out a large one is what costs (~0.4 ms for
    512 KB, ~0.7-1.3 ms for 1 MB on a loaded VM: page faults, each block that large has its own mapping,
    allocator.py), and a whole forged 1 MB frame ~2 ms: paid by sleeping, as the door's earlier ``Budget`` did,
    each one slept ~110 ms at a 0.02 share while the other cars' frames waited behind it in Zenoh's FIFO (0.47 of
    their results under a full-speed forgery, issue 47). So a keyless flood of large forgeries under car1's key
    costs what it drops and, while it floods, only car1's own large frames.

    The only waits left are short: a refusal or drop that finds the bucket ``burst_s`` in debt waits its own cost
    over the share, at most ``max_pause_s`` (1 ms): under a flood of small junk fast enough to spend the share
    (thousands a second) the door then reads about ``share`` of the time, Zenoh's FIFO fills and pushes back on
    the senders' links, and a car's frame behind the FIFO's ``door_queue`` messages waits ~16 ms at most."""

    def __init__(
        self,
        share: float,
        burst_s: float,
        large_bytes: int = 256 * 1024,
        suspect_s: float = 2.0,
        max_senders: int = 1024,
        max_pause_s: float = 0.001,
        clock=time.monotonic,
        sleep=time.sleep,
    ):
        self.share, self.burst_s, self.large_bytes, self.suspect_s = share, burst_s, large_bytes, suspect_s
        self.max_pause_s = max_pause_s
        self._clock, self._sleep = clock, sleep
        self._tokens, self._then = burst_s, clock()
        self._verdicts = _RecentVerdicts(suspect_s, max_senders)  # key chunks: last accepted, last refused
        self.dropped = 0  # messages dropped unread
        self.refused_cpu_s = 0.0  # CPU time of the messages refused (read) and dropped (unread)
        self.throttled_s = 0.0  # time spent waiting (short waits, only while the bucket is burst_s in debt)

    def _refill(self, now: float) -> None:
        self._tokens = min(self.burst_s, self._tokens + (now - self._then) * self.share)
        self._then = now

    def admit(self, sender: str, nbytes: int) -> bool:
        """Whether to read a message of ``nbytes`` under key chunk ``sender`` (else drop it unread)."""
        now = self._clock()
        self._refill(now)
        if self._tokens > 0.0 or nbytes < self.large_bytes:
            return True
        return self._verdicts.trusted(sender, now)

    def spent(self, sender: str, cpu_s: float, accepted: bool) -> None:
        """A message read: accepted (queued for the gate) or refused, at ``cpu_s`` of the door's CPU (signature
        checks left out); only a refusal is charged."""
        self._verdicts.note(sender, accepted, self._clock())
        if not accepted:
            self._charge(cpu_s)

    def drop(self, cpu_s: float) -> None:
        """A message dropped unread at ``cpu_s``."""
        self.dropped += 1
        self._charge(cpu_s)

    def _charge(self, cpu_s: float) -> None:
        self.refused_cpu_s += cpu_s
        self._refill(self._clock())
        self._tokens = max(self._tokens - cpu_s, -2.0 * self.burst_s)  # the debt is bounded: so is the catch-up
        if self._tokens < -self.burst_s:
            pause = min(cpu_s / self.share, self.max_pause_s)
            self._sleep(pause)
            self.throttled_s += pause

    def error(self) -> WireError:
        return WireError(
            503,
            "overloaded",
            "the door's CPU share for refusals is spent: large messages under a key that was refused lately or "
            "never accepted are dropped unread",
            "door",
            self.share,
            limit_env("door_share"),
        )


class KeyRate:
    """A token bucket per verified sender (REST): ``rate_hz`` frames a second on average, ``burst`` at once. Only
    a sender whose signature verified is charged, so nobody can spend another car's allowance. Bounded: the
    least recently seen of more than ``max_keys`` senders is forgotten (it starts again with a full bucket)."""

    def __init__(self, rate_hz: float, burst: float, max_keys: int = 4096, clock=time.monotonic):
        self.rate_hz, self.burst, self.max_keys, self._clock = rate_hz, burst, max_keys, clock
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # key -> (tokens, when)
        self._lock = threading.Lock()

    def empty(self, key: str) -> bool:
        """Whether ``key``'s bucket holds less than one frame now (nothing is charged): the REST door asks this of
        the sender a body claims before decoding it or checking its signature, so a key holder's flood is refused
        (429) for the cost of reading its headers, while nobody else can spend that key's allowance."""
        now = self._clock()
        with self._lock:
            tokens, then = self._buckets.get(key, (self.burst, now))
        return min(self.burst, tokens + (now - then) * self.rate_hz) < 1.0

    def allow(self, key: str) -> bool:
        now = self._clock()
        with self._lock:
            tokens, then = self._buckets.pop(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - then) * self.rate_hz)
            ok = tokens >= 1.0
            self._buckets[key] = (tokens - 1.0 if ok else tokens, now)
            while len(self._buckets) > self.max_keys:
                self._buckets.popitem(last=False)
        return ok


class SignatureBudget:
    """A door's signature checks under a token bucket of CPU-seconds: ``share`` of one core a second on average,
    ``burst_s`` CPU-seconds at once. Only checks that fail spend it (a check that verifies is the fleet's own
    traffic, bounded by the cars' rates; a replay of it is refused before its check). While the bucket is empty
    (in debt: a check's cost is known once it has run) ``allow`` lets through only signers that verified lately
    and failed no check in the last ``suspect_s``: a keyless sender forging a car's frames can then deny that car
    alone, and only while it floods; every other car's frames are checked as before. It never sleeps: what it does
    not allow is refused at once (``overloaded``), so the door goes on with the next message."""

    def __init__(
        self, share: float, burst_s: float, suspect_s: float = 2.0, max_signers: int = 1024, clock=time.monotonic
    ):
        self.share, self.burst_s, self.suspect_s, self.max_signers = share, burst_s, suspect_s, max_signers
        self._clock = clock
        self._tokens, self._then = burst_s, clock()
        self._verdicts = _RecentVerdicts(suspect_s, max_signers)  # signers: last verified, last failed a check
        self._lock = threading.Lock()
        self.refused = 0
        self.failed_cpu_s = 0.0

    def _refill(self, now: float) -> None:
        self._tokens = min(self.burst_s, self._tokens + (now - self._then) * self.share / 2)
        self._then = now

    def allow(self, signer: str) -> bool:
        now = self._clock()
        with self._lock:
            self._refill(now)
            if self._tokens > 0.0:
                return True
            ok = self._verdicts.trusted(signer, now)
            if not ok:
                self.refused += 1
            return ok

    def spent(self, signer: str, cpu_s: float, verified: bool) -> None:
        now = self._clock()
        with self._lock:
            self._verdicts.note(signer, verified, now)
            if not verified:
                self._refill(now)
                self._tokens -= cpu_s
                self.failed_cpu_s += cpu_s

    def error(self, signer: str) -> WireError:
        return WireError(
            503,
            "overloaded",
            f"the door's budget for signature checks that fail is spent; {signer!r} is not checked now (a sender "
            "that verified lately and failed no check is)",
            "mac",
            self.share,
            limit_env("signature_share"),
        )


class StaleProbe:
    """At most one message a second per claimed sender (bounded table) may have its signature checked although
    its stamp is outside the clock window: so a genuine car with a wrong clock is told why (a signed Refusal),
    while a recorder playing hour-old frames gets nearly all of them refused before any check."""

    def __init__(self, interval_s: float = 1.0, max_senders: int = 1024, clock=time.monotonic):
        self.interval_s, self.max_senders, self._clock = interval_s, max_senders, clock
        self._last: OrderedDict[str, float] = OrderedDict()
        self._lock = threading.Lock()

    def allow(self, sender: str) -> bool:
        now = self._clock()
        with self._lock:
            last = self._last.get(sender)
            if last is not None and now - last < self.interval_s:
                return False
            self._last[sender] = now
            self._last.move_to_end(sender)
            while len(self._last) > self.max_senders:
                self._last.popitem(last=False)
            return True


class Door:
    """``lane(sender, data)`` for stream messages: the intake lane a raw message may wait in, or WireError when
    the gate would certainly refuse it; ``query(data)`` the same for a query's payload (the verified signer).
    ``newest(vehicle_id, key)``: the newest (stamp, seq) accepted from a sender signed with that key
    (``signatures.signer_key``). ``budget``: the door's signature budget (one per door: the stream's, the queries',
    REST's are separate objects)."""

    def __init__(
        self,
        keyring: Keyring,
        limits,
        ego_id: str,
        newest: Callable[[str, bytes | None], tuple[float, int] | None],
        recent: int,
        budget: SignatureBudget | None = None,
        clock=time.time,
    ):
        self.keyring, self.limits, self.ego_id = keyring, limits, ego_id
        self._newest = newest
        self.recent = RecentSignatures(recent)
        self.budget = budget or SignatureBudget(limits.signature_share, limits.signature_burst_s)
        self.stale_probe = StaleProbe()
        self._clock = clock
        self.signature_cpu_s = 0.0  # CPU time of the signature checks (the door thread's Budget leaves it out)

    def lane(self, sender: str, data: bytes) -> tuple[str, str | None]:
        """(lane, verified signer or None) for a stream message under key chunk ``sender``; raises WireError."""
        env, claimed = self.envelope(data)
        self.precheck(sender, env, claimed, probe=True)
        signer = self.verify(env, claimed)
        try:
            self.keyring.authorize(signer, sender)
        except AuthError:  # a genuine signer under another's key chunk: the gate names what is wrong
            return UNVERIFIED_LANE, None
        return (EGO if sender == self.ego_id else SIGNED), signer

    def query(self, data: bytes) -> str:
        """The verified signer of a query's payload (a Signed frame); WireError for what the gate would refuse and
        for what the budget does not check now. Nothing refused here waits in the intake."""
        env, claimed = self.envelope(data)
        self.precheck(self.claimed_sender(env, claimed), env, claimed, probe=False)
        return self.verify(env, claimed)

    @staticmethod
    def claimed_sender(env: Signed, claimed: tuple) -> str:
        """The vehicle a message claims to come from: its key id, or the frame's own id under the fleet key."""
        return (claimed[2] or env.key_id) if env.key_id == FLEET_KEY_ID else env.key_id

    def envelope(self, data: bytes) -> tuple[Signed, tuple[float, int, str | None]]:
        """Steps 1-3: a Signed envelope under a known key around something frame-shaped."""
        if not data or data[0] not in _MAP_FIRST_BYTES:
            raise _undecodable("not a msgpack map (a Signed frame is one)")
        self._refuse_by_headers(data)
        env = peek_signed(data, self.limits)
        if env is None:  # undecodable, not an envelope, or a malformed one: the gate refuses each
            raise _not_signed()
        if not self.keyring.knows(env.key_id, env.alg):
            raise _no_key(env.key_id, env.alg)
        claimed = frame_claim(env.payload)
        if claimed is None:  # junk, signed or not: the gate refuses it whoever signed it, so no MAC is spent on it
            raise _not_a_frame()
        return env, claimed

    def precheck(self, sender: str, env: Signed, claimed: tuple, probe: bool = False, replays: bool = True) -> None:
        """Steps 4-7 (no crypto): a copy of a message verified or failed lately, not newer than the sender's last,
        a stamp outside the clock window (``probe``: one a second per sender may still be checked, stream).
        ``replays=False`` leaves copies and old frames of verified senders to the peer table (REST: its refusal
        names the replay profile and the restart floor)."""
        if replays and self.recent.is_copy(env.key_id, env.mac, env.payload):
            raise WireError(409, "replayed", "a copy of a message already received", "mac")
        if replays:
            self._refuse_old(sender, signer_key(env.alg, env.key_id, env.cert), claimed[:2])
        if self.limits.clock_checked:
            try:
                _check_stamp_clock(claimed[0], self._clock(), self.limits, "stamp")
            except WireError:
                if not (probe and self.stale_probe.allow(sender)):
                    raise
        if self.recent.failed(env.key_id, env.mac, claimed[:2], env.payload):
            raise WireError(401, "unauthenticated", "a copy of a message whose signature did not verify", "mac")

    def verify(self, env: Signed, claimed: tuple) -> str:
        """Step 8: the signature, under the budget."""
        who = env.key_id
        if not self.budget.allow(who):
            raise self.budget.error(who)
        t0 = time.thread_time()
        try:
            signer = self.keyring.verify_signed(env.key_id, env.alg, env.mac, env.payload, env.cert, time.time())
        except AuthError as e:
            # the failed check's digest (a pass over the payload: 1.4 ms for 1 MB) is part of its cost, paid from
            # the signature budget (which refuses) and not the door's share (which sleeps: paid there, 6 forged
            # 1 MB frames a second kept the door asleep and the cars' frames 1.6 s late; issue 47 probes)
            self.recent.add_failed(env.key_id, env.mac, claimed[:2], env.payload)
            cost = time.thread_time() - t0
            self.signature_cpu_s += cost
            self.budget.spent(who, cost, verified=False)
            raise WireError(e.status, e.error, e.detail, "mac", env.alg) from None
        self.recent.add(env.key_id, env.mac, env.payload)
        cost = time.thread_time() - t0
        self.signature_cpu_s += cost
        self.budget.spent(who, cost, verified=True)
        return signer

    def _refuse_by_headers(self, data: bytes) -> None:
        """Refuse from the top-level headers alone (nothing copied, whatever the size) what steps 2-3 would refuse
        after decoding: no envelope, no key, a payload that is not a map; and what step 8 would refuse whatever
        the message holds: a signer the signature budget does not check now (while a keyless flood forges a car,
        each forgery then costs the door its header read, not two copies of its payload). Anything this cannot
        read goes on to the full decode."""
        spans = envelope_spans(data)
        if spans is None:
            return
        if b"mac" not in spans or b"payload" not in spans:
            raise _not_signed()
        key_id, alg = spans.get(b"key_id"), spans.get(b"alg")
        if key_id is not None and key_id[0] in _STR_HEADERS and (alg is None or alg[0] in _STR_HEADERS):
            try:
                kid = data[key_id[1] : key_id[2]].decode()
                algorithm = _DEFAULT_ALG if alg is None else data[alg[1] : alg[2]].decode()
            except UnicodeDecodeError:
                return
            if not self.keyring.knows(kid, algorithm):
                raise _no_key(kid, algorithm)
            if not self.budget.allow(kid):  # it would be refused at step 8 whatever it holds: not even copied out
                raise self.budget.error(kid)
        header, start, end = spans[b"payload"]
        if header in _BIN_HEADERS and (start == end or data[start] not in _MAP_FIRST_BYTES):
            raise _not_a_frame()

    def _refuse_old(self, sender: str, key: bytes | None, claimed: tuple[float, int]) -> None:
        newest = self._newest(sender, key)
        if newest is None:
            return
        if claimed <= newest:
            raise WireError(
                409, "replayed", f"(stamp, seq) {claimed} is not newer than the last accepted {newest}", "stamp"
            )
