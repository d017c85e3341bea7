"""A keyless flood of large Zenoh queries against a `bb-align serve` child process: the service's resident memory
(RSS) before, during and after, and whether a signed car's own queries are still answered (issue 31, F8).

    .venv/bin/python benchmarks/query_flood.py --seconds 25 --senders 2 --mb 4

Each sender is its own process with its own Zenoh session, sending queries of ``--mb`` MB of junk (just under the
service's message limit) on ``bbalign/align/ego`` as fast as Zenoh takes them, without waiting for the replies.
Meanwhile car1 (a fleet-key signer) asks for an alignment once a second. Prints one JSON document. ``--pin``: the
service process on CPU 1, this process and the senders on CPU 0 (as stream_flood.py --pin)."""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

KEY = "bench-fleet-key-0123456789abcdef"


def _junk(kind: str, nbytes: int) -> bytes:
    """``junk``: a msgpack map header and zeros (refused at the first look); ``envelope``: a well-formed
    HMAC-SHA256 envelope under the fleet key's id with a zero MAC (decoded and its MAC computed before refusal)."""
    import msgpack

    if kind == "junk":
        return b"\x81\xa3mac" + b"\0" * (nbytes - 5)
    payload = b"\0" * (nbytes - 200)
    return msgpack.packb({"key_id": "fleet", "alg": "hmac-sha256", "mac": b"\0" * 32, "payload": payload})


def _sender(endpoint: str, seconds: float, nbytes: int, kind: str, out) -> None:
    import zenoh

    from bb_align.protocol import ZenohSettings

    junk = _junk(kind, nbytes)
    sent, deadline = 0, time.monotonic() + seconds
    with zenoh.open(ZenohSettings(listen=[], connect=[endpoint]).to_zenoh_config()) as s:
        while time.monotonic() < deadline:
            s.get("bbalign/align/ego", lambda reply: None, payload=junk, timeout=2.0)
            sent += 1
    out.put(sent)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=25.0)
    ap.add_argument("--senders", type=int, default=2)
    ap.add_argument("--mb", type=float, default=4.0)
    ap.add_argument("--after", type=float, default=10.0, help="seconds watched after the flood")
    ap.add_argument("--kind", choices=("junk", "envelope"), default="envelope")
    ap.add_argument("--pin", action="store_true", help="the service on CPU 1, this process and the senders on CPU 0")
    a = ap.parse_args()

    from stream_flood import CARS_CPUS, SERVICE_CPUS, pin

    if a.pin:
        pin(os.getpid(), CARS_CPUS)  # the senders (spawned children) inherit it

    from bb_align.lab.harness import start_service
    from bb_align_client import ZenohPeer, encode_frame
    from service_support import RANGE_M, moving_pair, secure_settings

    limit = 4 * 1024 * 1024
    nbytes = min(int(a.mb * 1024 * 1024), limit - 1024)
    settings = secure_settings(True)
    with tempfile.TemporaryDirectory() as log_dir:
        svc = start_service(settings, KEY, Path(log_dir), timeout_s=120)
        if a.pin:
            pin(svc.pid, SERVICE_CPUS)
        load0 = os.getloadavg()[0]
        ep = svc.zenoh_endpoint
        _, ego, peer = moving_pair(1)[0]
        rss, asked, answered = [], 0, 0
        try:
            with ZenohPeer("car1", connect=[ep], key=KEY, block_when_congested=True) as car:
                time.sleep(1.0)
                t0 = time.monotonic()

                def sample(phase: str) -> None:
                    rss.append((round(time.monotonic() - t0, 1), phase, svc.memory_mb()["rss_mb"]))

                def ask(seq: int) -> None:
                    nonlocal asked, answered
                    asked += 1
                    frame = encode_frame(peer.points, peer.boxes, vehicle_id="car1", stamp=time.time(), seq=seq,
                                         range_m=RANGE_M)  # fmt: skip
                    try:
                        car.request_align(frame, "ego", timeout=5.0)
                        answered += 1
                    except Exception as e:  # noqa: BLE001  (a refusal is an answer too)
                        answered += type(e).__name__ in ("ServiceError", "FrameRefused")

                for i in range(3):
                    sample("before")
                    ask(i)
                    time.sleep(1.0)
                q = mp.get_context("spawn").Queue()
                procs = [mp.get_context("spawn").Process(target=_sender, args=(ep, a.seconds, nbytes, a.kind, q))
                         for _ in range(a.senders)]  # fmt: skip
                for p in procs:
                    p.start()
                flood_start = time.monotonic()
                seq = 3
                while time.monotonic() - flood_start < a.seconds:
                    sample("flood")
                    ask(seq)
                    seq += 1
                    time.sleep(1.0)
                sent = sum(q.get(timeout=60) for _ in procs)
                for p in procs:
                    p.join(30)
                after_start = time.monotonic()
                while time.monotonic() - after_start < a.after:
                    sample("after")
                    time.sleep(1.0)
                sample("after")
        finally:
            code = svc.stop()
    by = lambda ph: [r for _, p, r in rss if p == ph and r is not None]  # noqa: E731
    print(
        json.dumps(
            {
                "senders": a.senders,
                "kind": a.kind,
                "query_mb": round(nbytes / 2**20, 3),
                "seconds": a.seconds,
                "queries_sent": sent,
                "rss_mb": {
                    "before": max(by("before")),
                    "flood_max": max(by("flood")),
                    "after_end": by("after")[-1],
                },
                "car1_queries_answered": f"{answered}/{asked}",
                "pinned": a.pin,
                "load_avg_1min": [round(load0, 2), round(os.getloadavg()[0], 2)],
                "exit_code": code,
                "samples": rss,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
