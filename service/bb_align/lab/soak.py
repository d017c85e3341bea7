"""``bb-align soak``: flood a service from N simulated peers with valid and hostile frames, then account for
every message.

The service is started as a separate process (vehicle profile: signed frames, a fresh fleet key, loopback ports),
or an already running one is targeted (``--connect``, ``--rest``, ``--key``, optionally ``--pid`` for its memory).
An ego car and N peers (bb_align.lab.sim scenes) publish at ``rate_hz`` over Zenoh on loopback for ``duration``
seconds; a share of the peers' messages are attacks (garbage, unsigned, wrongly signed, replayed, NaN boxes, a
PNG decompression bomb, oversized, a spoofed sender, junk sender ids). At the end it checks, from the service's
own counters (/v1/peers, /metrics) against what was sent:

- every message is accounted for: sent = accepted + rejected + dropped before the gate;
- every accepted stream frame has a result (success or a failure reason) or is counted as dropped (latest-only);
- every result the service produced reached the listener; every attack was refused; refusal notices went only
  to signed frames (never to unsigned or undecodable junk);
- the service is still ready, its memory grew less than ``rss_growth_mb``, and (when started here) SIGTERM
  makes it drain and exit 0.
"""

from __future__ import annotations

import json
import re
import secrets
import tempfile
import time
import zlib
from collections import Counter
from pathlib import Path

import msgpack
import numpy as np
import typer

from .harness import ServiceProcess, free_port, simulated_cars, start_service

EGO_ID = "ego"
PREFIX = "bbalign-soak"
ATTACKS = ("garbage", "unsigned", "bad_mac", "replay", "nan_box", "png_bomb", "spoofed_id", "junk_sender", "oversized")
# What the service must answer to each attack (bbalign_frames_rejected_total{error=...}).
EXPECTED_ERROR = {
    "garbage": "undecodable",
    "unsigned": "unauthenticated",
    "bad_mac": "unauthenticated",
    "replay": "replayed",
    "nan_box": "invalid",
    "png_bomb": "invalid",
    "spoofed_id": "invalid",
    "junk_sender": "unauthenticated",
    "oversized": "too_large",
}


def start_soak_service(workers: int, log_dir: Path, timeout_s: float = 90.0) -> ServiceProcess:
    """The service (vehicle profile, a fresh fleet key) on free loopback ports, ready to take frames."""
    from bb_align.server.settings import Settings

    settings = Settings(
        ego_id=EGO_ID,
        port=free_port(),
        workers=workers,
        zenoh={"listen": [f"tcp/127.0.0.1:{free_port()}"], "prefix": PREFIX},
    )
    return start_service(settings, secrets.token_hex(32), log_dir, timeout_s)


# ---- what the cars send ---------------------------------------------------------------------------------------
def _png_bomb(side: int) -> bytes:
    """A PNG whose header matches a side x side BV image but whose image data inflates to 64x more bytes."""
    import struct

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)))

    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    idat = zlib.compress(bytes(64 * side * (side + 1)), 9)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


class Sender:
    """Builds each message (valid or an attack) and remembers what it sent."""

    def __init__(self, key: str, max_message_bytes: int, rng: np.random.Generator):
        from bb_align.protocol import pack, sign

        self._pack, self._sign = pack, sign
        self.key = key
        self.rng = rng
        self.max_message_bytes = max_message_bytes
        self.last_valid: dict[str, bytes] = {}
        self._bombs: dict[int, bytes] = {}

    def valid(self, frame, stamp: float, seq: int) -> bytes:
        data = self._sign(self._pack(frame.model_copy(update={"stamp": stamp, "seq": seq})), self.key)
        self.last_valid[frame.vehicle_id] = data
        return data

    def attack(self, kind: str, frame, stamp: float, seq: int) -> tuple[str, bytes]:
        """(key chunk to publish under, payload) for one attack on behalf of ``frame``'s car."""
        vid = frame.vehicle_id
        f = frame.model_copy(update={"stamp": stamp, "seq": seq})
        if kind == "garbage":  # 0xc1 is never used by msgpack: undecodable, whatever follows
            return vid, b"\xc1" + self.rng.bytes(int(self.rng.integers(0, 2000)))
        if kind == "unsigned":
            return vid, self._pack(f)
        if kind == "bad_mac":
            return vid, self._sign(self._pack(f), "not-the-fleet-key-" + "x" * 16)
        if kind == "replay":  # the car's last valid frame, byte for byte
            return vid, self.last_valid[vid]
        if kind == "nan_box":
            d = f.model_dump(mode="python")
            d["boxes"] = d["boxes"] or [[1.0, 1.0, 0.0, 4.0, 2.0, 1.5, 0.0]]
            d["boxes"][0][0] = float("nan")
            return vid, self._sign(msgpack.packb(d, use_bin_type=True), self.key)
        if kind == "png_bomb":
            side = int(round(2 * f.bev.range_m / f.bev.resolution_m))
            bomb = self._bombs.setdefault(side, _png_bomb(side))
            return vid, self._sign(self._pack(f.model_copy(update={"png": bomb})), self.key)
        if kind == "spoofed_id":
            return vid, self._sign(self._pack(f.model_copy(update={"vehicle_id": "ego"})), self.key)
        if kind == "junk_sender":  # an unsigned frame under a fresh id: must not create peer state
            junk = f"junk-{int(self.rng.integers(1 << 40)):x}"
            return junk, self._pack(f.model_copy(update={"vehicle_id": junk}))
        if kind == "oversized":  # over the service's limit, under Zenoh's own reassembly bound
            return vid, b"\x00" * (self.max_message_bytes + 1024)
        raise ValueError(kind)


# ---- the run ---------------------------------------------------------------------------------------------------
def _metrics(rest: str, token: str | None = None) -> dict[str, float]:
    import httpx

    headers = {"authorization": f"Bearer {token}"} if token else {}
    out: dict[str, float] = {}
    for line in httpx.get(rest + "/metrics", timeout=10, headers=headers).text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


def _sum(metrics: dict[str, float], prefix: str, **labels: str) -> float:
    total = 0.0
    for name, v in metrics.items():
        if name.startswith(prefix + "{") or name == prefix:
            if all(f'{k}="{val}"' in name for k, val in labels.items()):
                total += v
    return total


def _label_values(metrics: dict[str, float], prefix: str, label: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for name, v in metrics.items():
        if name.startswith(prefix + "{"):
            m = re.search(f'{label}="([^"]*)"', name)
            if m:
                out[m.group(1)] = out.get(m.group(1), 0.0) + v
    return out


def run_soak(
    *,
    duration_s: float = 120.0,
    n_peers: int = 8,
    rate_hz: float = 10.0,
    attack_share: float = 0.3,
    workers: int = 2,
    frames: int = 4,
    seed: int = 7,
    rss_growth_mb: float = 150.0,
    warmup_s: float = 10.0,
    grace_s: float = 60.0,
    connect: str | None = None,
    rest: str | None = None,
    key: str | None = None,
    pid: int | None = None,
    max_message_bytes: int = 4 * 1024 * 1024,
    oversized_every_s: float = 5.0,
    log_dir: Path | None = None,
    progress: bool = True,
) -> dict:
    """The soak run; returns the report (``report["ok"]``: every check passed). Everything on loopback."""
    import httpx
    import zenoh
    from tqdm import tqdm

    from bb_align.protocol import Refusal, ZenohSettings, load_answer, poses_key
    from bb_align_client import ZenohPeer
    from bb_align_client.zenoh_peer import ArrivalLog

    rng = np.random.default_rng(seed)
    cars = simulated_cars(n_peers, frames, seed, ego_id=EGO_ID)
    log_dir = Path(log_dir or tempfile.mkdtemp(prefix="bbalign-soak-"))
    if connect is None:
        target = start_soak_service(workers, log_dir)
    else:
        if rest is None or key is None:
            raise ValueError("targeting a running service needs its REST address and fleet key")
        target = ServiceProcess(rest, connect, key, pid=pid)
    sender = Sender(target.key, max_message_bytes, rng)
    results = ArrivalLog()
    sent_at: dict[tuple[str, int], float] = {}
    sent = Counter()  # kind -> messages ("valid", "valid_ego", attack kinds)
    valid_per_peer = Counter()
    listener = zenoh.open(ZenohSettings(listen=[], connect=[target.zenoh_endpoint], prefix=PREFIX).to_zenoh_config())
    pubs = {}
    crash = None
    report: dict = {}
    try:
        sub = listener.declare_subscriber(poses_key(PREFIX, EGO_ID, "*"), results)
        pubs = {
            c.vehicle_id: ZenohPeer(
                c.vehicle_id,
                connect=[target.zenoh_endpoint],
                prefix=PREFIX,
                block_when_congested=True,
                verify_answers=False,  # publishes only; the listener below reads the answers
            ).open()
            for c in cars
        }
        raw = zenoh.open(ZenohSettings(listen=[], connect=[target.zenoh_endpoint], prefix=PREFIX).to_zenoh_config())
        pubs["@raw"] = raw
        for p in list(pubs.values())[:-1]:
            p.wait_for_subscriber(10.0)
        time.sleep(0.5)
        rss_start = None
        t0 = time.perf_counter()
        n_ticks = int(round((warmup_s + duration_s) * rate_hz))
        last_oversized = -1e9
        ticks = tqdm(range(n_ticks), desc="soak", unit="tick", disable=not progress, mininterval=2.0)
        for k in ticks:
            delay = t0 + k / rate_hz - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            if k == int(warmup_s * rate_hz):
                rss_start = target.memory_mb()["rss_mb"]
            if target.proc is not None and target.proc.poll() is not None:
                crash = f"the service exited with {target.proc.returncode} during the run"
                break
            stamp, idx = time.time(), k % frames
            for car in cars:
                frame = car.frames[idx]
                if car.vehicle_id == EGO_ID:
                    pubs[EGO_ID].publish(sender.valid(frame, stamp, k))
                    sent["valid_ego"] += 1
                    continue
                if rng.random() < attack_share:
                    kind = ATTACKS[int(rng.integers(len(ATTACKS) - 1))]  # oversized: paced separately
                    now = time.perf_counter()
                    if now - last_oversized > oversized_every_s:
                        kind, last_oversized = "oversized", now
                    if kind == "replay" and car.vehicle_id not in sender.last_valid:
                        kind = "unsigned"
                    chunk, data = sender.attack(kind, frame, stamp, k)
                    if chunk == car.vehicle_id:  # the car's own session: arrives after its earlier frames
                        pubs[chunk].publish(data)
                    else:
                        raw.put(f"{PREFIX}/frames/{chunk}", data, congestion_control=zenoh.CongestionControl.BLOCK)
                    sent[kind] += 1
                else:
                    pubs[car.vehicle_id].publish(sender.valid(frame, stamp, k))
                    sent_at[(car.vehicle_id, k)] = time.perf_counter()
                    sent["valid"] += 1
                    valid_per_peer[car.vehicle_id] += 1
        ticks.close()
        publish_s = time.perf_counter() - t0
        # Quiesce: every queue empty and every result out.
        deadline = time.monotonic() + grace_s
        while time.monotonic() < deadline:
            m = _metrics(target.rest)
            if m.get("bbalign_queued_jobs", 1) == 0 and m.get("bbalign_intake_messages", 1) == 0:
                time.sleep(1.0)  # the last results on their way
                break
            time.sleep(0.5)
        metrics = _metrics(target.rest)
        peers = httpx.get(target.rest + "/v1/peers", timeout=10).json()
        ready = httpx.get(target.rest + "/readyz", timeout=10).status_code == 200
        rss_end = target.memory_mb()["rss_mb"]
        sub.undeclare()
    finally:
        for p in pubs.values():
            p.close()
        listener.close()
        exit_code = target.stop()

    with results.lock:
        items = list(results.items)
    got = Counter()
    latency = []
    outcomes = Counter()
    notices = Counter()  # refusals told to the sender of a signed frame, by error
    for t_recv, data in items:
        r = load_answer(data)
        if isinstance(r, Refusal):
            notices[r.refused.error] += 1
            continue
        got[r.peer_id] += 1
        outcomes["success" if r.success else r.reason] += 1
        t_sent = sent_at.get((r.peer_id, r.peer_seq))
        if t_sent is not None:
            latency.append((t_recv - t_sent) * 1e3)
    rejected = _label_values(metrics, "bbalign_frames_rejected_total", "error")
    dropped = _label_values(metrics, "bbalign_frames_dropped_total", "peer")
    attacks_sent = sum(sent[k] for k in ATTACKS)
    expected_rejections = Counter(EXPECTED_ERROR[k] for k in ATTACKS for _ in range(sent[k]))
    accepted = sum(p["frames_accepted"] for p in peers.values())
    per_peer = {}
    for vid, p in peers.items():
        per_peer[vid] = {
            "valid_sent": valid_per_peer[vid],
            "accepted": p["frames_accepted"],
            "results": p["results"],
            "dropped": p["frames_dropped"],
            "failed": p["failed"],
            "intake_dropped": p["intake_dropped"],
            "results_received": got[vid],
        }
    unverified_drops = dropped.get("(unverified)", 0.0)
    q = lambda a, pct: float(np.percentile(a, pct)) if len(a) else None  # noqa: E731
    checks = {
        "no_crash": crash is None and ready,
        "exit_code_0_on_sigterm": exit_code == 0 if target.proc is not None else None,
        "every_valid_frame_answered_or_counted": all(
            v["accepted"] == v["results"] + v["dropped"] for v in per_peer.values()
        ),
        "every_valid_frame_accepted_or_dropped_at_intake": all(
            v["valid_sent"] == v["accepted"] + v["intake_dropped"] for v in per_peer.values()
        )
        and unverified_drops == 0,
        "every_result_received": all(v["results"] == v["results_received"] for v in per_peer.values()),
        "every_attack_refused_with_the_right_error": all(
            rejected.get(err, 0) >= n for err, n in expected_rejections.items()
        )
        and sum(rejected.values()) == attacks_sent,
        "no_valid_frame_refused": sum(rejected.values()) == attacks_sent,
        "no_refusal_notice_for_unsigned_junk": not set(notices) & {"unauthenticated", "undecodable", "too_large"},
        "peers_tracked_bounded": metrics.get("bbalign_peers_tracked", 1e9) <= n_peers + 1,
        "rss_growth_within_bound": None
        if rss_start is None or rss_end is None
        else rss_end - rss_start <= rss_growth_mb,
    }
    report = {
        "config": {
            "duration_s": duration_s,
            "warmup_s": warmup_s,
            "peers": n_peers,
            "rate_hz": rate_hz,
            "attack_share": attack_share,
            "workers": workers,
            "frames": frames,
            "seed": seed,
            "rss_growth_bound_mb": rss_growth_mb,
        },
        "publish_s": publish_s,
        "sent": {
            "total": sum(sent.values()),
            "valid_peer": sent["valid"],
            "valid_ego": sent["valid_ego"],
            "attacks": attacks_sent,
            "by_kind": dict(sent),
        },
        "service": {
            "accepted_stream_frames": accepted,
            "rejected": rejected,
            "rejected_total": sum(rejected.values()),
            "dropped": dropped,
            "results_produced": sum(p["results"] for p in peers.values()),
            "results_received": sum(got.values()),
            "outcomes": dict(outcomes),
            "refusal_notices": dict(notices),
            "peers_tracked_end": metrics.get("bbalign_peers_tracked"),
        },
        "per_peer": per_peer,
        "latency_ms": {"p50": q(latency, 50), "p99": q(latency, 99), "n": len(latency)},
        "rss_mb": {
            "start": rss_start,
            "end": rss_end,
            "growth": None if rss_start is None or rss_end is None else rss_end - rss_start,
        },
        "exit_code": exit_code,
        "crash": crash,
        "checks": checks,
        "ok": all(v is not False for v in checks.values()),
        "service_log": str(target.log_path) if target.log_path else None,
    }
    return report


def soak(
    duration: float = typer.Option(120.0, min=1, max=3600, help="seconds of flooding after the warm-up"),
    peers: int = typer.Option(8, min=1, max=32, help="simulated peer cars (plus the ego car)"),
    rate_hz: float = typer.Option(10.0, min=0.5, max=50, help="frames per car per second"),
    attack_share: float = typer.Option(0.3, min=0, max=1, help="share of the peers' messages that are attacks"),
    workers: int = typer.Option(2, min=1, max=16, help="engine workers of the started service"),
    warmup: float = typer.Option(10.0, min=0, max=600, help="seconds before RSS is first read"),
    rss_growth_mb: float = typer.Option(150.0, min=0, help="largest RSS growth accepted, MB"),
    seed: int = typer.Option(7, help="scene and attack seed"),
    connect: str | None = typer.Option(None, help="target a running service's Zenoh endpoint (loopback)"),
    rest: str | None = typer.Option(None, help="... its REST address, e.g. http://127.0.0.1:8000"),
    key: str | None = typer.Option(
        None, envvar="BBALIGN_AUTH__FLEET_KEY", show_default=False, help="... its fleet key"
    ),
    pid: int | None = typer.Option(None, help="... its process id (for RSS)"),
    json_out: Path | None = typer.Option(None, "--json", help="write the report as JSON"),
) -> None:
    """Flood a service (started here, or --connect) from N simulated peers with valid and hostile frames over
    Zenoh on loopback, then account for every message (exit 1 when a check fails)."""
    for endpoint in filter(None, (connect, rest)):
        host = endpoint.split("//")[-1].split("/")[-1].rsplit(":", 1)[0]
        if host not in ("127.0.0.1", "localhost"):
            raise typer.BadParameter(f"the soak stays on loopback: {endpoint}")
    report = run_soak(
        duration_s=duration,
        n_peers=peers,
        rate_hz=rate_hz,
        attack_share=attack_share,
        workers=workers,
        warmup_s=warmup,
        rss_growth_mb=rss_growth_mb,
        seed=seed,
        connect=connect,
        rest=rest,
        key=key,
        pid=pid,
    )
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(report, indent=1))
    s, svc, lat, rss = report["sent"], report["service"], report["latency_ms"], report["rss_mb"]
    fmt = lambda v, spec=".0f": "-" if v is None else format(v, spec)  # noqa: E731
    typer.echo(
        f"sent {s['total']} ({s['valid_peer']} valid peer frames, {s['valid_ego']} ego, {s['attacks']} "
        f"attacks); accepted {svc['accepted_stream_frames']}, rejected {svc['rejected_total']} "
        f"{svc['rejected']}, dropped {svc['dropped']}; results {svc['results_produced']} produced / "
        f"{svc['results_received']} received; latency p50 {fmt(lat['p50'])} ms p99 {fmt(lat['p99'])} ms; "
        f"RSS {fmt(rss['start'], '.1f')} -> {fmt(rss['end'], '.1f')} MB; exit code {report['exit_code']}"
    )
    for name, ok in report["checks"].items():
        typer.echo(f"  {'ok  ' if ok else ('n/a ' if ok is None else 'FAIL')} {name}")
    if not report["ok"]:
        raise typer.Exit(1)
