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
envelopes. Recorded per phase: results per car, ``stale_ego_frame`` results, service CPU (cores, in total and per
thread group from /proc/<pid>/task: Zenoh's rx-N, tx-N and other threads, the door thread, the Python threads:
engine workers, gate, REST), the cores of the cars' side (this process) and of the flooders, the load average, and
RSS. A phase's results are those for the frames sent in it (by their stamps) published by 2 s after its end,
the same for the baseline and the flood (the flooders go on 3 s past the phase); ``kept`` is the flood's over
the baseline's, per car (``kept_per_frame_sent``: the same per frame sent, for a machine so busy that the
streams skip ticks). Prints and writes JSON, then a summary table; ``--plot`` draws results kept per car.

``--pin`` models a vehicle, where the flooders are other computers: the service process (every thread, with Zenoh's
receive threads and the door) on CPU 1, this process (ego, cars, listener) and the flooders on CPU 0, for the
baseline and the flood alike. ``--repeat N`` runs every case N times (the machine may be shared).
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
SERVICE_CPUS, CARS_CPUS = {1}, {0}  # --pin: the service on a core of its own, the senders on the other
SIZES = {  # FloodConfig fields per flood size
    "small": {"small_per_cycle": 200, "big_per_cycle": 0},
    "big": {"small_per_cycle": 0, "big_per_cycle": 1},
}


def _outcome(data: bytes) -> tuple[str, float | None]:
    """A result's outcome, read without checking its signature (the listener holds no key): "success" or its
    reason, and its peer frame's stamp (time.time() when it was sent)."""
    import msgpack

    from bb_align.protocol import Limits, peek_signed

    env = peek_signed(data, Limits())
    body = msgpack.unpackb(env.payload if env is not None else data, raw=False)
    stamp = body.get("peer_stamp")
    stamp = float(stamp) if isinstance(stamp, int | float) else None
    return ("success" if body.get("success") else str(body.get("reason"))), stamp


def pin(pid: int, cpus: set[int]) -> None:
    """Every thread of ``pid`` onto ``cpus`` (threads it starts later inherit the affinity of their creator)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            os.sched_setaffinity(int(tid), cpus)
        except (ProcessLookupError, FileNotFoundError):
            pass  # the thread ended meanwhile


def _group(comm: str) -> str:
    """A thread's group by its OS name: Zenoh names its runtimes' threads (rx-0, tx-0, app-0, net-0, acc-0), the
    service names its door and query threads; the rest are Python threads (engine workers, gate, REST)."""
    if comm.startswith("bbalign-"):
        return comm.removeprefix("bbalign-")
    head = comm.split("-", 1)[0]
    if head in ("rx", "tx"):
        return f"zenoh_{head}"
    if head in ("app", "net", "acc", "zenoh"):
        return "zenoh_other"
    return "python"


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds (user + system) per thread group of ``pid``, and ``sys`` (the kernel's part, all threads) and
    ``total`` (the whole process, threads that ended included)."""
    tick = os.sysconf("SC_CLK_TCK")
    out: Counter = Counter()
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            comm = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
            fields = Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue
        utime, stime = int(fields[11]) / tick, int(fields[12]) / tick  # stat fields 14 and 15
        out[_group(comm)] += utime + stime
        out["sys"] += stime
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    out["total"] = (int(fields[11]) + int(fields[12])) / tick
    return dict(out)


def _cores(before: dict, after: dict, seconds: float) -> dict[str, float]:
    return {k: round((after.get(k, 0.0) - before.get(k, 0.0)) / seconds, 3) for k in sorted(after)}


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
        outcome, stamp = _outcome(sample.payload.to_bytes())
        now = time.time()
        with self.lock:
            self.results.append((now, car, outcome, stamp))

    def run(self, seconds: float) -> tuple[float, float]:
        """Publish for ``seconds`` (the ego, car1, car2 once per 0.1 s tick); (start, end) of the phase, wall
        clock (the frames' stamps)."""
        from bb_align_client import encode_frame
        from service_support import RANGE_M

        t0, w0 = time.monotonic(), time.time()
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
        return w0, time.time()

    def count(self, t0: float, t1: float, until: float) -> dict:
        """The results for the frames sent in [t0, t1) (by their stamps) that arrived by ``until``."""
        with self.lock:
            got = [r for r in self.results if r[3] is not None and t0 <= r[3] < t1 and r[0] < until]
        per_car = Counter(r[1] for r in got)
        reasons = Counter(r[2] for r in got)
        lat = sorted(r[0] - r[3] for r in got)
        pct = lambda q: round(lat[min(len(lat) - 1, int(q * len(lat)))] * 1e3) if lat else None  # noqa: E731
        return {
            "results": {c: per_car[c] for c in CARS},
            "outcomes": dict(reasons),
            "latency_ms_p50_p90": [pct(0.5), pct(0.9)],
        }


def phase(streams: Streams, svc, seconds: float, settle_s: float, pinned: bool = False) -> dict:
    """One phase: stream for ``seconds``, count the results for the frames sent in it (by their stamps) published
    by ``settle_s`` after its end (the same for the baseline and the flood: the flood goes on meanwhile), with
    the service's CPU (per thread group) and RSS over it, this process's CPU (the ego, the cars and the listener)
    and the load average."""
    if pinned:  # threads the service started since the last phase inherit CPU 1; this is belt and braces
        pin(svc.pid, SERVICE_CPUS)
    cpu0, w0, peers0, door0 = svc.cpu_seconds(), time.monotonic(), svc.get("/v1/peers"), _door_refused(svc)
    thr0, own0, load0 = thread_cpu(svc.pid), _own_cpu(), os.getloadavg()[0]
    t0, t1 = streams.run(seconds)
    cpu1, w1 = svc.cpu_seconds(), time.monotonic()
    thr1, own1 = thread_cpu(svc.pid), _own_cpu()
    time.sleep(settle_s)
    out = streams.count(t0, t1, t1 + settle_s)
    peers1 = svc.get("/v1/peers")
    out["frames_accepted"] = {
        c: peers1.get(c, {}).get("frames_accepted", 0) - peers0.get(c, {}).get("frames_accepted", 0) for c in CARS
    }
    out["frames_dropped"] = {
        c: peers1.get(c, {}).get("frames_dropped", 0) - peers0.get(c, {}).get("frames_dropped", 0) for c in CARS
    }
    out["frames_sent"] = streams.ticks
    out["door_refused_per_s"] = round((_door_refused(svc) - door0) / (time.monotonic() - w0), 1)
    out["results_per_s"] = {c: round(n / seconds, 3) for c, n in out["results"].items()}
    out["stale_ego_frame"] = out["outcomes"].get("stale_ego_frame", 0)
    out["service_cores"] = round((cpu1 - cpu0) / (w1 - w0), 3)
    out["service_threads_cores"] = _cores(thr0, thr1, w1 - w0)
    out["cars_side_cores"] = round((own1 - own0) / (w1 - w0), 3)
    out["load_avg_1min"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    out["service_rss_mb"] = svc.memory_mb().get("rss_mb")
    return out


def _own_cpu() -> float:
    t = os.times()
    return t.user + t.system


def _door_refused(svc) -> float:
    """Messages the service's Zenoh door refused so far (bbalign_door_refused_total, every error)."""
    import httpx

    text = httpx.get(svc.rest + "/metrics", timeout=10).text
    return sum(float(ln.rsplit(" ", 1)[1]) for ln in text.splitlines() if ln.startswith("bbalign_door_refused_total{"))


def run_case(streams, svc, ep: str, size: str, n: int, seconds: float, pinned: bool, blocks: int = 1) -> dict:
    """``blocks`` times a baseline phase then a flood phase (alternating, so both see the same background load of
    a shared machine); counts summed over the blocks, rates averaged."""
    from bb_align.lab.flood import FloodConfig, FloodProcess

    bases, floods, put = [], [], []
    for _ in range(blocks):
        bases.append(phase(streams, svc, seconds, 2.0, pinned))
        cfg = FloodConfig(duration_s=seconds + 3.0, replays_per_cycle=0, **SIZES[size])
        flooders = [FloodProcess(ep, "bbalign", {"ego": None, "car1": None, "car2": None}, cfg) for _ in range(n)]
        try:
            for f in flooders:
                f.start()
            floods.append(phase(streams, svc, seconds, 2.0, pinned))  # the flooders go on 3 s past the phase
            put += [f.finish() for f in flooders]
        finally:
            for f in flooders:
                f.stop()
        time.sleep(3.0)  # the flood's last messages drain before the next baseline
    base, flood = _merge(bases), _merge(floods)
    kept = {
        c: round(flood["results"][c] / base["results"][c], 3) if base["results"][c] else None for c in CARS
    }  # fmt: skip
    rate = lambda ph, c: ph["results"][c] / max(1, ph["frames_sent"])  # noqa: E731
    return {
        "size": size,
        "flooders": n,
        "pinned": pinned,
        "blocks": blocks,
        "kept_per_frame_sent": {c: round(rate(flood, c) / rate(base, c), 3) if rate(base, c) else None for c in CARS},
        "no_flood": base,
        "flood": flood,
        "kept": kept,
        "kept_per_block": [
            {c: round(f["results"][c] / b["results"][c], 3) if b["results"][c] else None for c in CARS}
            for b, f in zip(bases, floods, strict=True)
        ],
        "flooders_put": [
            {
                "msg_per_s": round(p["msg_per_s"]),
                "mb_per_s": round(p["mb_per_s"], 1),
                "cpu_cores": round(p["cpu_cores"], 2),
            }
            for p in put
        ],  # fmt: skip
    }


def _merge(phases: list[dict]) -> dict:
    """Phases as one: integer counts summed, other numbers averaged, the load average's first and last."""
    first = phases[0]
    out: dict = {}
    for key, value in first.items():
        values = [ph.get(key) for ph in phases]
        if key == "load_avg_1min":
            out[key] = [first[key][0], phases[-1][key][1]]
        elif isinstance(value, dict):
            keys = sorted({k for v in values for k in v})
            out[key] = _merge([{k: v.get(k, 0) for k in keys} for v in values])
        elif isinstance(value, bool) or value is None:
            out[key] = value
        elif isinstance(value, int):
            out[key] = sum(values)
        elif isinstance(value, float):
            out[key] = round(sum(values) / len(values), 3)
        elif isinstance(value, list):
            cols = [[v[i] for v in values if v[i] is not None] for i in range(len(value))]
            out[key] = [round(sum(c) / len(c)) if c else None for c in cols]
        else:
            out[key] = value
    return out


def plot(out: dict, path: Path) -> None:
    """Two panels per case: the cars' frames the service accepted during the flood (of those sent), and the
    results during the flood over the baseline just before it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = out["cases"]
    labels = [
        f"{c['size']}\n{c['flooders']} session{'s' if c['flooders'] > 1 else ''}"
        + (f"\nrun {c['run']}" if c.get("run") else "")
        for c in cases
    ]
    fig, axes = plt.subplots(1, 2, figsize=(2.2 * len(cases) + 2, 4), sharey=True)
    width = 0.38
    for i, (car, how) in enumerate((("car1", "client publisher"), ("car2", "plain put"))):
        xs = [j + (i - 0.5) * width for j in range(len(cases))]
        accepted = [c["flood"]["frames_accepted"][car] / max(1, c["flood"]["frames_sent"]) for c in cases]
        axes[0].bar(xs, accepted, width, label=f"{car} ({how})")
        axes[1].bar(xs, [c["kept"][car] or 0.0 for c in cases], width, label=f"{car} ({how})")
    for ax, title in zip(
        axes, ("frames accepted during the flood / sent", "results: flood / baseline (alternating phases)"), strict=True
    ):
        ax.axhline(0.9, color="k", ls="--", lw=1)
        ax.set_xticks(range(len(cases)), labels, fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.set_ylim(0, max([1.15] + [1.05 * (k or 0) for c in cases for k in c["kept"].values()]))
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
    ap.add_argument("--pin", action="store_true", help="the service on CPU 1, the cars and flooders on CPU 0")
    ap.add_argument("--repeat", type=int, default=1, help="runs of every case")
    ap.add_argument(
        "--blocks", type=int, default=1, help="baseline and flood phases alternated this many times per case"
    )
    ap.add_argument("--limit", action="append", default=[], metavar="NAME=VALUE", help="a service Limits field")
    a = ap.parse_args()
    if a.pin:
        if not (SERVICE_CPUS | CARS_CPUS) <= os.sched_getaffinity(0):
            sys.exit(
                f"--pin needs CPUs {sorted(SERVICE_CPUS | CARS_CPUS)}; this process may use {os.sched_getaffinity(0)}"
            )
        pin(os.getpid(), CARS_CPUS)  # before any session or child: both inherit it

    import zenoh
    from tqdm import tqdm

    from bb_align.lab.harness import start_service
    from bb_align.protocol import ZenohSettings
    from bb_align_client import ZenohPeer
    from service_support import moving_pair, secure_settings

    cases = [(s, int(n), r) for r in range(1, a.repeat + 1) for s in a.sizes.split(",") for n in a.flooders.split(",")]
    out: dict = {
        "title": a.title,
        "command": " ".join(sys.argv),
        "seconds": a.seconds,
        "blocks": a.blocks,
        "pinned": {"service_cpus": sorted(SERVICE_CPUS), "cars_and_flooders_cpus": sorted(CARS_CPUS)}
        if a.pin
        else None,
        "cpus": os.cpu_count(),
        "load_avg_at_start": [round(x, 2) for x in os.getloadavg()],
        "zenoh_runtime": os.environ.get("ZENOH_RUNTIME"),
        "limits": a.limit,
        "cases": [],
    }
    with tempfile.TemporaryDirectory() as log_dir:
        limits = {k: json.loads(v) for k, v in (x.split("=", 1) for x in a.limit)}
        svc = start_service(secure_settings(True, limits=limits), KEY, Path(log_dir), timeout_s=600)
        if a.pin:
            pin(svc.pid, SERVICE_CPUS)
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
                phase(streams, svc, 8.0, 2.0, a.pin)  # warm-up: tracks acquired, caches filled
                for size, n, run in tqdm(cases, desc="flood cases"):
                    case = run_case(streams, svc, ep[0], size, n, a.seconds, a.pin, a.blocks)
                    case["run"] = run if a.repeat > 1 else None
                    out["cases"].append(case)
                    print(json.dumps({k: case[k] for k in ("size", "flooders", "run", "kept")}), file=sys.stderr)
                out["peers"] = {
                    k: {kk: v[kk] for kk in ("frames_accepted", "frames_dropped", "results")}
                    for k, v in svc.get("/v1/peers").items()
                }  # fmt: skip
                sub.undeclare()
        finally:
            out["exit_code"] = svc.stop()
    out["load_avg_at_end"] = [round(x, 2) for x in os.getloadavg()]
    text = json.dumps(out, indent=1)
    print(text)
    if a.json:
        a.json.write_text(text + "\n")
    if a.plot:
        plot(out, a.plot)
    print(summary(out))


def summary(out: dict) -> str:
    """One line per case: kept per car, the cores of each side in the flood (baseline in brackets), RSS, load."""
    pinned = out["pinned"]
    lines = [
        f"{out['title']}: {out['seconds']} s per phase, {out.get('blocks', 1)} block(s) per case, "
        + (
            f"service on CPU {pinned['service_cpus']}, cars and flooders on CPU {pinned['cars_and_flooders_cpus']}"
            if pinned
            else "unpinned (every process on every core)"
        )  # fmt: skip
        + f"; load average {out['load_avg_at_start']} at start, {out['load_avg_at_end']} at end",
        "size  sess run | kept car1 car2 (target 0.9) | service cores flood (base): total, zenoh rx, door, python,"
        " sys | cars side | flooders | RSS MB | load 1-min",
    ]
    for c in out["cases"]:
        f, b = c["flood"], c["no_flood"]
        ft, bt = f["service_threads_cores"], b["service_threads_cores"]
        kept = " ".join(f"{c['kept'][car]:.3f}" if c["kept"][car] is not None else "  -  " for car in CARS)
        lines.append(
            f"{c['size']:5s} {c['flooders']:4d} {c.get('run') or 1:3d} | {kept:>14s} {'':13s}| "
            f"{f['service_cores']:.2f} ({b['service_cores']:.2f}), "
            + ", ".join(f"{ft.get(k, 0):.2f} ({bt.get(k, 0):.2f})" for k in ("zenoh_rx", "door", "python", "sys"))
            + f" | {f['cars_side_cores']:.2f} ({b['cars_side_cores']:.2f})"
            f" | {sum(p['cpu_cores'] for p in c['flooders_put']) / c.get('blocks', 1):.2f}"
            f" | {f['service_rss_mb']}"
            f" | {b['load_avg_1min'][0]}-{f['load_avg_1min'][1]}"
        )
        if "kept_per_frame_sent" in c:  # a busy machine skips ticks: results per frame sent, flood / baseline
            per_sent = " ".join(f"{c['kept_per_frame_sent'][car] or 0:.3f}" for car in CARS)
            lines.append(f"{'':15s}| kept per frame sent: {per_sent}")
        if c.get("blocks", 1) > 1:
            per = "; ".join(" ".join(f"{k[car] or 0:.2f}" for car in CARS) for k in c["kept_per_block"])
            lines.append(f"{'':15s}| kept per block: {per}")
    return "\n".join(lines)


class _Signing:
    """car2's sender: a plain ``session.put`` of the signed frame (no ZenohPeer publisher)."""

    def __init__(self, session, key: str):
        from bb_align_client import sign_frame

        self.session, self.key, self._sign = session, key, sign_frame

    def put(self, key_expr: str, frame: bytes) -> None:
        self.session.put(key_expr, self._sign(frame, self.key))


if __name__ == "__main__":
    main()
