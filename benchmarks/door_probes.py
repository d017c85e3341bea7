"""Issue 47's attacker probes re-run against a live service: genuine cars' results before, during and after each.

    .venv/bin/python benchmarks/door_probes.py --seconds 10 --record

One `bb-align serve` child process (the vehicle profile with Ed25519 credentials made by ``bb-align keys`` for
the ego and three cars, 2 workers, loopback only) for the whole run. The ego, car1 and car2 publish signed frames
at 10 Hz (car1 with the client's publisher, car2 with a plain put), driving smoothly with odometry as the product
expects of a stream (``--no-odometry``: none, the tracks' weak case); a keyless session hears every answer on
``poses/ego/*``. car3 holds a credential but does not stream (an absent car). Each probe:
a baseline window, the attack for one window, then a window right after it (``--seconds`` each); a window's
results are those for the genuine frames sent in it (matched by car, stamp and seq) heard by 2 s after its end.

Probes (the attackers are their own processes: bb_align.lab.flood, and the REST flood's):

- ``forged_slow`` / ``forged_full``: 2 keyless sessions flooding 1 MB Ed25519 envelopes shaped like frames
  (fresh stamp, seq far ahead, car1's certificate copied from one of its real signed frames, a zero or a random
  signature, in turn) on car1's frame key, 3 per second per session or as fast as they go: car1 is the forged
  car, car2 the other car; ``forged_ego_slow``: the same at 3 per second on the ego's key with the ego's
  certificate;
- ``query_replay``: 2 keyless sessions asking ``align/ego`` with genuine frames recorded from car1 and car2 (the
  last 40 of each, byte for byte), about 190 per second each, not waiting for the replies (which they count);
- ``stale_absent``: 2 keyless sessions replaying 50 genuine frames of car3 stamped an hour ago on its frame key, as
  fast as they go;
- ``rest_flood``: 8 threads (a process of their own) posting car3's freshly signed frames (its own key) to
  ``/v1/align`` as fast as the service answers.

Recorded per window: results per second per genuine car, latency p50 / p90 (publish -> answer heard), outcomes,
the door's refusals; per probe: ``kept`` (during / baseline, after / baseline, per car and for both cars), and
what the ego signed for the attacker: signed answers on ``poses/ego/*`` for frames no genuine car sent, signed
query replies the replayers got, REST answers by status. Writes JSON (``--json``; ``--record``: docs/) and a
figure. A shared machine: the rates are what this machine gave with the background load recorded.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from collections import Counter, deque
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

ROOT = Path(__file__).resolve().parents[1]
CARS = ("car1", "car2")
PROBES = ("forged_slow", "forged_full", "forged_ego_slow", "query_replay", "stale_absent", "rest_flood")


class Listener:
    """Every answer heard on ``poses/ego/*``: (time heard, car, outcome, peer stamp, peer seq, signed)."""

    def __init__(self):
        self.heard: list[tuple] = []
        self.lock = threading.Lock()

    def on_sample(self, sample) -> None:
        import msgpack

        from bb_align.protocol import Limits, peek_signed

        data = sample.payload.to_bytes()
        env = peek_signed(data, Limits())
        body = msgpack.unpackb(env.payload if env is not None else data, raw=False)
        row = (time.time(), str(sample.key_expr).rsplit("/", 1)[-1], "success" if body.get("success") else
               str(body.get("reason")), body.get("peer_stamp"), body.get("peer_seq"), env is not None)  # fmt: skip
        with self.lock:
            self.heard.append(row)


class Streams:
    """The ego, car1 and car2 at 10 Hz (skipping a tick, never bursting, when late); ``sent`` (car, stamp, seq).

    The cars drive as the product expects of a stream: the frames replayed forwards then backwards, each car stopping
    and turning round as a car can (never a jump back to the first frame, which made every car re-acquire every
    2 s; lab.harness.to_and_fro_times) with their odometry (the
    true pose; ``odometry=False``: none, the track predicts from its own motion). Each frame's image is rasterised
    once; a tick re-stamps and signs it (the cars stand for other machines: the benchmark's own CPU stays small)."""

    def __init__(self, frames, ego, car1, car2_session, creds, odometry: bool = True):
        from bb_align.protocol import Pose
        from bb_align_client.encode import make_frame
        from service_support import RANGE_M

        self.ego, self.car1, self.car2, self.creds = ego, car1, car2_session, creds
        self.images = []  # per frame index: {car: wire Frame, stamp and seq set per tick}
        for _, e, p in frames:
            made = {}
            for vid, c in (("ego", e), *((car, p) for car in CARS)):
                odo = Pose.from_matrix(c.T_world_sensor) if odometry else None
                made[vid] = make_frame(c.points, c.boxes, vehicle_id=vid, stamp=0.0, odometry=odo, range_m=RANGE_M)
            self.images.append(made)
        self.sent: set[tuple[str, float, int]] = set()
        self.on_air: deque[tuple[str, bytes]] = deque(maxlen=80)  # the cars' last signed frames, as sent
        self.seq = 0

    def run(self, seconds: float) -> tuple[float, float]:
        from bb_align.lab.bench.throughput import loop_index
        from bb_align.protocol import pack
        from bb_align_client import sign_frame

        t0, w0, tick = time.monotonic(), time.time(), 0
        while time.monotonic() - t0 < seconds:
            if time.monotonic() - (t0 + tick * 0.1) > 0.05:
                tick += 1
                continue
            made, t = self.images[loop_index(self.seq, len(self.images))], time.time()
            signed = {
                c: sign_frame(pack(f.model_copy(update={"stamp": t, "seq": self.seq})), self.creds[c])
                for c, f in made.items()
            }
            self.ego.publish(signed["ego"])
            self.car1.publish(signed["car1"])  # signed bytes are published as they are
            self.car2.put("bbalign/frames/car2", signed["car2"])
            self.on_air.extend(signed.items())
            self.sent.update({("car1", t, self.seq), ("car2", t, self.seq)})
            self.seq += 1
            tick += 1
            time.sleep(max(0.0, t0 + tick * 0.1 - time.monotonic()))
        return w0, time.time()


def count(listener: Listener, sent: set, t0: float, t1: float, until: float) -> dict:
    """The answers to the genuine frames sent in [t0, t1), heard by ``until``."""
    with listener.lock:
        rows = [r for r in listener.heard if r[3] is not None and t0 <= r[3] < t1 and r[0] < until]
    mine = [r for r in rows if (r[1], r[3], r[4]) in sent]
    lat = sorted(r[0] - r[3] for r in mine)
    pct = lambda q: round(lat[min(len(lat) - 1, int(q * len(lat)))] * 1e3) if lat else None  # noqa: E731
    per_car = Counter(r[1] for r in mine)
    return {
        "results_per_s": {c: round(per_car[c] / (t1 - t0), 3) for c in CARS},
        "frames_sent": sum(1 for c, s, _ in sent if c == "car1" and t0 <= s < t1),
        "outcomes": dict(Counter(r[2] for r in mine)),
        "latency_ms_p50_p90": [pct(0.5), pct(0.9)],
    }


def foreign_signed(listener: Listener, sent: set, t0: float, t1: float) -> dict:
    """Signed answers heard on poses/ego/* in [t0, t1) (by time heard) for frames no genuine car sent, by car."""
    with listener.lock:
        rows = [r for r in listener.heard if t0 <= r[0] < t1 and r[5] and (r[1], r[3], r[4]) not in sent]
    return dict(Counter(f"{r[1]}:{r[2]}" for r in rows))


def door_refused(svc) -> dict:
    """bbalign_door_refused_total by error, the door's sleep (bbalign_door_throttled_seconds), signature counters."""
    import httpx

    text = httpx.get(svc.rest + "/metrics", timeout=10).text
    out: Counter = Counter()
    for ln in text.splitlines():
        if ln.startswith(("bbalign_door_refused_total{", "bbalign_signature", "bbalign_door_throttled")):
            out[ln.rsplit(" ", 1)[0]] += float(ln.rsplit(" ", 1)[1])
    return dict(out)


class RestFlood:
    """``threads`` threads posting car3's freshly signed frames to /v1/align until stopped, in a process of their
    own (as the other attackers: threads in this process would take the GIL from the genuine cars' senders, which
    then skip ticks: a measure of the benchmark, not of the service), the frames' images encoded once (encoding one
    per post, 8 threads took a core of this 2-core machine from everything else); statuses counted."""

    def __init__(self, rest: str, cred_path: Path, threads: int):
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        self.n, self.ready, self.stop_event, self.out = threads, ctx.Event(), ctx.Event(), ctx.Queue()
        self.proc = ctx.Process(
            target=_rest_flood, args=(rest, str(cred_path), threads, self.ready, self.stop_event, self.out)
        )

    def start(self) -> None:
        self.proc.start()
        if not self.ready.wait(120):
            raise RuntimeError("the REST flood process did not get ready")

    def finish(self) -> dict:
        self.stop_event.set()
        report = self.out.get(timeout=120)
        self.proc.join(30)
        return report

    def stop(self) -> None:
        self.stop_event.set()
        self.proc.join(30)
        if self.proc.is_alive():
            self.proc.kill()


def _rest_flood(rest: str, cred_path: str, threads: int, ready, stop_event, out) -> None:
    """The REST flood's process: ``threads`` threads, each posting /v1/align (car3's own key) as fast as the
    service answers, until ``stop_event``; puts its report on ``out``."""
    import httpx
    import msgpack

    from bb_align.protocol import Credential, pack_align_request
    from bb_align_client import encode_frame, sign_frame
    from service_support import RANGE_M, moving_pair

    cred = Credential.load(Path(cred_path))
    # frames encoded once (a frame's image is the costly part); each post gets a fresh stamp and seq, signed anew:
    # the attacker's own CPU stays small, as on a machine of its own, and what is measured is the service's
    encoded = [
        msgpack.unpackb(encode_frame(p.points, p.boxes, vehicle_id="car3", stamp=0.0, seq=0, range_m=RANGE_M))
        for _, _, p in moving_pair(20)
    ]
    status: Counter = Counter()
    lock, seqs = threading.Lock(), iter(range(10**6, 10**7))

    def run() -> None:
        with httpx.Client(base_url=rest, timeout=30.0) as http:
            while not stop_event.is_set():
                with lock:
                    seq = next(seqs)
                frame = msgpack.packb({**encoded[seq % len(encoded)], "stamp": time.time(), "seq": seq})
                body = pack_align_request(sign_frame(frame, cred))  # the peer frame; the ego's is cached
                try:
                    r = http.post("/v1/align", content=body, headers={"content-type": "application/msgpack"})
                    code = str(r.status_code) + ("+retry-after" if "retry-after" in r.headers else "")
                except httpx.HTTPError as e:
                    code = type(e).__name__
                with lock:
                    status[code] += 1

    workers = [threading.Thread(target=run, daemon=True) for _ in range(threads)]
    ready.set()
    t0 = time.monotonic()
    for t in workers:
        t.start()
    for t in workers:
        t.join()
    status["seconds"] = round(time.monotonic() - t0, 1)
    out.put({"threads": threads, "status": dict(status), "own_process": True})


def attackers(probe: str, ep: str, seconds: float, recorded: dict, certs: dict):
    """The probe's attacker(s): objects with start() and finish()."""
    from bb_align.lab.flood import FloodConfig, FloodProcess

    quiet = {"small_per_cycle": 0, "big_per_cycle": 0, "replays_per_cycle": 0, "duration_s": seconds}
    forged = {**quiet, "big_per_cycle": 1, "kinds": ["forged_frame", "forged_frame_random_sig"]}
    if probe.startswith("forged_"):  # car1's frames forged (car2 is the other car), or the ego's
        victim = "ego" if probe == "forged_ego_slow" else "car1"
        cfg = FloodConfig(**forged, big_per_s=0.0 if probe == "forged_full" else 3.0)
        return [FloodProcess(ep, "bbalign", {victim: certs[victim]}, cfg) for _ in range(2)]
    if probe == "query_replay":
        cfg = FloodConfig(**{**quiet, "replays_per_cycle": 1}, replays_per_s=190.0, query_key="bbalign/align/ego")
        return [FloodProcess(ep, "bbalign", {c: None for c in CARS}, cfg, recorded["genuine"]) for _ in range(2)]
    if probe == "stale_absent":
        cfg = FloodConfig(**{**quiet, "replays_per_cycle": 1})
        return [FloodProcess(ep, "bbalign", {"car3": None}, cfg, recorded["stale"]) for _ in range(2)]
    raise ValueError(probe)


def throttled(svc) -> float:
    """Seconds the door thread has slept so far (its refusals' CPU share spent)."""
    return door_refused(svc).get("bbalign_door_throttled_seconds", 0.0)


def run_probe(probe: str, ctx: dict, seconds: float) -> dict:
    """Baseline, attack, after: one window each, the genuine streams going on throughout."""
    streams, listener, svc = ctx["streams"], ctx["listener"], ctx["svc"]
    refused0 = door_refused(svc)
    peers, slept = [svc.get("/v1/peers")], [throttled(svc)]
    windows = {"baseline": streams.run(seconds)}
    peers.append(svc.get("/v1/peers"))
    slept.append(throttled(svc))
    if probe == "rest_flood":
        attack = [RestFlood(svc.rest, ctx["keys"] / "car3.cred", 8)]
    else:
        attack = attackers(probe, svc.zenoh_endpoint, seconds, ctx["recorded"], ctx["certs"])
    try:
        for a in attack:
            a.start()
        windows["during"] = streams.run(seconds)
        peers.append(svc.get("/v1/peers"))
        slept.append(throttled(svc))
        report = [a.finish() for a in attack]
    finally:
        for a in attack:
            getattr(a, "stop", lambda: None)()
    peers.append(svc.get("/v1/peers"))  # the attackers' last messages are in the after window
    slept.append(throttled(svc))
    windows["after"] = streams.run(seconds)
    time.sleep(2.5)
    peers.append(svc.get("/v1/peers"))
    refused1 = door_refused(svc)
    slept.append(refused1.get("bbalign_door_throttled_seconds", 0.0))
    out = {w: count(listener, streams.sent, t0, t1, t1 + 2.0) for w, (t0, t1) in windows.items()}
    for i, w in ((0, "baseline"), (1, "during"), (3, "after")):
        p0, p1 = peers[i], peers[i + 1]
        out[w]["frames"] = {c: {k: p1.get(c, {}).get(k, 0) - p0.get(c, {}).get(k, 0) for k in ("frames_accepted",
                            "frames_dropped")} for c in CARS}  # fmt: skip
        out[w]["door_slept_s"] = round(slept[i + 1] - slept[i], 2)
    base = out["baseline"]["results_per_s"]
    for w in ("during", "after"):
        out[w]["kept"] = {c: round(out[w]["results_per_s"][c] / base[c], 3) if base[c] else None for c in CARS}
        tot = sum(base.values())
        out[w]["kept"]["both"] = round(sum(out[w]["results_per_s"].values()) / tot, 3) if tot else None
    t_att = windows["during"][0]
    out["signed_for_attacker"] = foreign_signed(listener, streams.sent, t_att, time.time())
    out["attackers"] = report
    out["door_refused"] = {
        k: round(refused1.get(k, 0) - refused0.get(k, 0)) for k in refused1 if refused1.get(k, 0) != refused0.get(k, 0)
    }  # noqa: E501
    out["load_avg_1min"] = round(os.getloadavg()[0], 2)
    out["cpu_s_total"] = svc.cpu_seconds()
    out["service_rss_mb"] = svc.memory_mb().get("rss_mb")
    return out


def record_frames(ctx: dict) -> None:
    """What an attacker copies from the air before its attack (the frames the cars signed and sent): the ego's and
    car1's certificates (from their real signed frames), the last genuine frames of car1 and car2, and 50 frames
    car3 signed an hour ago."""
    from bb_align.protocol import Limits, peek_signed
    from bb_align_client import encode_frame, sign_frame
    from service_support import RANGE_M

    ctx["streams"].run(4.0)
    on_air = list(ctx["streams"].on_air)
    genuine = [(vid, data) for vid, data in on_air if vid in CARS]
    certs = {v: next(peek_signed(data, Limits()).cert for vid, data in on_air if vid == v) for v in ("ego", "car1")}
    hour_ago = time.time() - 3600.0
    stale = []
    for i in range(50):
        _, _, p = ctx["frames"][i % len(ctx["frames"])]
        f = encode_frame(p.points, p.boxes, vehicle_id="car3", stamp=hour_ago + 0.1 * i, seq=i, range_m=RANGE_M)
        stale.append(("car3", sign_frame(f, ctx["creds"]["car3"])))
    ctx["certs"], ctx["recorded"] = certs, {"genuine": genuine, "stale": stale}


def plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(out["probes"])
    fig, ax = plt.subplots(figsize=(1.8 * len(names) + 2, 3.8))
    bars = [(c, w) for c in CARS for w in ("during", "after")]
    for i, (c, w) in enumerate(bars):
        xs = [j + (i - 1.5) * 0.2 for j in range(len(names))]
        ax.bar(xs, [out["probes"][n][w]["kept"][c] or 0 for n in names], 0.2, label=f"{c} {w} / baseline")
    ax.axhline(0.8, color="k", ls="--", lw=1)
    ax.set_xticks(range(len(names)), [n.replace("_", "\n") for n in names], fontsize=8)
    ax.set_ylabel("genuine cars' results/s kept")
    ax.set_title("Issue 47 probes: genuine cars' results during and after each attack, over the baseline", fontsize=10)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=10.0, help="each window (baseline, attack, after)")
    ap.add_argument("--probes", default=",".join(PROBES))
    ap.add_argument("--no-odometry", action="store_true", help="the cars send no odometry (tracks predict alone)")
    ap.add_argument("--record", action="store_true", help="write docs/security_probes_round3.{json,png}")
    a = ap.parse_args()
    probes = a.probes.split(",")
    if unknown := set(probes) - set(PROBES):
        sys.exit(f"door_probes: --probes: unknown {sorted(unknown)} (known: {', '.join(PROBES)})")
    import zenoh

    from bb_align.lab.harness import make_credentials, start_service
    from bb_align.protocol import ZenohSettings
    from bb_align_client import ZenohPeer
    from service_support import service_settings

    base = (ROOT / "docs") if a.record else (ROOT / "out")
    base.mkdir(exist_ok=True)
    out = {
        "command": " ".join(["benchmarks/door_probes.py", *sys.argv[1:]]),
        "seconds": a.seconds,
        "cpus": os.cpu_count(),
        "load_avg_at_start": [round(x, 2) for x in os.getloadavg()],
        "probes": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        keys = Path(tmp) / "keys"
        creds = make_credentials(keys, ["ego", "car1", "car2", "car3"])
        auth = {"ca_cert": str(keys / "ca.pub"), "credential": str(keys / "ego.cred")}
        settings = service_settings(True, profile="vehicle", workers=2, limits={"check_stamp_clock": True}, auth=auth)
        svc = start_service(settings, None, Path(tmp), timeout_s=300)
        ep = [svc.zenoh_endpoint]
        zcfg = lambda: ZenohSettings(listen=[], connect=ep).to_zenoh_config()  # noqa: E731
        try:
            with (
                zenoh.open(zcfg()) as air,
                zenoh.open(zcfg()) as car2,
                ZenohPeer("ego", connect=ep, key=creds["ego"], verify_answers=False) as ego,
                ZenohPeer("car1", connect=ep, key=creds["car1"], verify_answers=False) as car1,
            ):
                from bb_align.lab.harness import to_and_fro_times
                from service_support import moving_pair

                frames = moving_pair(20, times=to_and_fro_times(20, 0.1, speed_m_s=10.0))
                listener = Listener()
                sub = air.declare_subscriber("bbalign/poses/ego/*", listener.on_sample)
                assert ego.wait_for_subscriber(10) and car1.wait_for_subscriber(10)
                streams = Streams(frames, ego, car1, car2, creds, odometry=not a.no_odometry)
                ctx = {"svc": svc, "streams": streams, "listener": listener, "frames": frames, "creds": creds}
                ctx["keys"] = keys
                streams.run(8.0)  # warm-up: tracks acquired
                record_frames(ctx)
                for probe in probes:
                    out["probes"][probe] = r = run_probe(probe, ctx, a.seconds)
                    print(probe, json.dumps({w: r[w]["kept"] for w in ("during", "after")}), file=sys.stderr)
                sub.undeclare()
        finally:
            out["service_exit_code"] = svc.stop()
    out["load_avg_at_end"] = [round(x, 2) for x in os.getloadavg()]
    (base / "security_probes_round3.json").write_text(json.dumps(out, indent=1) + "\n")
    plot(out, base / "security_probes_round3.png")
    print(summary(out))


def summary(out: dict) -> str:
    lines = ["probe           | baseline res/s car1 car2 | during/base car1 car2 | after/base car1 car2 |"
             " p90 ms base/during/after | signed for attacker"]  # fmt: skip
    for name, r in out["probes"].items():
        b = r["baseline"]["results_per_s"]
        p90 = "/".join(str(r[w]["latency_ms_p50_p90"][1]) for w in ("baseline", "during", "after"))
        signed = sum(r["signed_for_attacker"].values()) + sum(
            v for a in r["attackers"] for k, v in a.get("query_replies", {}).items() if k.startswith("signed")
        )
        k = {w: " ".join(f"{r[w]['kept'][c]}" for c in CARS) for w in ("during", "after")}
        lines.append(f"{name:15s} | {b['car1']:.2f} {b['car2']:.2f} | {k['during']} | {k['after']} | {p90} | {signed}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
