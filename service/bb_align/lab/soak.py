"""``bb-align soak``: drive a service with hostile traffic on loopback, then account for every message.

The service is started as a separate process in the secure profile, with Ed25519 credentials for the ego and every
car made by ``bb-align keys`` (or an already running one is targeted: ``--connect``, ``--rest``, ``--keys`` or the
fleet ``--key``, optionally ``--pid`` for its memory). An ego car and N peers (bb_align.lab.sim scenes) publish
signed frames at ``rate_hz`` over Zenoh on loopback, through these phases:

1. **attacks** (after a warm-up): a share of the peers' messages are attacks (garbage, unsigned, untrusted
   signature, replayed, NaN boxes, a PNG decompression bomb, oversized, a car claiming the ego's id, junk sender
   ids). From the service's own counters (/v1/peers, /metrics) against what was sent: every message accounted for,
   every accepted frame answered or counted as dropped, every result received, every attack refused with the
   right error, the peer table bounded, memory growth bounded.
2. **baseline** and **flood** (``flood``, same length): the authenticated streams alone, then the same streams
   while a keyless publisher in its own process floods the cars' frame keys as fast as it can (bb_align.lab.flood).
   Measured: authenticated frames lost, results per second against the baseline, drops per intake lane and per
   signed id (junk must be charged to the unverified lane only).
3. **odd shapes** (``odd_shapes``): odd-shaped signed frames within and beyond the served limits, each answered
   (a Result or a refusal naming the field), service RSS at start and end.

At the end the service must still be ready and (when started here) drain on SIGTERM and exit 0.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
import typer

from .harness import ServiceProcess, fleet_credentials, free_port, make_credentials, simulated_cars, start_service
from .soak_attacks import ATTACKS, REFUSED_AT_DECODE, Sender, expected_errors
from .soak_phases import (
    UNVERIFIED,
    FloodPhase,
    OddShapesPhase,
    PhaseRunner,
    Snapshot,
    Timeline,
    Traffic,
    combine,
    flood_checks,
    label_values,
    percentiles,
    quiesce,
    refusal_notices,
    results_by_phase,
    run_odd_shapes,
    start_flood,
)

__all__ = ["ATTACKS", "run_soak", "soak"]

EGO_ID = "ego"
PREFIX = "bbalign-soak"
ATTACK_PHASES = ("warmup", "attacks")


def start_soak_service(workers: int, log_dir: Path, keys_dir: Path, timeout_s: float = 90.0) -> ServiceProcess:
    """The service in the secure profile (its own credential, the fleet authority trusted) on free loopback
    ports, ready to take frames."""
    from bb_align.server.settings import Settings

    settings = Settings(
        ego_id=EGO_ID,
        port=free_port(),
        workers=workers,
        zenoh={"listen": [f"tcp/127.0.0.1:{free_port()}"], "prefix": PREFIX},
        auth={"ca_cert": str(keys_dir / "ca.pub"), "credential": str(keys_dir / f"{EGO_ID}.cred")},
    )
    return start_service(settings, None, log_dir, timeout_s)


def _attack_report(
    snap: Snapshot, traffic: Traffic, results, latency, signers, n_peers, decode_refused: set[tuple[str, int]]
) -> tuple[dict, dict]:
    """(report parts, checks) of the warm-up and attack phases, from the counters read after they drained.
    ``decode_refused``: the (vehicle id, seq) of frames a worker refused when decoding them."""
    sent, valid_per_peer, signed_attacks = Counter(), Counter(), Counter()
    for phase in ATTACK_PHASES:
        sent.update(traffic.sent[phase])
        valid_per_peer.update(traffic.valid_per_peer[phase])
        signed_attacks.update(traffic.signed_attacks[phase])
    decoded = Counter(vid for vid, k in traffic.decoded_keys if traffic.sent_at[(vid, k)][1] in ATTACK_PHASES)
    got = Counter()
    for phase in ATTACK_PHASES:
        got.update(results.get(phase, Counter()))
    metrics, peers = snap.metrics, snap.peers
    rejected = label_values(metrics, "bbalign_frames_rejected_total", "error")
    dropped = label_values(metrics, "bbalign_frames_dropped_total", "peer")
    attacks_sent = sum(sent[k] for k in ATTACKS)
    # Frames the gate admits as the car's own (valid ones, and REFUSED_AT_DECODE attacks), and the attacks it refuses.
    gate_attacks_sent = attacks_sent - sum(decoded.values())
    refused_decoding = len(decode_refused & traffic.decoded_keys)
    errors = expected_errors(signers)
    expected = Counter(errors[k] for k in ATTACKS if k not in REFUSED_AT_DECODE for _ in range(sent[k]))
    expected.update(errors[k] for k in REFUSED_AT_DECODE for _ in range(refused_decoding))
    per_peer = {
        vid: {
            "valid_sent": valid_per_peer[vid],
            "admitted_sent": valid_per_peer[vid] + decoded[vid],
            "signed_attacks_sent": signed_attacks[vid],
            "accepted": p["frames_accepted"],
            "results": p["results"],
            "dropped": p["frames_dropped"],
            "failed": p["failed"],
            "intake_dropped": p["intake_dropped"],
            "results_received": got[vid],
        }
        for vid, p in peers.items()
    }
    # A full intake lane (the gate stalled) pushes out messages signed by a car: its valid frames or its signed
    # attacks; the rest of the attacks are refused (or, unsigned, dropped in the unverified lane).
    attacks_dropped = sum(v["intake_dropped"] - (v["admitted_sent"] - v["accepted"]) for v in per_peer.values())
    attacks_dropped += dropped.get(UNVERIFIED, 0.0)
    refused = sum(rejected.values())
    checks = {
        "every_valid_frame_answered_or_counted": all(
            v["accepted"] == v["results"] + v["dropped"] for v in per_peer.values()
        ),
        "every_valid_frame_accepted_or_dropped_at_intake": all(
            v["admitted_sent"] <= v["accepted"] + v["intake_dropped"] <= v["valid_sent"] + v["signed_attacks_sent"]
            for v in per_peer.values()
        ),
        "every_result_received": all(v["results"] == v["results_received"] for v in per_peer.values()),
        "every_attack_refused_with_the_right_error": all(
            rejected.get(e, 0) >= n - attacks_dropped for e, n in expected.items()
        ),
        # refused at the gate or, REFUSED_AT_DECODE, by a worker (only those frames: decode_refused); such an
        # attack replaced unread is a dropped frame of its car, as any replaced frame
        "no_valid_frame_refused": refused - refused_decoding + attacks_dropped == gate_attacks_sent
        and decode_refused <= traffic.decoded_keys
        and all(v["accepted"] <= v["admitted_sent"] for v in per_peer.values()),
        "peers_tracked_bounded": metrics.get("bbalign_peers_tracked", 1e9) <= n_peers + 1,
    }
    report = {
        "sent": {
            "total": sum(sent.values()),
            "valid_peer": sent["valid"],
            "valid_ego": sent["valid_ego"],
            "attacks": attacks_sent,
            "by_kind": dict(sent),
        },
        "service": {
            "accepted_stream_frames": sum(p["frames_accepted"] for p in peers.values()),
            "rejected": rejected,
            "rejected_total": refused,
            "attacks_dropped_at_intake": attacks_dropped,
            "refused_at_decode": refused_decoding,
            "not_decoded": sum(decoded.values()) - refused_decoding,
            "dropped": dropped,
            "results_produced": sum(p["results"] for p in peers.values()),
            "results_received": sum(got.values()),
            "peers_tracked_end": metrics.get("bbalign_peers_tracked"),
        },
        "per_peer": per_peer,
        "latency_ms": percentiles([v for phase in ATTACK_PHASES for v in latency.get(phase, [])]),
    }
    return report, checks


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
    flood: FloodPhase | None = None,
    odd_shapes: OddShapesPhase | None = None,
    connect: str | None = None,
    rest: str | None = None,
    key: str | None = None,
    keys_dir: Path | None = None,
    prefix: str | None = None,
    pid: int | None = None,
    max_message_bytes: int = 4 * 1024 * 1024,
    oversized_every_s: float = 5.0,
    log_dir: Path | None = None,
    plot: Path | None = None,
    progress: bool = True,
) -> dict:
    """The soak run; returns the report (``report["ok"]``: every check passed). Everything on loopback.
    ``flood``: add the baseline and flood phases; ``odd_shapes``: add the odd-shapes phase."""
    import httpx
    import zenoh

    from bb_align.protocol import ZenohSettings, poses_key
    from bb_align_client import ZenohPeer
    from bb_align_client.zenoh_peer import ArrivalLog

    rng = np.random.default_rng(seed)
    cars = simulated_cars(n_peers, frames, seed, ego_id=EGO_ID)
    ids = [c.vehicle_id for c in cars]
    log_dir = Path(log_dir or tempfile.mkdtemp(prefix="bbalign-soak-"))
    fleet_dir = log_dir / "fleet"
    if connect is None:
        signers = make_credentials(fleet_dir, ids)  # `bb-align keys init` + `issue` per car
        target, prefix = start_soak_service(workers, log_dir, fleet_dir), PREFIX
    else:
        if rest is None or (key is None and keys_dir is None):
            raise ValueError("targeting a running service needs its REST address and its fleet's keys or fleet key")
        signers = fleet_credentials(Path(keys_dir), ids) if keys_dir else dict.fromkeys(ids, key)
        target, prefix = ServiceProcess(rest, connect, key, pid=pid), prefix or "bbalign"
    load_before = os.getloadavg()
    sender = Sender(signers, max_message_bytes, rng)
    arrivals = ArrivalLog()
    listener = zenoh.open(ZenohSettings(listen=[], connect=[target.zenoh_endpoint], prefix=prefix).to_zenoh_config())
    timeline = Timeline(target.rest)
    pubs, flooder = {}, None
    crash, blocks, odd, snaps = None, [], None, {}
    rss = {}

    def crashed() -> str | None:
        if target.proc is not None and target.proc.poll() is not None:
            return f"the service exited with {target.proc.returncode} during the run"
        return None

    try:
        sub = listener.declare_subscriber(poses_key(prefix, EGO_ID, "*"), arrivals)
        for vid in ids:  # publishers only; the listener reads the answers
            pubs[vid] = ZenohPeer(
                vid, connect=[target.zenoh_endpoint], prefix=prefix, block_when_congested=True, verify_answers=False
            ).open()
        raw = zenoh.open(ZenohSettings(listen=[], connect=[target.zenoh_endpoint], prefix=prefix).to_zenoh_config())
        for p in pubs.values():
            p.wait_for_subscriber(10.0)
        time.sleep(0.5)
        traffic = Traffic(cars, pubs, raw, sender, ego_id=EGO_ID, prefix=prefix, rate_hz=rate_hz, rng=rng)
        traffic.oversized_every_s = oversized_every_s
        timeline.start()
        t0 = time.perf_counter()
        crash = traffic.run("warmup", warmup_s, attack_share, crashed=crashed, progress=progress)
        rss["start"] = target.memory_mb()["rss_mb"]
        crash = crash or traffic.run("attacks", duration_s, attack_share, crashed=crashed, progress=progress)
        publish_s = time.perf_counter() - t0
        timeline.phase("attacks", t0, time.perf_counter())
        quiesce(target, grace_s)
        snaps["attacks"] = Snapshot.take(target)
        rss["end"] = target.memory_mb()["rss_mb"]
        runner = PhaseRunner(target, traffic, timeline, crashed, grace_s, progress)
        if flood is not None and crash is None:
            # the flooder replays what the cars sent last (its recording of the air), fresh for each block
            blocks = runner.flood_comparison(
                flood, lambda: start_flood(target, prefix, cars, signers, flood, sender.recorded())
            )
            crash = runner.crash
        if odd_shapes is not None and crash is None:
            t = time.perf_counter()
            odd = run_odd_shapes(target, traffic, odd_shapes, progress=progress)
            timeline.phase("odd shapes", t, time.perf_counter())
        ready = httpx.get(target.rest + "/readyz", timeout=10).status_code == 200
        rss["final"] = target.memory_mb()["rss_mb"]
        sub.undeclare()
    finally:
        if flooder is not None:
            flooder.stop()
        timeline.stop()
        for p in pubs.values():
            p.close()
        if "raw" in locals():
            raw.close()
        listener.close()
        exit_code = target.stop()

    with arrivals.lock:
        items = list(arrivals.items)
    results, latency, outcomes, decode_refused = results_by_phase(items, traffic.sent_at)
    report, checks = _attack_report(snaps["attacks"], traffic, results, latency, signers, n_peers, decode_refused)
    report["service"]["outcomes"] = dict(sum((outcomes[p] for p in ATTACK_PHASES), Counter()))
    notices = refusal_notices(items)
    report["service"]["refusal_notices"] = dict(notices)
    growth = None if rss.get("start") is None or rss.get("end") is None else rss["end"] - rss["start"]
    checks = {
        "no_crash": crash is None and ready,
        "exit_code_0_on_sigterm": exit_code == 0 if target.proc is not None else None,
        **checks,
        # refusals are told only to the sender of a signed frame, never to unsigned or undecodable junk
        "no_refusal_notice_for_unsigned_junk": not set(notices) & {"unauthenticated", "undecodable", "too_large"},
        "rss_growth_within_bound": None if growth is None else growth <= rss_growth_mb,
    }
    stream = {}
    if blocks:
        for kind in ("baseline", "flood"):
            stream[kind] = combine(kind, blocks, traffic, results, latency)
        comparison, flood_ok = flood_checks(stream["baseline"], stream["flood"], flood)
        stream["flood_vs_baseline"] = comparison
        checks.update(flood_ok)
    if odd is not None:
        checks.update(odd["checks"])
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
            "signing": "ed25519 (bb-align keys)" if keys_dir or connect is None else "hmac-sha256 (fleet key)",
            "flood": None if flood is None else flood.model_dump(),
            "odd_shapes": None if odd_shapes is None else odd_shapes.model_dump(),
        },
        "machine": {"cpus": os.cpu_count(), "load_average_before": load_before, "load_average_after": os.getloadavg()},
        "publish_s": publish_s,
        **report,
        "rss_mb": {"start": rss.get("start"), "end": rss.get("end"), "growth": growth, "final": rss.get("final")},
        "phases": stream,
        "odd_shapes": odd,
        "timeline": {
            "samples": timeline.samples,
            "phases": timeline.phases,
            "results": [t - timeline.t0 for t, _ in items],
        },
        "exit_code": exit_code,
        "crash": crash,
        "checks": checks,
        "ok": all(v is not False for v in checks.values()),
        "service_log": str(target.log_path) if target.log_path else None,
    }
    if plot is not None:
        from .soak_plot import plot_soak

        plot_soak(report, plot)
    return report


def _summary(report: dict) -> list[str]:
    s, svc, lat, rss = report["sent"], report["service"], report["latency_ms"], report["rss_mb"]
    fmt = lambda v, spec=".0f": "-" if v is None else format(v, spec)  # noqa: E731
    lines = [
        f"attacks: sent {s['total']} ({s['valid_peer']} valid peer frames, {s['valid_ego']} ego, {s['attacks']} "
        f"attacks); accepted {svc['accepted_stream_frames']}, rejected {svc['rejected_total']:.0f} "
        f"{svc['rejected']}; results {svc['results_produced']} produced / {svc['results_received']} received; "
        f"latency p50 {fmt(lat['p50'])} ms p99 {fmt(lat['p99'])} ms; RSS {fmt(rss['start'], '.1f')} -> "
        f"{fmt(rss['end'], '.1f')} MB"
    ]
    for name in ("baseline", "flood"):
        p = report["phases"].get(name)
        if p:
            lines.append(
                f"{name} ({p['blocks']} blocks, {p['seconds']:.0f} s): ego {p['ego']['accepted']:.0f}/"
                f"{p['ego']['sent']} accepted, peers {p['peers']['accepted']}/{p['peers']['sent']}; "
                f"{p['results_per_s']:.2f} results/s; intake drops by lane {p['intake_dropped_by_lane']}, charged to "
                f"signed ids {p['intake_dropped_charged_to_signed_ids']}; refused at the door "
                f"{sum(p['refused_at_the_door'].values()):.0f}; service CPU {fmt(p['service_cpu_cores'], '.2f')} cores"
            )
    fl = report["phases"].get("flood", {}).get("flooder")
    if fl:
        lines.append(f"flooder: {fl['msg_per_s']:.0f} msg/s, {fl['mb_per_s']:.0f} MB/s, {fl['messages']}")
    odd = report.get("odd_shapes")
    if odd:
        r = odd["rss_mb"]
        lines.append(
            f"odd shapes: {odd['frames']} frames {odd['outcomes']}; RSS {fmt(r['start'], '.1f')} -> "
            f"{fmt(r['end'], '.1f')} MB (max {fmt(r['max'], '.1f')})"
        )
    return lines + [f"exit code {report['exit_code']}"]


def soak(
    duration: float = typer.Option(120.0, min=1, max=3600, help="seconds of the attack mix after the warm-up"),
    peers: int = typer.Option(8, min=1, max=32, help="simulated peer cars (plus the ego car)"),
    rate_hz: float = typer.Option(10.0, min=0.5, max=50, help="frames per car per second"),
    attack_share: float = typer.Option(0.3, min=0, max=1, help="share of the peers' messages that are attacks"),
    workers: int = typer.Option(2, min=1, max=16, help="engine workers of the started service"),
    warmup: float = typer.Option(10.0, min=0, max=600, help="seconds before RSS is first read"),
    rss_growth_mb: float = typer.Option(150.0, min=0, help="largest RSS growth accepted over the attacks, MB"),
    flood_s: float = typer.Option(
        60.0, min=0, max=3600, help="seconds of the baseline and of the keyless flood phase each (0: neither)"
    ),
    odd_shapes: bool = typer.Option(True, help="end with the odd-shaped signed frames phase"),
    seed: int = typer.Option(7, help="scene and attack seed"),
    connect: str | None = typer.Option(None, help="target a running service's Zenoh endpoint (loopback)"),
    rest: str | None = typer.Option(None, help="... its REST address, e.g. http://127.0.0.1:8000"),
    keys: Path | None = typer.Option(
        None, help="... its fleet authority's directory (bb-align keys init; DIR/ego.cred is the service's)"
    ),
    key: str | None = typer.Option(
        None, envvar="BBALIGN_AUTH__FLEET_KEY", show_default=False, help="... or its fleet HMAC key"
    ),
    prefix: str | None = typer.Option(None, help="... its Zenoh key prefix [bbalign]"),
    pid: int | None = typer.Option(None, help="... its process id (for RSS)"),
    json_out: Path | None = typer.Option(None, "--json", help="write the report as JSON"),
    plot: Path | None = typer.Option(None, help="write a PNG of results/s and drops through the phases"),
) -> None:
    """Drive a service (started here, or --connect) with valid and hostile traffic over Zenoh on loopback: an
    attack mix, a keyless flood against a baseline, odd-shaped frames; account for every message (exit 1 when a
    check fails)."""
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
        flood=FloodPhase(seconds=flood_s) if flood_s > 0 else None,
        odd_shapes=OddShapesPhase() if odd_shapes else None,
        seed=seed,
        connect=connect,
        rest=rest,
        key=key,
        keys_dir=keys,
        prefix=prefix,
        pid=pid,
        plot=plot,
    )
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(report, indent=1))
    for line in _summary(report):
        typer.echo(line)
    for name, ok in report["checks"].items():
        typer.echo(f"  {'ok  ' if ok else ('n/a ' if ok is None else 'FAIL')} {name}")
    if not report["ok"]:
        raise typer.Exit(1)
