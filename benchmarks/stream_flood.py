"""Signed cars' results with and without keyless flooders, each its own process and Zenoh session (issue 31, F7).

    .venv/bin/python benchmarks/stream_flood.py --seconds 15 --flooders 1,2,3 --sizes small,big \
        --json docs/security_stream_flood.json --plot docs/security_stream_flood.png

One `bb-align serve` child process (fleet key, 2 workers, tracking on) for the whole run. The ego and two cars
publish signed frames at 10 Hz, each its own Zenoh session: the ego and car1 with the client's default publisher
(ZenohPeer: congestion control DROP), car2 with a plain ``session.put`` (the senders as they are); the cars' frames
come from the synthetic street (tests/service_support.moving_pair). A keyless session counts the results
published on poses/ego/* and reads their outcome. Then, for each (flood size, number of flooding sessions): a
no-flood baseline right before the flood (the machine is shared: both see the same background load), then the same
time with N FloodProcess children (bb_align.lab.flood), each its own session, flooding the ego's and both cars'
frame keys as fast as its blocking publisher goes: ``small`` 1-byte junk, ``big`` 1 MB zero-MAC HMAC and unsigned
envelopes. Recorded per phase: results per car, ``stale_ego_frame`` results, service CPU (cores) and RSS. Prints
and writes JSON; ``--plot`` draws results kept per car.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

KEY = "bench-fleet-key-0123456789abcdef"
CARS = ("car1", "car2")
SIZES = {  # FloodConfig fields per flood size
    "small": {"small_per_cycle": 200, "big_per_cycle": 0},
    "big": {"small_per_cycle": 0, "big_per_cycle": 1},
}


def _outcome(data: bytes) -> str:
    """A result's outcome, read without checking its signature (the listener holds no key): "success" or its
    reason."""
    import msgpack

    from bb_align.protocol import Limits, peek_signed

    env = peek_signed(data, Limits())
    body = msgpack.unpackb(env.payload if env is not None else data, raw=False)
    return "success" if body.get("success") else str(body.get("reason"))


class Streams:
    """The ego and the cars at 10 Hz on their own thread; ``results`` (time, car, outcome) from the listener."""

    def __init__(self, frames, ego, car1, car2_session, key_prefix: str):
        self.frames, self.ego, self.car1, self.car2 = frames, ego, car1, car2_session
        self.car2_key = f"{key_prefix}/frames/car2"
        self.results: list[tuple[float, str, str]] = []
        self.sent: Counter = Counter()
        self.lock = threading.Lock()
        self.seq = self.ticks = 0

    def on_result(self, sample) -> None:
        car = str(sample.key_expr).rsplit("/", 1)[-1]
        outcome = _outcome(sample.payload.to_bytes())
        with self.lock:
            self.results.append((time.monotonic(), car, outcome))

    def run(self, seconds: float) -> tuple[float, float]:
        """Publish for ``seconds`` (the ego, car1, car2 once per 0.1 s tick); (start, end) of the phase."""
        from bb_align_client import encode_frame
        from service_support import RANGE_M

        t0 = time.monotonic()
        tick, self.ticks = 0, 0
        while time.monotonic() - t0 < seconds:
            late = time.monotonic() - (t0 + tick * 0.1)
            if late > 0.05:  # a busy machine: skip the tick as a car would, never a burst of stale frames
                tick += 1
                continue
            _, e, p = self.frames[self.seq % len(self.frames)]
            t = time.time()
            enc = lambda c, vid, t=t: encode_frame(
                c.points, c.boxes, vehicle_id=vid, stamp=t, seq=self.seq, range_m=RANGE_M
            )  # noqa: E731
            self.ego.publish(enc(e, "ego"))
            self.car1.publish(enc(p, "car1"))
            self.car2.put(self.car2_key, enc(p, "car2"))
            self.sent.update(("car1", "car2"))
            self.ticks += 1
            self.seq += 1
            tick += 1
            time.sleep(max(0.0, t0 + tick * 0.1 - time.monotonic()))
        return t0, time.monotonic()

    def count(self, t0: float, t1: float) -> dict:
        with self.lock:
            got = [r for r in self.results if t0 <= r[0] < t1]
        per_car = Counter(car for _, car, _ in got)
        reasons = Counter(outcome for _, _, outcome in got)
        return {"results": {c: per_car[c] for c in CARS}, "outcomes": dict(reasons)}


def phase(streams: Streams, svc, seconds: float, settle_s: float) -> dict:
    """One phase: stream for ``seconds``, count the results published from its start until ``settle_s`` after its
    end (the last frames' answers), with the service's CPU and RSS over it."""
    cpu0, w0, peers0, door0 = svc.cpu_seconds(), time.monotonic(), svc.get("/v1/peers"), _door_refused(svc)
    t0, t1 = streams.run(seconds)
    cpu1, w1 = svc.cpu_seconds(), time.monotonic()
    time.sleep(settle_s)
    out = streams.count(t0, t1 + settle_s)
    peers1 = svc.get("/v1/peers")
    out["frames_accepted"] = {
        c: peers1.get(c, {}).get("frames_accepted", 0) - peers0.get(c, {}).get("frames_accepted", 0) for c in CARS
    }
    out["frames_sent"] = streams.ticks
    out["door_refused_per_s"] = round((_door_refused(svc) - door0) / (time.monotonic() - w0), 1)
    out["results_per_s"] = {c: round(n / seconds, 3) for c, n in out["results"].items()}
    out["stale_ego_frame"] = out["outcomes"].get("stale_ego_frame", 0)
    out["service_cores"] = round((cpu1 - cpu0) / (w1 - w0), 3)
    out["service_rss_mb"] = svc.memory_mb().get("rss_mb")
    return out


def _door_refused(svc) -> float:
    """Messages the service's Zenoh door refused so far (bbalign_door_refused_total, every error)."""
    import httpx

    text = httpx.get(svc.rest + "/metrics", timeout=10).text
    return sum(float(ln.rsplit(" ", 1)[1]) for ln in text.splitlines() if ln.startswith("bbalign_door_refused_total{"))


def run_case(streams, svc, ep: str, size: str, n: int, seconds: float) -> dict:
    from bb_align.lab.flood import FloodConfig, FloodProcess

    base = phase(streams, svc, seconds, 2.0)
    cfg = FloodConfig(duration_s=seconds + 3.0, replays_per_cycle=0, **SIZES[size])
    flooders = [FloodProcess(ep, "bbalign", {"ego": None, "car1": None, "car2": None}, cfg) for _ in range(n)]
    try:
        for f in flooders:
            f.start()
        flood = phase(streams, svc, seconds, 0.0)
        put = [f.finish() for f in flooders]
    finally:
        for f in flooders:
            f.stop()
    time.sleep(3.0)  # the flood's last messages drain before the next baseline
    kept = {
        c: round(flood["results"][c] / base["results"][c], 3) if base["results"][c] else None for c in CARS
    }  # fmt: skip
    return {
        "size": size,
        "flooders": n,
        "no_flood": base,
        "flood": flood,
        "kept": kept,
        "flooders_put": [
            {
                "msg_per_s": round(p["msg_per_s"]),
                "mb_per_s": round(p["mb_per_s"], 1),
                "cpu_cores": round(p["cpu_cores"], 2),
            }
            for p in put
        ],  # fmt: skip
    }


def plot(out: dict, path: Path) -> None:
    """Two panels per case: the cars' frames the service accepted during the flood (of those sent), and the
    results during the flood over the baseline just before it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = out["cases"]
    labels = [f"{c['size']}\n{c['flooders']} session{'s' if c['flooders'] > 1 else ''}" for c in cases]
    fig, axes = plt.subplots(1, 2, figsize=(2.2 * len(cases) + 2, 4), sharey=True)
    width = 0.38
    for i, (car, how) in enumerate((("car1", "client publisher"), ("car2", "plain put"))):
        xs = [j + (i - 0.5) * width for j in range(len(cases))]
        accepted = [c["flood"]["frames_accepted"][car] / max(1, c["flood"]["frames_sent"]) for c in cases]
        axes[0].bar(xs, accepted, width, label=f"{car} ({how})")
        axes[1].bar(xs, [c["kept"][car] or 0.0 for c in cases], width, label=f"{car} ({how})")
    for ax, title in zip(
        axes, ("frames accepted during the flood / sent", "results: flood / baseline just before"), strict=True
    ):
        ax.axhline(0.9, color="k", ls="--", lw=1)
        ax.set_xticks(range(len(cases)), labels, fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.set_ylim(0, 1.15)
    axes[0].legend(loc="lower left", fontsize=8)
    fig.suptitle(out.get("title", "Signed cars under keyless Zenoh floods"), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=15.0, help="each phase (baseline, flood)")
    ap.add_argument("--flooders", default="1,2,3", help="numbers of flooding sessions, comma separated")
    ap.add_argument("--sizes", default="small,big", help="flood sizes: small (1 byte), big (1 MB)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--plot", type=Path, default=None)
    ap.add_argument("--title", default="Signed cars under keyless Zenoh floods")
    a = ap.parse_args()

    import zenoh
    from tqdm import tqdm

    from bb_align.lab.harness import start_service
    from bb_align.protocol import ZenohSettings
    from bb_align_client import ZenohPeer
    from service_support import moving_pair, secure_settings

    cases = [(s, int(n)) for s in a.sizes.split(",") for n in a.flooders.split(",")]
    out: dict = {"title": a.title, "seconds": a.seconds, "zenoh_runtime": os.environ.get("ZENOH_RUNTIME"), "cases": []}
    with tempfile.TemporaryDirectory() as log_dir:
        svc = start_service(secure_settings(True), KEY, Path(log_dir), timeout_s=600)
        ep = [svc.zenoh_endpoint]
        zcfg = lambda: ZenohSettings(listen=[], connect=ep).to_zenoh_config()  # noqa: E731
        try:
            with (
                zenoh.open(zcfg()) as listener,
                zenoh.open(zcfg()) as car2,
                ZenohPeer("ego", connect=ep, key=KEY, verify_answers=False) as ego,
                ZenohPeer("car1", connect=ep, key=KEY, verify_answers=False) as car1,
            ):
                streams = Streams(moving_pair(20), ego, car1, _Signing(car2, KEY), "bbalign")
                sub = listener.declare_subscriber("bbalign/poses/ego/*", streams.on_result)
                assert ego.wait_for_subscriber(10) and car1.wait_for_subscriber(10)
                time.sleep(1.0)
                phase(streams, svc, 8.0, 2.0)  # warm-up: tracks acquired, caches filled
                for size, n in tqdm(cases, desc="flood cases"):
                    case = run_case(streams, svc, ep[0], size, n, a.seconds)
                    out["cases"].append(case)
                    print(json.dumps({k: case[k] for k in ("size", "flooders", "kept")}), file=sys.stderr)
                out["peers"] = {
                    k: {kk: v[kk] for kk in ("frames_accepted", "frames_dropped", "results")}
                    for k, v in svc.get("/v1/peers").items()
                }  # fmt: skip
                sub.undeclare()
        finally:
            out["exit_code"] = svc.stop()
    text = json.dumps(out, indent=1)
    print(text)
    if a.json:
        a.json.write_text(text + "\n")
    if a.plot:
        plot(out, a.plot)


class _Signing:
    """car2's sender: a plain ``session.put`` of the signed frame (no ZenohPeer publisher)."""

    def __init__(self, session, key: str):
        from bb_align_client import sign_frame

        self.session, self.key, self._sign = session, key, sign_frame

    def put(self, key_expr: str, frame: bytes) -> None:
        self.session.put(key_expr, self._sign(frame, self.key))


if __name__ == "__main__":
    main()
