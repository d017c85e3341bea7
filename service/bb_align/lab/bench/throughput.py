"""The service under load: an ego car and N peers publish frames at 10 Hz over Zenoh, the ego-side service
(a separate process, as deployed) aligns them and publishes poses; measured are the results per second, the
frames dropped by its latest-only queues, and the latency from publish to pose received.

Everything stays on loopback: the service listens on tcp/127.0.0.1:<free port>, the cars connect there, multicast
scouting is off. Each peer count runs in a fresh service process, which is always stopped.
"""

from __future__ import annotations

import json
import secrets
import time
from collections import Counter
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bb_align.engine.config import AlignConfig
from bb_align.engine.geometry import pose_error, se2, se3_from_se2
from bb_align.protocol import Pose

from ..harness import CarStream, ServiceProcess, free_port, simulated_cars, start_service

EGO_ID = "ego"
PREFIX = "bbalign-bench"


# The service child: explicit settings only (no BBALIGN_* environment), uvicorn on loopback. A fresh fleet key
# for this run comes on stdin (never on the command line) when the service authenticates frames.
class ServiceBenchConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    peer_counts: list[int] = Field([1, 4, 8], min_length=1)
    seconds: float = Field(10.0, gt=0, le=600, description="measured window per peer count")
    warmup_s: float = Field(2.0, ge=0, le=60, description="publishing before the window (caches, connections)")
    grace_s: float = Field(3.0, ge=0, le=60, description="wait for results after the last frame")
    rate_hz: float = Field(10.0, gt=0, le=50)
    workers: int = Field(2, ge=1, le=16)
    frames: int = Field(
        6, ge=1, le=100, description="simulated frames per car, replayed forwards then backwards (no jumps to track)"
    )
    send_odometry: bool = Field(
        True, description="frames carry the car's odometry (here its true pose): the service tracks with it"
    )
    seed: int = 303
    send_pose: bool = Field(True, description="frames carry the car's reported pose (the service then gates matches)")
    pose_sigma_m: float = Field(2.0, ge=0, description="reported-pose noise (GNSS), x and y, 1 sigma")
    pose_sigma_deg: float = Field(2.0, ge=0, description="reported-pose yaw noise, 1 sigma")
    min_distance_m: float = Field(10.0, ge=0)
    max_distance_m: float = Field(40.0, gt=0, description="peers this close mostly align (the full engine runs)")
    startup_timeout_s: float = Field(90.0, gt=0)
    stagger: bool = Field(
        False,
        description="each peer's frames at its own phase of the period, spread evenly after the ego's (LiDARs not "
        "synchronised to a common clock); False: every car's frame at the same instant (LiDARs phase-locked to GNSS "
        "time: each sweep's frames arrive as one burst)",
    )


def phases_s(n_peers: int, period_s: float, stagger: bool) -> list[float]:
    """Each car's publishing offset within the period, the ego's first (0): the peers spread evenly over the
    period when ``stagger``, else all at the ego's instant."""
    return [0.0] + [(j + 1) * period_s / (n_peers + 1) if stagger else 0.0 for j in range(n_peers)]


def simulated_streams(
    cfg: ServiceBenchConfig,
    n_peers: int,
    config: AlignConfig,
    progress: Callable[[Iterable, str], Iterable] | None = None,
) -> list[CarStream]:
    """Ego first, then ``n_peers`` peers 10-40 m away, ``cfg.frames`` consecutive simulated frames each."""
    from ..sim import SimConfig

    return simulated_cars(
        n_peers,
        cfg.frames,
        cfg.seed,
        ego_id=EGO_ID,
        dt=1.0 / cfg.rate_hz,
        sim_config=SimConfig(min_distance_m=cfg.min_distance_m, max_distance_m=cfg.max_distance_m),
        bev_options={"range_m": config.bev.range_m, "resolution_m": config.bev.resolution_m},
        reported_pose=(lambda T, car, k: reported_pose(T, cfg, car, k)) if cfg.send_pose else (lambda T, car, k: None),
        progress=progress,
    )


def loop_index(k: int, n: int) -> int:
    """Frame k of an endless replay of n frames, forwards then backwards (0 1 2 1 0 1 ...): the cars move back
    and forth smoothly, so a track sees motion, never a jump back to the first frame."""
    if n <= 1:
        return 0
    i = k % (2 * (n - 1))
    return i if i < n else 2 * (n - 1) - i


def reported_pose(T_world_sensor: np.ndarray, cfg: ServiceBenchConfig, car: int, frame: int) -> np.ndarray:
    """The true pose with GNSS-like noise, seeded per car and frame: the position off by (dx, dy) in the world, the
    heading off by a yaw about the car itself. (A yaw applied on the left would turn the car about the world
    origin, hundreds of metres away, and move it by tens of metres.)"""
    rng = np.random.default_rng([cfg.seed, car, frame, 11])
    dx, dy = rng.normal(0.0, cfg.pose_sigma_m, 2)
    dyaw = np.radians(rng.normal(0.0, cfg.pose_sigma_deg))
    T = np.asarray(T_world_sensor, dtype=float)
    return se3_from_se2(se2(0.0, dx, dy)) @ T @ se3_from_se2(se2(dyaw, 0.0, 0.0))


# ---- the service process --------------------------------------------------------------------------------------
def start_bench_service(cfg: ServiceBenchConfig, config: AlignConfig, log_dir: Path) -> ServiceProcess:
    from bb_align.server.settings import Settings

    settings = Settings(
        ego_id=EGO_ID,
        host="127.0.0.1",
        port=free_port(),
        workers=cfg.workers,
        align=config,
        zenoh={
            "enabled": True,
            "mode": "peer",
            "listen": [f"tcp/127.0.0.1:{free_port()}"],
            "connect": [],
            "multicast_scouting": False,
            "prefix": PREFIX,
        },
    )
    return start_service(settings, secrets.token_hex(32), log_dir, cfg.startup_timeout_s)


# ---- one load run ---------------------------------------------------------------------------------------------
def _pct(values, qs=(50, 90, 99)) -> dict[str, float]:
    v = np.asarray(values, dtype=float)
    if len(v) == 0:
        return {f"p{q}": float("nan") for q in qs}
    return {f"p{q}": float(np.percentile(v, q)) for q in qs}


def run_load(svc: ServiceProcess, cars: list[CarStream], n_peers: int, cfg: ServiceBenchConfig) -> dict:
    """Publish ego + n_peers frames at cfg.rate_hz for warmup + seconds; return the measured run."""
    import zenoh

    from bb_align.protocol import ZenohSettings, load_result, pack, poses_key
    from bb_align_client import ZenohPeer
    from bb_align_client.zenoh_peer import ArrivalLog

    period = 1.0 / cfg.rate_hz
    n_warm = int(round(cfg.warmup_s * cfg.rate_hz))
    n_ticks = n_warm + int(round(cfg.seconds * cfg.rate_hz))
    streams = cars[: 1 + n_peers]
    received = ArrivalLog()
    sent: dict[tuple[str, int], tuple[float, int]] = {}  # (peer id, seq) -> (publish time, frame index)
    listener = zenoh.open(
        ZenohSettings(
            listen=[], connect=[svc.zenoh_endpoint], multicast_scouting=False, prefix=PREFIX
        ).to_zenoh_config()
    )
    senders = []
    try:
        sub = listener.declare_subscriber(poses_key(PREFIX, EGO_ID, "*"), received)
        signing = {"key": svc.key} if svc.key else {"verify_answers": False}
        senders = [
            ZenohPeer(c.vehicle_id, connect=[svc.zenoh_endpoint], prefix=PREFIX, **signing).open() for c in streams
        ]
        time.sleep(0.5)  # sessions connected before the first frame
        t_base = time.time()
        t0 = time.perf_counter()
        cpu0 = wall0 = None
        phases = phases_s(n_peers, period, cfg.stagger)
        for k in range(n_ticks):
            if k == n_warm:
                cpu0, wall0 = svc.cpu_seconds(), time.perf_counter()
            idx = loop_index(k, len(streams[0].frames))
            for car, sender, phase in zip(streams, senders, phases):  # the ego's frame first
                delay = t0 + k * period + phase - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                stamp = t_base + k * period + phase  # the sweep's own time: its car's phase of the period
                update = {"stamp": stamp, "seq": k}
                if cfg.send_odometry:
                    update["odometry"] = Pose.from_matrix(car.T_world_sensor[idx])
                frame = car.frames[idx].model_copy(update=update)
                data = pack(frame)
                sender.publish(data)
                if car.vehicle_id != EGO_ID:
                    sent[(car.vehicle_id, k)] = (time.perf_counter(), idx)
        wall1, cpu1 = time.perf_counter(), svc.cpu_seconds()
        # Results for the last frames may still be on their way.
        deadline = time.perf_counter() + cfg.grace_s
        expected = {key for key in sent if key[1] >= n_warm}
        got: set = set()
        seen = 0
        while time.perf_counter() < deadline:
            with received.lock:
                new = received.items[seen:]
            seen += len(new)
            got.update(_keys(new))
            if expected <= got:
                break
            time.sleep(0.05)
        sub.undeclare()
        peers_status = svc.get("/v1/peers")
        crosschecks = _engine_runs(svc, "crosscheck")
        memory = svc.memory_mb()
    finally:
        for s in senders:
            s.close()
        listener.close()

    with received.lock:
        items = list(received.items)
    results = []
    for t_recv, data in items:
        try:
            r = load_result(data)
        except ValueError:
            continue
        if r.peer_seq < n_warm or (r.peer_id, r.peer_seq) not in sent:
            continue
        t_sent, idx = sent[(r.peer_id, r.peer_seq)]
        results.append((t_recv - t_sent, r, idx))
    in_window = [key for key in sent if key[1] >= n_warm]
    results.sort(key=lambda x: x[1].peer_seq)
    latency = [x[0] * 1e3 for x in results]
    half = len(results) // 2
    errors = []
    n_frames = len(streams[0].frames)
    for _, r, idx in results:
        if r.success and r.T_ego_peer is not None and r.ego_seq is not None:
            # The service pairs the peer frame with the ego frame nearest in time, not always the same tick.
            car = next(c for c in streams if c.vehicle_id == r.peer_id)
            T_ego = streams[0].T_world_sensor[loop_index(r.ego_seq, n_frames)]
            T_true = np.linalg.inv(T_ego) @ car.T_world_sensor[idx]
            errors.append(pose_error(r.matrix(), T_true))
    window_s = cfg.seconds
    dropped = len(in_window) - len(results)
    lat_first, lat_second = _pct(latency[:half], (50,))["p50"], _pct(latency[half:], (50,))["p50"]
    cores = None
    if cpu0 is not None and cpu1 is not None and wall0 is not None:
        cores = (cpu1 - cpu0) / max(wall1 - wall0, 1e-9)
    drop_fraction = dropped / max(len(in_window), 1)
    sustained = bool(drop_fraction <= 0.01 and (not np.isfinite(lat_first) or lat_second <= 1.25 * lat_first + 10))
    return {
        "peers": n_peers,
        "offered_fps": n_peers * cfg.rate_hz,
        "sent": len(in_window),
        "results": len(results),
        "results_fps": len(results) / window_s,
        "dropped": dropped,
        "drop_fraction": drop_fraction,
        "service_frames_dropped_total": int(sum(p.get("frames_dropped", 0) for p in peers_status.values())),
        "latency_ms": _pct(latency),
        "latency_ms_first_half_p50": lat_first,
        "latency_ms_second_half_p50": lat_second,
        "service_latency_ms": _pct([r.latency_ms for _, r, _ in results if r.latency_ms is not None]),
        "queue_wait_ms": _pct([r.timings_ms.get("queue_wait", 0.0) for _, r, _ in results]),
        "service_timings_ms_p50": {
            k: float(np.median([r.timings_ms.get(k, 0.0) for _, r, _ in results]))
            for k in sorted({k for _, r, _ in results for k in r.timings_ms})
        },
        "success_fraction": float(np.mean([r.success for _, r, _ in results])) if results else 0.0,
        "outcomes": dict(Counter("success" if r.success else str(r.reason) for _, r, _ in results)),
        "sources": dict(Counter(str(r.source) for _, r, _ in results)),
        "per_peer_results_fps": {
            c.vehicle_id: sum(1 for _, r, _ in results if r.peer_id == c.vehicle_id) / window_s for c in streams[1:]
        },
        # answered without a measurement of their own (the service behind its frames: unmeasured_after_s)
        "measured_fps": sum(1 for _, r, _ in results if r.source not in ("stream", "prediction")) / window_s,
        "wrong": sum(1 for t, d in errors if t > 1.0 or d > 1.0),  # successes 1 m / 1 deg or more off the truth
        "t_err_median_m": float(np.median([e[0] for e in errors])) if errors else None,
        "r_err_median_deg": float(np.median([e[1] for e in errors])) if errors else None,
        "service_cpu_cores": cores,
        # the tracks' cross-checks (full acquisitions beside the tracks) over warm-up and window, and how often
        # each track got one on average
        "crosschecks": crosschecks,
        "crosscheck_every_s_per_track": (n_peers * n_ticks * period / crosschecks) if crosschecks else None,
        "service_memory": memory,
        "sustained": sustained,
    }


def _engine_runs(svc: ServiceProcess, step: str) -> int | None:
    """How many times the service ran an engine step (its /metrics ``bbalign_engine_seconds_count``)."""
    import httpx

    from ..soak_phases import metric_sum, read_metrics

    try:
        return int(metric_sum(read_metrics(svc.rest), "bbalign_engine_seconds_count", step=step))
    except httpx.HTTPError:
        return None


def _keys(items):
    """(peer id, seq) of received results; unreadable publications are not counted."""
    from bb_align.protocol import load_result

    for _, data in items:
        try:
            r = load_result(data)
        except ValueError:
            continue
        yield r.peer_id, r.peer_seq


def measure_service(
    cfg: ServiceBenchConfig,
    config: AlignConfig,
    progress: Callable[[Iterable, str], Iterable] | None = None,
    log_dir: Path | None = None,
) -> dict:
    """One fresh service process per peer count; the report's ``service`` section (or an ``error``)."""
    import tempfile

    pose = (
        f"reported poses with {cfg.pose_sigma_m:g} m / {cfg.pose_sigma_deg:g} deg noise"
        if cfg.send_pose
        else "no reported poses"
    )
    out: dict = {
        "transport": "zenoh tcp/127.0.0.1 (multicast scouting off)",
        "poses": pose,
        "rate_hz": cfg.rate_hz,
        "seconds": cfg.seconds,
        "warmup_s": cfg.warmup_s,
        "workers": cfg.workers,
        "config": json.loads(cfg.model_dump_json()),
        "runs": {},
    }
    try:
        cars = simulated_streams(cfg, max(cfg.peer_counts), config, progress)
    except Exception as e:  # report, do not lose the engine numbers already measured
        return {**out, "error": f"building the frames failed: {type(e).__name__}: {e}"}
    with tempfile.TemporaryDirectory(prefix="bbalign-bench-") as tmp:
        logs = Path(log_dir or tmp)
        for n in progress(cfg.peer_counts, "service runs") if progress else cfg.peer_counts:
            svc = None
            try:
                svc = start_bench_service(cfg, config, logs)
                out["runs"][str(n)] = run_load(svc, cars, n, cfg)
            except Exception as e:
                out.setdefault("errors", {})[str(n)] = f"{type(e).__name__}: {e}"
            finally:
                if svc is not None:
                    svc.stop()
    return out
