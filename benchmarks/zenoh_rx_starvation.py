"""Why two keyless flooding sessions starved the signed cars (issue 31, F7): Zenoh alone, no service.

    .venv/bin/python benchmarks/zenoh_rx_starvation.py --mode fifo --flooders 2
    ZENOH_RUNTIME='(rx: (worker_threads: 6))' \
        .venv/bin/python benchmarks/zenoh_rx_starvation.py --mode fifo --flooders 3

A subscriber session listens on ``bbalign/frames/*`` and a Python thread drains its handler like the service's door
(20 us of CPU per junk message, then 1 ms asleep: the door's 2 % CPU budget); a car session publishes a 20 kB
message at 10 Hz with congestion control DROP (the client's default). ``--flooders`` processes, each its own
session, put 1-byte junk on frames/ego, car1, car2 as fast as their blocking publishers go. ``--mode``: ``fifo``
(the old door: ``FifoChannel(16)``, whose callback blocks Zenoh's receive thread when full), ``ring``
(``RingChannel(16)``: drops the oldest), and ``ds-fifo`` / ``ds-ring`` with Zenoh's ingress downsampling on
frames/* at 50 Hz per remote session (the fix). Prints JSON: car messages received of sent, before and during the
flood, junk reaching Python per second, the subscriber process's CPU."""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import threading
import time

FLOODER = r"""
import json, sys, time, zenoh
ep, secs = sys.argv[1], float(sys.argv[2])
c = zenoh.Config(); c.insert_json5("mode", '"peer"'); c.insert_json5("connect/endpoints", json.dumps([ep]))
c.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(c) as s:
    pubs = [s.declare_publisher(f"bbalign/frames/{k}", congestion_control=zenoh.CongestionControl.BLOCK)
            for k in ("ego", "car1", "car2")]
    time.sleep(1.0)
    n, t0 = 0, time.monotonic()
    while time.monotonic() - t0 < secs:
        for i in range(200):
            pubs[i % 3].put(b"\xc1")
        n += 200
    print(json.dumps({"msgs": n, "rate": n / (time.monotonic() - t0)}))
"""


def _config(listen=(), connect=(), extra=None):
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", json.dumps(list(listen)))
    c.insert_json5("connect/endpoints", json.dumps(list(connect)))
    c.insert_json5("scouting/multicast/enabled", "false")
    for k, v in (extra or {}).items():
        c.insert_json5(k, json.dumps(v))
    return c


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", choices=("fifo", "ring", "ds-fifo", "ds-ring"), default="fifo")
    ap.add_argument("--flooders", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=10.0)
    a = ap.parse_args()

    import zenoh

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    extra = {}
    if a.mode.startswith("ds"):
        rule = {"key_expr": "bbalign/frames/*", "freq": 50.0}
        extra["downsampling"] = [{"flows": ["ingress"], "messages": ["put"], "rules": [rule]}]
    svc = zenoh.open(_config(listen=[ep], extra=extra))
    ring = a.mode.endswith("ring")
    sub = svc.declare_subscriber(
        "bbalign/frames/*", zenoh.handlers.RingChannel(16) if ring else zenoh.handlers.FifoChannel(16)
    )
    got = {"car1": 0, "junk": 0}

    def drain() -> None:
        while True:
            try:
                sample = sub.handler.recv()
            except zenoh.ZError:
                return
            if sample.payload.to_bytes().startswith(b"car1"):
                got["car1"] += 1
                continue
            got["junk"] += 1
            t = time.thread_time()
            while time.thread_time() - t < 20e-6:  # the door's check of one junk message
                pass
            time.sleep(0.001)  # its CPU budget

    door = threading.Thread(target=drain, daemon=True)
    door.start()
    car = zenoh.open(_config(connect=[ep]))
    pub = car.declare_publisher("bbalign/frames/car1", congestion_control=zenoh.CongestionControl.DROP)
    time.sleep(1.0)

    def run(seconds: float) -> dict:
        g0, j0, sent, t0 = got["car1"], got["junk"], 0, time.monotonic()
        while time.monotonic() - t0 < seconds:
            pub.put(b"car1" + b"x" * 20000)
            sent += 1
            time.sleep(0.1)
        time.sleep(1.0)
        return {"sent": sent, "car1_got": got["car1"] - g0, "junk_per_s": round((got["junk"] - j0) / seconds)}

    base = run(a.seconds / 2)
    procs = [
        subprocess.Popen([sys.executable, "-c", FLOODER, ep, str(a.seconds + 1)], stdout=subprocess.PIPE)
        for _ in range(a.flooders)
    ]
    try:
        time.sleep(1.5)
        cpu0 = time.process_time()
        flood = run(a.seconds)
        cores = (time.process_time() - cpu0) / (a.seconds + 1.0)
        rates = [round(json.loads(p.communicate(timeout=60)[0])["rate"]) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(10)
    sub.undeclare()
    door.join(5)
    car.close()
    svc.close()
    print(json.dumps({
        "mode": a.mode, "flooders": a.flooders, "no_flood": base, "flood": flood,
        "flooders_put_msg_per_s": rates, "subscriber_cores": round(cores, 2),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
