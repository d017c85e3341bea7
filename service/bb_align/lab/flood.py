"""A keyless on-air flooder for ``bb-align soak``: junk published over Zenoh as fast as one local publisher can.

It holds no key. What it sends is what anyone in radio range can make:

- ``byte``: 1-byte garbage on the ego's and the peers' own frame keys (the most messages per second);
- ``zero_mac_hmac``: a large HMAC envelope with an all-zero MAC under the fleet key id;
- ``zero_mac_ed25519``: a large Ed25519 envelope with an all-zero signature and a genuine vehicle certificate
  copied from the air (certificates are public: every signed frame carries one), so the certificate verifies;
- ``forged_frame``: like ``zero_mac_ed25519`` but the payload is a frame-shaped map with a fresh stamp and a seq far
  ahead, so nothing short of the signature check (SHA-512 over the whole payload) can refuse it: the costliest
  junk a keyless sender can make;
- ``unsigned``: a large unsigned frame-shaped map;
- ``forged_frame_random_sig``: the same with 64 random bytes for the signature;
- ``replay``: genuine signed frames recorded from the air earlier in the run, sent again byte for byte (or, with
  ``query_key``, sent as align queries on that key; the replies are counted, signed or not).

``kinds`` picks the large kinds, ``big_per_s`` / ``replays_per_s`` pace them (0: as fast as the publisher goes).

It runs in its own process (``python -m bb_align.lab.flood``, instructions as one JSON line on stdin), so it
competes with the service for CPU as a co-located attacker would, but never for the soak's GIL. It prints one
``ready`` line once its publishers reach a subscriber, floods for ``duration_s`` (bounded), then prints its counts
as one JSON line.
"""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
import threading
import time
from collections import Counter
from typing import Literal

import msgpack
from pydantic import BaseModel, Field

from bb_align.protocol import Limits, peek_signed

BIG_KINDS = ("zero_mac_hmac", "zero_mac_ed25519", "forged_frame", "unsigned")
ALL_BIG_KINDS = (*BIG_KINDS, "forged_frame_random_sig")
NEEDS_CERT = ("zero_mac_ed25519", "forged_frame", "forged_frame_random_sig")


class FloodConfig(BaseModel):
    """What the flooder sends and for how long (every number of the flood in one place)."""

    duration_s: float = Field(60.0, gt=0, le=3600, description="seconds of flooding, then it stops by itself")
    small_per_cycle: int = Field(200, ge=0, description="1-byte messages per cycle (round-robin over the target keys)")
    big_per_cycle: int = Field(1, ge=0, description="large envelopes per cycle (round-robin over kinds and keys)")
    big_bytes: int = Field(1 << 20, ge=1, description="payload bytes of each large envelope")
    replays_per_cycle: int = Field(20, ge=0, description="recorded genuine frames sent again per cycle")
    ready_timeout_s: float = Field(30.0, gt=0, description="longest wait for the service's subscriber")
    kinds: list[Literal[ALL_BIG_KINDS]] = Field(list(BIG_KINDS), min_length=1, description="large kinds, in turn")
    big_per_s: float = Field(0.0, ge=0, description="pace of the large envelopes (0: as fast as the publisher goes)")
    replays_per_s: float = Field(0.0, ge=0, description="pace of the replays (0: as fast as the publisher goes)")
    query_key: str | None = Field(None, description="send the replays as queries on this key (e.g. bbalign/align/ego)")


def _envelope(key_id: str, alg: str, mac: bytes, payload: bytes, cert: bytes | None = None) -> bytes:
    env = {"schema_version": 1, "key_id": key_id, "alg": alg, "mac": mac, "payload": payload}
    if cert is not None:
        env["cert"] = cert
    return msgpack.packb(env, use_bin_type=True)


def big_junk(kind: str, vehicle_id: str, big_bytes: int, cert: bytes | None) -> bytes:
    """One large junk message of ``kind`` aimed at ``vehicle_id``'s frame key."""
    blob = b"\0" * big_bytes
    if kind == "zero_mac_hmac":
        return _envelope("fleet", "hmac-sha256", b"\0" * 32, blob)
    if kind == "zero_mac_ed25519":
        return _envelope(vehicle_id, "ed25519", b"\0" * 64, blob, cert)
    frame = {"schema_version": 1, "vehicle_id": vehicle_id, "seq": 1 << 62, "stamp": time.time(), "png": blob}
    if kind in ("forged_frame", "forged_frame_random_sig"):
        mac = b"\0" * 64 if kind == "forged_frame" else os.urandom(64)
        return _envelope(vehicle_id, "ed25519", mac, msgpack.packb(frame, use_bin_type=True), cert)
    if kind == "unsigned":
        return msgpack.packb(frame, use_bin_type=True)
    raise ValueError(kind)


def flood(
    endpoint: str,
    prefix: str,
    targets: dict[str, bytes | None],
    config: FloodConfig,
    recorded: list[tuple[str, bytes]] = (),
) -> dict:
    """Flood ``<prefix>/frames/<id>`` for each target id (id -> its public certificate, copied from the air, or
    None) from one Zenoh session, replaying ``recorded`` (vehicle id, genuine signed frame) too; returns what was
    put, by kind. Blocking puts: every message put reaches the receiver's link, so the rate is what a local
    publisher really delivers."""
    import zenoh

    from bb_align.protocol import ZenohSettings, frames_key

    ids = sorted(targets)
    cfg = ZenohSettings(listen=[], connect=[endpoint], prefix=prefix).to_zenoh_config()
    sent, nbytes = Counter(), Counter()
    with zenoh.open(cfg) as session:
        pubs = {
            vid: session.declare_publisher(frames_key(prefix, vid), congestion_control=zenoh.CongestionControl.BLOCK)
            for vid in ids
        }
        deadline = time.monotonic() + config.ready_timeout_s
        while not all(p.matching_status.matching for p in pubs.values()) and time.monotonic() < deadline:
            time.sleep(0.02)
        big = [(k, vid) for vid in ids for k in config.kinds if targets[vid] or k not in NEEDS_CERT]
        replays = [(vid, data) for vid, data in recorded if vid in pubs]
        replies, put_replay = Counter(), _replayer(session, pubs, config.query_key)
        print("ready", flush=True)
        t0, cpu0 = time.perf_counter(), time.process_time()
        end, i, r = t0 + config.duration_s, 0, 0
        while time.perf_counter() < end:
            for j in range(config.small_per_cycle):
                pubs[ids[j % len(ids)]].put(b"\xc1")  # 0xc1: never valid msgpack
            sent["byte"] += config.small_per_cycle
            nbytes["byte"] += config.small_per_cycle
            for _ in range(config.big_per_cycle if big and _due(t0, i, config.big_per_s) else 0):
                kind, vid = big[i % len(big)]
                data = big_junk(kind, vid, config.big_bytes, targets[vid])  # fresh stamps
                pubs[vid].put(data)
                sent[kind] += 1
                nbytes[kind] += len(data)
                i += 1
            for _ in range(config.replays_per_cycle if replays and _due(t0, r, config.replays_per_s) else 0):
                vid, data = replays[r % len(replays)]
                put_replay(vid, data, replies)
                sent["replay"] += 1
                nbytes["replay"] += len(data)
                r += 1
            if config.small_per_cycle == 0:
                time.sleep(0.0005)  # paced kinds only: do not spin
        elapsed, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        time.sleep(2.0 if config.query_key else 0.0)  # the last replies come in
        for p in pubs.values():
            p.undeclare()
    total = sum(sent.values())
    return {
        "elapsed_s": elapsed,
        "messages": dict(sent),
        "bytes": dict(nbytes),
        "total_messages": total,
        "msg_per_s": total / elapsed,
        "mb_per_s": sum(nbytes.values()) / elapsed / 1e6,
        "cpu_cores": cpu / elapsed,  # the flooder's own CPU (it shares this machine's cores with the service)
        "query_replies": dict(replies),  # with query_key: replies by kind (signed_ok, signed_err, unsigned_err...)
    }


def _due(t0: float, n: int, per_s: float) -> bool:
    """Whether the ``n``-th paced message is due (always, unpaced)."""
    return per_s <= 0 or time.perf_counter() >= t0 + n / per_s


def _replayer(session, pubs: dict, query_key: str | None):
    """Send one recorded frame: put on its car's frame key, or asked as a query on ``query_key`` with its replies
    counted (the flooder does not wait for them: a replayer never does)."""
    lock, limits = threading.Lock(), Limits()

    def put(vid: str, data: bytes, replies: Counter) -> None:
        pubs[vid].put(data)

    def ask(vid: str, data: bytes, replies: Counter) -> None:
        def on_reply(reply) -> None:
            ok = reply.ok is not None
            payload = (reply.ok if ok else reply.err).payload.to_bytes()
            kind = ("signed_" if peek_signed(payload, limits) is not None else "unsigned_") + ("ok" if ok else "err")
            with lock:
                replies[kind] += 1

        session.get(query_key, on_reply, payload=data, timeout=5.0)

    return put if query_key is None else ask


class FloodProcess:
    """The flooder in a child process: ``start`` returns once it is flooding, ``finish`` its counts. Always
    ended: ``finish`` kills it when it overruns its own deadline."""

    def __init__(
        self,
        endpoint: str,
        prefix: str,
        targets: dict[str, bytes | None],
        config: FloodConfig,
        recorded: list[tuple[str, bytes]] = (),
    ):
        self.config = config
        b64 = lambda b: base64.b64encode(b).decode()  # noqa: E731
        self._arg = {
            "endpoint": endpoint,
            "prefix": prefix,
            "targets": {k: None if v is None else b64(v) for k, v in targets.items()},
            "config": config.model_dump(),
            "recorded": [(vid, b64(data)) for vid, data in recorded],
        }
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        """The child reads its instructions on stdin (recorded frames can be megabytes: not for argv)."""
        argv = [sys.executable, "-m", "bb_align.lab.flood"]
        self.proc = subprocess.Popen(
            argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        self.proc.stdin.write(json.dumps(self._arg) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline().strip()  # bounded: the child gives up waiting after ready_timeout_s
        if line != "ready":
            self.proc.kill()
            _, err = self.proc.communicate(timeout=10)
            raise RuntimeError(f"the flooder did not start: {line!r} {err[-800:]}")

    def finish(self) -> dict:
        try:
            out, err = self.proc.communicate(timeout=self.config.duration_s + 30.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate(timeout=10)
        lines = [ln for ln in out.splitlines() if ln.startswith("{")]
        if self.proc.returncode != 0 or not lines:
            raise RuntimeError(f"the flooder failed ({self.proc.returncode}): {err[-800:]}")
        return json.loads(lines[-1])

    def stop(self) -> None:
        """End the child if it is still running (error paths)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


def _main() -> None:
    arg = json.loads(sys.stdin.readline())
    targets = {k: None if v is None else base64.b64decode(v) for k, v in arg["targets"].items()}
    recorded = [(vid, base64.b64decode(data)) for vid, data in arg["recorded"]]
    report = flood(arg["endpoint"], arg["prefix"], targets, FloodConfig(**arg["config"]), recorded)
    print(json.dumps(report), flush=True)


if __name__ == "__main__":
    _main()
