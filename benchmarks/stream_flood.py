"""Signed cars' results with and without keyless flooders, each its own process and Zenoh session (issue 31, F7).

    .venv/bin/python benchmarks/stream_flood.py --seconds 20 --flooders 2

A `bb-align serve` child process (fleet key, 2 workers, tracking on); the ego and two cars publish signed frames at
10 Hz with the client's default publisher (ZenohPeer: congestion control DROP), the cars' frames from the
synthetic street (tests/service_support.moving_pair). A keyless session counts the results published on
poses/ego/*. Phase 1: no flood; phase 2: ``--flooders`` FloodProcess children (bb_align.lab.flood: 1-byte junk,
1 MB zero-MAC envelopes, on the ego's and the cars' frame keys, as fast as each publisher goes). Prints JSON."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

KEY = "bench-fleet-key-0123456789abcdef"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--flooders", type=int, default=2)
    a = ap.parse_args()

    import zenoh

    from bb_align.lab.flood import FloodConfig, FloodProcess
    from bb_align.lab.harness import start_service
    from bb_align.protocol import ZenohSettings
    from bb_align_client import ZenohPeer, encode_frame
    from service_support import RANGE_M, moving_pair, secure_settings

    frames = moving_pair(20)
    settings = secure_settings(True)
    out = {"seconds": a.seconds, "flooders": a.flooders, "phases": {}}
    with tempfile.TemporaryDirectory() as log_dir:
        svc = start_service(settings, KEY, Path(log_dir), timeout_s=120)
        ep = [svc.zenoh_endpoint]
        results: list[tuple[float, str]] = []
        lock = threading.Lock()

        def on_result(sample) -> None:
            with lock:
                results.append((time.monotonic(), str(sample.key_expr).rsplit("/", 1)[-1]))

        try:
            with (
                zenoh.open(ZenohSettings(listen=[], connect=ep).to_zenoh_config()) as listener,
                ZenohPeer("ego", connect=ep, key=KEY, verify_answers=False) as ego,
                ZenohPeer("car1", connect=ep, key=KEY, verify_answers=False) as car1,
                ZenohPeer("car2", connect=ep, key=KEY, verify_answers=False) as car2,
            ):
                sub = listener.declare_subscriber("bbalign/poses/ego/*", on_result)
                assert all(c.wait_for_subscriber(10) for c in (ego, car1, car2))
                seq = 0

                def stream(seconds: float) -> dict:
                    nonlocal seq
                    t0 = time.monotonic()
                    sent = 0
                    while time.monotonic() - t0 < seconds:
                        _, e, p = frames[seq % len(frames)]
                        t = time.time()
                        for car, name, cloud in ((ego, "ego", e), (car1, "car1", p), (car2, "car2", p)):
                            car.publish(
                                encode_frame(
                                    cloud.points, cloud.boxes, vehicle_id=name, stamp=t, seq=seq, range_m=RANGE_M
                                )  # fmt: skip
                            )
                        sent += 2
                        seq += 1
                        time.sleep(max(0.0, t0 + seq_step(t0) - time.monotonic()))
                    time.sleep(3.0)  # the last results
                    with lock:
                        got = [r for r in results if r[0] >= t0]
                    return {"peer_frames_sent": sent, "results": len(got), "results_per_s": len(got) / seconds}

                def seq_step(t0: float) -> float:
                    return (int((time.monotonic() - t0) / 0.1) + 1) * 0.1

                stream(3.0)  # warm-up
                out["phases"]["no_flood"] = stream(a.seconds)
                flooders = [
                    FloodProcess(
                        ep[0],
                        "bbalign",
                        {"ego": None, "car1": None, "car2": None},
                        FloodConfig(duration_s=a.seconds + 2.0, replays_per_cycle=0),
                    )  # fmt: skip
                    for _ in range(a.flooders)
                ]
                try:
                    for f in flooders:
                        f.start()
                    out["phases"]["flood"] = stream(a.seconds)
                    out["flood"] = [f.finish() for f in flooders]
                finally:
                    for f in flooders:
                        f.stop()
                out["peers"] = svc.get("/v1/peers")
                out["peers"] = {k: {kk: v[kk] for kk in ("frames_accepted", "frames_dropped", "results")}
                                for k, v in out["peers"].items()}  # fmt: skip
                sub.undeclare()
        finally:
            out["exit_code"] = svc.stop()
    base, fl = out["phases"]["no_flood"]["results_per_s"], out["phases"]["flood"]["results_per_s"]
    out["results_kept"] = round(fl / base, 3) if base else None
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
