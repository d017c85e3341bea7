"""A tracking soak with a crash: a real service on loopback, N simulated peers at 10 Hz with tracking and odometry,
odometry jumps injected, ``kill -9`` of the service mid-stream and a restart; every answer checked against the
truth.

The service runs as ``bb-align serve`` runs (a child process, the vehicle profile: frames signed with a fresh
fleet key, stamps checked against its clock) on free loopback ports. The ego and ``peers`` cars (bb_align.lab.sim
scenes, 10-40 m apart) replay their simulated frames forwards then backwards (bb_align.lab.harness.to_and_fro_times:
each car stops and turns round as a car can, no jump back to the first frame), stamped with the time their tick was
due, each frame carrying the car's reported pose (GNSS noise) and its odometry (the true pose seen from the car's
own odometry origin). ``jumps`` re-anchor one car's odometry by 1-7 m at a given second (a relocalisation;
bb_align.lab.tracking.faults). At ``kill_at`` of the run the service is killed with SIGKILL (only the process this
harness started, by its id) and started again on the same ports while the cars keep publishing; Zenoh reconnects
the cars by itself.

Measured: every successful answer against the truth of the exact ego and peer frames it used (wrong: off by more
than 1 m or 1 deg), answered and dropped per peer, latency publish -> result, the service's RSS and CPU and the
machine's load average every ``sample_s``, and per peer the time from the kill (and from the restarted service's
readiness) until it is answered again, and until it is answered successfully again.
"""

from __future__ import annotations

import json
import os
import secrets
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bb_align.engine.geometry import pose_error, se2, se3_from_se2

from ..harness import CarStream, ServiceProcess, free_port, simulated_cars, start_service
from .faults import OdometryFault

EGO_ID = "ego"
PREFIX = "bbalign-tracksoak"
WRONG_M, WRONG_DEG = 1.0, 1.0


class SoakJump(BaseModel):
    """One car's odometry re-anchored by (dx, dy) m from ``at_s`` on (s from the start of publishing)."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    car: str
    at_s: float = Field(ge=0)
    dx: float
    dy: float


def default_jumps(seconds: float) -> list[SoakJump]:
    """Four re-anchorings of 1-7 m spread over the run: the ego's (every peer's track sees it) and three peers'."""
    plan = [("ego", 0.15, 4.0, 4.0), ("car3", 0.3, 0.0, 3.0), ("car5", 0.45, 7.0, 0.0), ("car2", 0.85, 1.0, 0.0)]
    return [SoakJump(car=c, at_s=round(f * seconds, 1), dx=dx, dy=dy) for c, f, dx, dy in plan]


class TrackSoakConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    peers: int = Field(8, ge=1, le=16)
    rate_hz: float = Field(10.0, gt=0, le=20)
    seconds: float = Field(1800.0, gt=0, le=7200, description="publishing time")
    kill_at: float | None = Field(0.6, gt=0, lt=1, description="SIGKILL the service at this share of the run")
    jumps: list[SoakJump] | None = Field(None, description="None: default_jumps(seconds)")
    frames: int = Field(
        80,
        ge=2,
        le=400,
        description="simulated frames per car, replayed forwards then backwards: 80 let the cars stop and turn round "
        "at 6 m/s^2 and still drive about 4 s of the scene (its distances spread as 40 frames at its own pace did)",
    )
    seed: int = 404
    min_distance_m: float = Field(10.0, ge=0)
    max_distance_m: float = Field(40.0, gt=0)
    pose_sigma_m: float = Field(2.0, ge=0, description="reported-pose (GNSS) noise, x and y, 1 sigma")
    pose_sigma_deg: float = Field(2.0, ge=0)
    workers: int = Field(2, ge=1, le=16)
    sample_s: float = Field(5.0, gt=0, description="RSS, CPU and load average sampled this often")
    rss_flat_mb_per_min: float = Field(
        0.25,
        gt=0,
        description="RSS counts as flat when, in each process, the least-squares slope of its per-minute lowest "
        "value after warm-up is below this (15 MB an hour; the creep before the allocator settings was 1.2-1.5 "
        "MB/min on a quiet machine)",
    )
    grace_s: float = Field(5.0, ge=0, description="results awaited after the last frame")
    startup_timeout_s: float = Field(120.0, gt=0)

    def jump_plan(self) -> list[SoakJump]:
        return default_jumps(self.seconds) if self.jumps is None else list(self.jumps)


def loop_index(k: int, n: int) -> int:
    """Frame k of an endless replay of n frames, forwards then backwards (0 1 .. n-1 n-2 .. 1 0 1 ..)."""
    if n <= 1:
        return 0
    i = k % (2 * (n - 1))
    return i if i < n else 2 * (n - 1) - i


def reported_pose(T_world_sensor: np.ndarray, cfg: TrackSoakConfig, car: int, frame: int) -> np.ndarray:
    """The true pose with GNSS-like noise (position in the world, heading about the car), seeded per car, frame."""
    rng = np.random.default_rng([cfg.seed, car, frame, 11])
    dx, dy = rng.normal(0.0, cfg.pose_sigma_m, 2)
    dyaw = np.radians(rng.normal(0.0, cfg.pose_sigma_deg))
    return se3_from_se2(se2(0.0, dx, dy)) @ np.asarray(T_world_sensor, float) @ se3_from_se2(se2(dyaw, 0.0, 0.0))


def odometry_origins(cars: list[CarStream], seed: int) -> dict[str, np.ndarray]:
    """Each car's odometry frame: its own origin (a 4x4 T_odom_world), far from the world's."""
    rng = np.random.default_rng([seed, 77])
    return {c.vehicle_id: se3_from_se2(se2(rng.uniform(-np.pi, np.pi), *rng.uniform(-500.0, 500.0, 2))) for c in cars}


@dataclass
class Row:
    """One result as received, checked against the truth."""

    t_recv: float  # s since publishing started
    peer: str
    seq: int
    ego_seq: int | None
    success: bool
    source: str | None
    reason: str | None
    latency_ms: float
    err_m: float | None
    err_deg: float | None
    distance_m: float
    event: str | None = None  # the track's event, when its state changed

    @property
    def wrong(self) -> bool:
        return self.success and (self.err_m is None or self.err_m > WRONG_M or self.err_deg > WRONG_DEG)


@dataclass
class Collector:
    """The subscriber callback (Zenoh's threads): every result decoded, matched to its frame and its truth."""

    cars: list[CarStream]
    t0: float
    sent: dict = field(default_factory=dict)  # (peer, seq) -> publish time (perf_counter)
    rows: list[Row] = field(default_factory=list)
    refusals: Counter = field(default_factory=Counter)
    unknown: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self):
        self.by_id = {c.vehicle_id: c for c in self.cars}
        self.n = len(self.cars[0].frames)

    def __call__(self, sample) -> None:
        from bb_align.protocol import Refusal, load_answer

        t = time.perf_counter()
        try:
            r = load_answer(sample.payload.to_bytes())
        except ValueError as e:
            with self.lock:
                self.refusals[f"undecodable: {e}"[:80]] += 1
            return
        if isinstance(r, Refusal):
            with self.lock:
                self.refusals[str(r.refused.error)] += 1
            return
        with self.lock:
            t_sent = self.sent.get((r.peer_id, r.peer_seq))
        if t_sent is None:
            with self.lock:
                self.unknown += 1
            return
        T_true = self.truth(r.peer_id, r.peer_seq, r.ego_seq)
        err = pose_error(r.matrix(), T_true) if (r.T_ego_peer is not None and T_true is not None) else (None, None)
        ref = T_true if T_true is not None else self.truth(r.peer_id, r.peer_seq, r.peer_seq)
        row = Row(
            t - self.t0,
            r.peer_id,
            r.peer_seq,
            r.ego_seq,
            bool(r.success),
            r.source,
            r.reason,
            (t - t_sent) * 1e3,
            err[0],
            err[1],
            float(np.hypot(ref[0, 3], ref[1, 3])),
            r.track_event,
        )
        with self.lock:
            self.rows.append(row)

    def truth(self, peer: str, seq: int, ego_seq: int | None) -> np.ndarray | None:
        """The true T_ego_peer of peer frame ``seq`` against ego frame ``ego_seq`` (the pair the service used)."""
        if ego_seq is None or peer not in self.by_id:
            return None
        T_ego = self.by_id[EGO_ID].T_world_sensor[loop_index(ego_seq, self.n)]
        return np.linalg.inv(T_ego) @ self.by_id[peer].T_world_sensor[loop_index(seq, self.n)]


# ---- the run ---------------------------------------------------------------------------------------------------
def soak_settings(cfg: TrackSoakConfig):
    """The service's settings: the vehicle profile on free loopback ports (kept for the restart)."""
    from bb_align.server.settings import Settings

    return Settings(
        ego_id=EGO_ID,
        host="127.0.0.1",
        port=free_port(),
        workers=cfg.workers,
        zenoh={
            "enabled": True,
            "mode": "peer",
            "listen": [f"tcp/127.0.0.1:{free_port()}"],
            "connect": [],
            "multicast_scouting": False,
            "prefix": PREFIX,
        },
    )


@dataclass
class Life:
    """One service process's life in the run: started, killed or stopped (s since publishing started)."""

    svc: ServiceProcess
    started_s: float | None  # ready (None: before publishing started)
    ended_s: float | None = None
    how: str | None = None


class Restart(threading.Thread):
    """Start the service again (same settings, same ports) beside the publishing loop, which must not wait."""

    def __init__(self, settings, key: str, log_dir: Path, timeout_s: float, t0: float):
        super().__init__(name="bbalign-soak-restart", daemon=True)
        self.args, self.t0 = (settings, key, log_dir, timeout_s), t0
        self.svc: ServiceProcess | None = None
        self.ready_s: float | None = None
        self.error: str | None = None

    def run(self) -> None:
        try:
            self.svc = start_service(*self.args)
            self.ready_s = time.perf_counter() - self.t0
        except Exception as e:  # reported in the run's output
            self.error = f"{type(e).__name__}: {e}"


def anonymous_mb(pid: int | None) -> float | None:
    """A process's anonymous resident memory (heaps, mappings of its own; not its mapped files), MB."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Anonymous:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


def _sample(lives: list[Life], collector: Collector, t: float) -> dict:
    svc = lives[-1].svc
    mem = svc.memory_mb()
    with collector.lock:
        n, ok = len(collector.rows), sum(r.success for r in collector.rows)
        wrong = sum(r.wrong for r in collector.rows)
    return {
        "t_s": round(t, 2),
        "pid": svc.pid,
        "rss_mb": mem["rss_mb"],
        "anon_mb": anonymous_mb(svc.pid),
        **_heap(svc),
        "cpu_s": svc.cpu_seconds(),
        "harness_cpu_s": sum(os.times()[:2]),
        "load": [float(v) for v in Path("/proc/loadavg").read_text().split()[:3]],
        "results": n,
        "successes": ok,
        "wrong": wrong,
    }


def publish_loop(
    cfg: TrackSoakConfig,
    cars: list[CarStream],
    senders: list,
    collector: Collector,
    lives: list[Life],
    on_kill: Callable[[float], Restart],
    progress: Callable[[Iterable, str], Iterable] | None,
) -> dict:
    """Publish every car's frame each tick for cfg.seconds; SIGKILL and restart at kill_at; sample every sample_s."""
    from bb_align.protocol import Pose, pack

    period, n = 1.0 / cfg.rate_hz, len(cars[0].frames)
    n_ticks = int(round(cfg.seconds * cfg.rate_hz))
    kill_tick = None if cfg.kill_at is None else int(round(cfg.kill_at * n_ticks))
    faults = [OdometryFault(j.car, int(round(j.at_s * cfg.rate_hz)), j.dx, j.dy) for j in cfg.jump_plan()]
    origins = odometry_origins(cars, cfg.seed)
    samples, lag_max, restart = [], 0.0, None
    every = max(1, int(round(cfg.sample_s * cfg.rate_hz)))
    t_base, t0 = time.time(), collector.t0
    ticks = range(n_ticks)
    for k in progress(ticks, "publishing") if progress else ticks:
        delay = t0 + k * period - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        lag_max = max(lag_max, -delay)
        if k == kill_tick:
            restart = on_kill(time.perf_counter() - t0)
        if restart is not None and restart.svc is not None and lives[-1].svc is not restart.svc:
            lives.append(Life(restart.svc, restart.ready_s))
        if k % every == 0:
            samples.append(_sample(lives, collector, time.perf_counter() - t0))
        idx = loop_index(k, n)
        for car, sender in zip(cars, senders):  # the ego's frame first
            O = origins[car.vehicle_id] @ car.T_world_sensor[idx]
            for fault in faults:
                O = fault.apply(car.vehicle_id, k, O)
            frame = car.frames[idx].model_copy(
                update={"stamp": t_base + k * period, "seq": k, "odometry": Pose.from_matrix(O)}
            )
            data = pack(frame)
            if car.vehicle_id != EGO_ID:
                with collector.lock:
                    collector.sent[(car.vehicle_id, k)] = time.perf_counter()
            sender.publish(data)
    if restart is not None:
        restart.join(cfg.startup_timeout_s)
        if restart.svc is not None and lives[-1].svc is not restart.svc:
            lives.append(Life(restart.svc, restart.ready_s))
    return {"samples": samples, "publisher_lag_max_s": lag_max, "restart_error": restart and restart.error}


def run_track_soak(
    cfg: TrackSoakConfig,
    log_dir: Path,
    progress: Callable[[Iterable, str], Iterable] | None = None,
    cache: Path | None = None,
    rows_out: Path | None = None,
) -> dict:
    """The whole soak; returns the report (``report["checks"]``). ``cache``: a folder keeping the simulated cars
    between runs (pickled; only this harness's own files are read back); ``rows_out``: every result as JSON lines."""
    import zenoh

    from bb_align.protocol import ZenohSettings, poses_key
    from bb_align_client import ZenohPeer

    from ..sim import SimConfig

    t_build = time.perf_counter()
    cars = _cached(
        cache,
        (
            "to-and-fro",  # the frames' times (harness.to_and_fro_times): cars cached before it are not reused
            cfg.peers,
            cfg.frames,
            cfg.seed,
            cfg.rate_hz,
            cfg.min_distance_m,
            cfg.max_distance_m,
            cfg.pose_sigma_m,
            cfg.pose_sigma_deg,
        ),
        lambda: simulated_cars(
            cfg.peers,
            cfg.frames,
            cfg.seed,
            ego_id=EGO_ID,
            dt=1.0 / cfg.rate_hz,
            sim_config=SimConfig(min_distance_m=cfg.min_distance_m, max_distance_m=cfg.max_distance_m),
            reported_pose=lambda T, car, k: reported_pose(T, cfg, car, k),
            progress=progress,
        ),
    )
    build_s = time.perf_counter() - t_build
    settings, key = soak_settings(cfg), secrets.token_hex(32)
    lives = [Life(start_service(settings, key, log_dir, cfg.startup_timeout_s), None)]
    endpoint = lives[0].svc.zenoh_endpoint
    listener, senders = None, []
    collector = Collector(cars, 0.0)
    kill: dict = {}

    def on_kill(t: float) -> Restart:
        life = lives[-1]
        life.svc.proc.kill()  # SIGKILL to the child this harness started, by its id
        life.svc.proc.wait(30)
        life.ended_s, life.how = time.perf_counter() - collector.t0, "SIGKILL"
        kill.update(t_s=t, pid=life.svc.pid)
        r = Restart(settings, key, log_dir, cfg.startup_timeout_s, collector.t0)
        r.start()
        return r

    try:
        zs = ZenohSettings(listen=[], connect=[endpoint], multicast_scouting=False, prefix=PREFIX)
        listener = zenoh.open(zs.to_zenoh_config())
        sub = listener.declare_subscriber(poses_key(PREFIX, EGO_ID, "*"), collector)
        senders = [ZenohPeer(c.vehicle_id, connect=[endpoint], prefix=PREFIX, key=key).open() for c in cars]
        time.sleep(1.0)  # sessions connected before the first frame
        collector.t0 = time.perf_counter()
        run = publish_loop(cfg, cars, senders, collector, lives, on_kill, progress)
        time.sleep(cfg.grace_s)  # the last frames' results
        last = lives[-1]
        run["samples"].append(_sample(lives, collector, time.perf_counter() - collector.t0))
        if last.svc.proc.poll() is None:
            run["peers_status"] = last.svc.get("/v1/peers")
            run["metrics"] = _metrics(last.svc)
        sub.undeclare()
    finally:
        for s in senders:
            s.close()
        if listener is not None:
            listener.close()
        for life in lives:
            if life.svc.proc is not None and life.svc.proc.poll() is None:
                life.ended_s = time.perf_counter() - collector.t0
                code = life.svc.stop()
                life.how = f"SIGTERM, exit {code}"
    if rows_out is not None:
        with open(rows_out, "w") as fh:
            for r in sorted(collector.rows, key=lambda r: r.t_recv):
                fh.write(json.dumps(vars(r)) + "\n")
    rep = report(cfg, cars, collector, lives, run, kill, build_s)
    keys = ("frames_accepted", "frames_dropped", "intake_dropped", "results", "failed")
    status = run.get("peers_status") or {}
    rep["service_counters_last_life"] = {p: {k: v.get(k) for k in keys} for p, v in status.items()}
    rep["service_metrics_last_life"] = run.get("metrics")
    return rep


def _metrics(svc: ServiceProcess) -> dict[str, float]:
    """The service's intake, door, drop and rejection counters (/metrics), summed over their peer labels."""
    import re

    from ..soak_phases import read_metrics

    out: dict[str, float] = defaultdict(float)
    for name, value in read_metrics(svc.rest).items():
        if name.startswith(("bbalign_frames", "bbalign_intake", "bbalign_door", "bbalign_alignments_total")):
            out[re.sub(r'peer="[^"]*",?', "", name).replace(",}", "}").replace("{}", "")] += value
    return dict(out)


def _heap(svc: ServiceProcess) -> dict[str, float]:
    """The service's C heap in use and free (MB) and Python's allocated blocks, from /metrics; {} when the
    service does not answer (being killed, restarting) or its C library has no mallinfo2."""
    import httpx

    from ..soak_phases import read_metrics

    names = {
        'bbalign_heap_bytes{state="in_use"}': ("heap_in_use_mb", 2**-20),
        'bbalign_heap_bytes{state="free"}': ("heap_free_mb", 2**-20),
        "bbalign_python_blocks": ("python_blocks", 1.0),
    }
    try:
        metrics = read_metrics(svc.rest, timeout=2.0)
    except httpx.HTTPError:
        return {}
    return {key: metrics[name] * scale for name, (key, scale) in names.items() if name in metrics}


def _cached(folder: Path | None, key: tuple, build: Callable[[], list[CarStream]]) -> list[CarStream]:
    """``build()``, kept in ``folder`` under a name made of ``key`` (the simulation takes minutes)."""
    import hashlib
    import pickle

    if folder is None:
        return build()
    path = Path(folder) / f"tracksoak-cars-{hashlib.sha1(repr(key).encode()).hexdigest()[:16]}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())  # noqa: S301 (a file this harness wrote)
    cars = build()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(cars))
    return cars


# ---- the report ------------------------------------------------------------------------------------------------
def _pct(values, qs=(50, 90, 99, 100)) -> dict[str, float | None]:
    v = np.asarray(list(values), dtype=float)
    return {f"p{q}": (float(np.percentile(v, q)) if len(v) else None) for q in qs}


def _wrong_rows(rows: list[Row], limit: int = 50) -> list[dict]:
    return [vars(r) for r in rows if r.wrong][:limit]


def recovery(rows: list[Row], peers: list[str], kill_s: float, kill_tick: int, ready_s: float | None) -> dict:
    """Per peer: s from the kill until the first answer (and the first successful one) for a frame published after
    the kill, and the same from the restarted service's readiness."""
    out, after = {}, [r for r in rows if r.seq >= kill_tick]
    for p in peers:
        mine = sorted((r for r in after if r.peer == p), key=lambda r: r.t_recv)
        first = mine[0].t_recv if mine else None
        first_ok = next((r.t_recv for r in mine if r.success), None)
        out[p] = {
            "answered_after_kill_s": None if first is None else first - kill_s,
            "success_after_kill_s": None if first_ok is None else first_ok - kill_s,
            "answered_after_ready_s": None if first is None or ready_s is None else first - ready_s,
            "success_after_ready_s": None if first_ok is None or ready_s is None else first_ok - ready_s,
        }
    return out


def _per_peer(rows: list[Row], sent: dict, peers: list[str]) -> dict:
    out = {}
    for p in peers:
        mine = [r for r in rows if r.peer == p]
        n_sent = sum(1 for (q, _) in sent if q == p)
        out[p] = {
            "sent": n_sent,
            "answered": len(mine),
            "dropped": n_sent - len(mine),
            "successful": sum(r.success for r in mine),
            "wrong": sum(r.wrong for r in mine),
            "distance_m": [round(min(r.distance_m for r in mine), 1), round(max(r.distance_m for r in mine), 1)]
            if mine
            else None,
            "latency_ms": _pct(r.latency_ms for r in mine),
            "error_m_p99": _pct((r.err_m for r in mine if r.success and r.err_m is not None), (99,))["p99"],
        }
    return out


def _jumps(rows: list[Row], cfg: TrackSoakConfig, window_s: float = 10.0) -> list[dict]:
    """Around each jump: the affected peers' answers in the window_s after it (by their frames' time)."""
    out = []
    for j in cfg.jump_plan():
        k0, k1 = int(round(j.at_s * cfg.rate_hz)), int(round((j.at_s + window_s) * cfg.rate_hz))
        near = [r for r in rows if k0 <= r.seq < k1 and (j.car == EGO_ID or r.peer == j.car)]
        by_peer = defaultdict(list)
        for r in sorted(near, key=lambda r: r.seq):
            by_peer[r.peer].append(r)
        first_ok = [next(((r.seq - k0) / cfg.rate_hz for r in v if r.success), None) for v in by_peer.values()]
        out.append(
            {
                **j.model_dump(),
                "answers_in_window": len(near),
                "successful": sum(r.success for r in near),
                "wrong": sum(r.wrong for r in near),
                "events": Counter((r.event or "").split(" (")[0] for r in near if r.event).most_common(5),
                "first_success_after_s": first_ok,
            }
        )
    return out


def _rss(samples: list[dict], lives: list[Life], warmup_s: float) -> list[dict]:
    """Per service process: RSS after warm-up (first, last, max) and its least-squares slope."""
    out = []
    for life in lives:
        start = life.started_s or 0.0
        mine = [s for s in samples if s["pid"] == life.svc.pid and s["rss_mb"] is not None]
        late = [s for s in mine if s["t_s"] >= start + warmup_s]
        row = {"pid": life.svc.pid, "started_s": life.started_s, "ended_s": life.ended_s, "how": life.how}
        if len(late) >= 3:
            t = np.array([s["t_s"] for s in late]) / 60.0
            m = np.array([s["rss_mb"] for s in late])
            slope, se = _slope(t, m)
            row.update(
                samples=len(late),
                minutes=float(t[-1] - t[0]),
                rss_first_mb=float(m[0]),
                rss_last_mb=float(m[-1]),
                rss_min_mb=float(m.min()),
                rss_max_mb=float(m.max()),
                slope_mb_per_min=slope,
                slope_se_mb_per_min=se,
            )
            floor_t, floor_m = _minute_floor(t, m)
            if len(floor_t) >= 3:
                row["floor_slope_mb_per_min"], row["floor_slope_se_mb_per_min"] = _slope(floor_t, floor_m)
                row["floor_mb"] = [round(float(v), 1) for v in floor_m]
            for key in ("anon_mb", "heap_in_use_mb", "heap_free_mb", "python_blocks"):  # a slope each, per minute
                pts = [(s["t_s"] / 60.0, s[key]) for s in late if s.get(key) is not None]
                if len(pts) >= 3:
                    name, unit = key.removesuffix("_mb"), "_mb" if key.endswith("_mb") else ""
                    row[f"{name}_slope{unit}_per_min"] = _slope(*map(np.array, zip(*pts)))[0]
                    row[f"{name}_first"], row[f"{name}_last"] = pts[0][1], pts[-1][1]
        out.append(row)
    return out


def _minute_floor(t_min: np.ndarray, mb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lowest RSS of each whole minute (with at least half its samples): the memory the process keeps,
    without the large arrays in flight at the moment of a sample (they swing the RSS by 10-40 MB)."""
    minute = np.floor(t_min - t_min[0])
    full = max(2, int(0.5 * np.median(np.unique(minute, return_counts=True)[1])))
    keep = [k for k in np.unique(minute) if (minute == k).sum() >= full]
    return np.array(keep) + t_min[0], np.array([mb[minute == k].min() for k in keep])


def _slope(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of y against t and its standard error."""
    b, a = np.polyfit(t, y, 1)
    res = y - (a + b * t)
    se = np.sqrt(res @ res / max(1, len(t) - 2) / ((t - t.mean()) @ (t - t.mean())))
    return float(b), float(se)


def report(cfg, cars, collector: Collector, lives: list[Life], run: dict, kill: dict, build_s: float) -> dict:
    rows = sorted(collector.rows, key=lambda r: r.t_recv)
    peers = [c.vehicle_id for c in cars if c.vehicle_id != EGO_ID]
    kill_tick = None if cfg.kill_at is None else int(round(cfg.kill_at * cfg.seconds * cfg.rate_hz))
    ready_s = lives[1].started_s if len(lives) > 1 else None
    rec = recovery(rows, peers, kill["t_s"], kill_tick, ready_s) if kill else {}
    samples = run["samples"]
    loads = [s["load"][0] for s in samples]
    warm = min(120.0, 0.2 * cfg.seconds)
    answered_again = [v["answered_after_kill_s"] for v in rec.values()]
    rep = {
        "config": json.loads(cfg.model_dump_json()),
        "jumps": [j.model_dump() for j in cfg.jump_plan()],
        "machine": {
            "cpus": os.cpu_count(),
            "load_1min": {"min": min(loads), "mean": float(np.mean(loads)), "max": max(loads)} if loads else None,
        },
        "frames_built_s": build_s,
        "publisher_lag_max_s": run["publisher_lag_max_s"],
        "sent": len(collector.sent),
        "answered": len(rows),
        "successful": sum(r.success for r in rows),
        "wrong": sum(r.wrong for r in rows),
        "wrong_rows": _wrong_rows(rows),
        "outcomes": dict(Counter("success" if r.success else str(r.reason) for r in rows).most_common()),
        "sources": dict(Counter(f"{r.source}:{'ok' if r.success else 'no'}" for r in rows).most_common()),
        "refusals": dict(collector.refusals),
        "unmatched_results": collector.unknown,
        "latency_ms": _pct(r.latency_ms for r in rows),
        "error_successful": {
            "m": _pct(r.err_m for r in rows if r.success and r.err_m is not None),
            "deg": _pct(r.err_deg for r in rows if r.success and r.err_deg is not None),
        },
        "per_peer": _per_peer(rows, collector.sent, peers),
        "jump_windows": _jumps(rows, cfg),
        "kill": kill or None,
        "restart_ready_s": ready_s,
        "restart_error": run.get("restart_error"),
        "recovery": rec,
        "recovery_max_s": max((v for v in answered_again if v is not None), default=None),
        "services": _rss(samples, lives, warm),
        "rss_warmup_s": warm,
        "samples": samples,
    }
    rep["checks"] = {
        "no_wrong_success": rep["wrong"] == 0,
        "every_peer_answered_after_restart": bool(kill) and all(v is not None for v in answered_again),
        "every_peer_answered": all(v["answered"] > 0 for v in rep["per_peer"].values()),
        "rss_flat_after_warmup": all(
            s["floor_slope_mb_per_min"] < cfg.rss_flat_mb_per_min
            for s in rep["services"]
            if "floor_slope_mb_per_min" in s
        ),
    }
    return rep


# ---- figure and text -------------------------------------------------------------------------------------------
def plot_track_soak(rep: dict, path: Path, bin_s: float = 10.0) -> None:
    """RSS of the service (each process), results and successful answers per second, latency p50/p99 and the
    machine's load average against time; the jumps and the kill marked."""
    from bb_align.io.plot import pyplot

    plt = pyplot()
    samples = rep["samples"]
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for pid in sorted({s["pid"] for s in samples}):
        mine = [s for s in samples if s["pid"] == pid and s["rss_mb"] is not None]
        t_min = [s["t_s"] / 60 for s in mine]
        (line,) = axes[0].plot(t_min, [s["rss_mb"] for s in mine], ".-", label=f"service pid {pid} RSS")
        anon = [(t, s["anon_mb"]) for t, s in zip(t_min, mine) if s.get("anon_mb") is not None]
        if anon:
            axes[0].plot(*zip(*anon), ":", color=line.get_color(), label=f"pid {pid} anonymous")
        heap = [(t, s["heap_in_use_mb"]) for t, s in zip(t_min, mine) if s.get("heap_in_use_mb") is not None]
        if heap:
            axes[0].plot(*zip(*heap), "--", color=line.get_color(), label=f"pid {pid} C heap in use")
    axes[0].set_ylabel("service memory (MB)")
    t = np.array([s["t_s"] for s in samples])
    res, ok = np.array([s["results"] for s in samples]), np.array([s["successes"] for s in samples])
    dt = np.diff(t)
    axes[1].plot(t[1:] / 60, np.diff(res) / dt, "-", label="results /s")
    axes[1].plot(t[1:] / 60, np.diff(ok) / dt, "-", label="successful /s")
    wrong = np.array([s["wrong"] for s in samples])
    axes[1].plot(t[1:] / 60, np.diff(wrong) / dt, "r-", label="wrong successes /s")
    axes[1].set_ylabel("answers per second")
    axes[2].plot(t / 60, [s["load"][0] for s in samples], "k-", label="load average (1 min)")
    axes[2].set_ylabel("load average")
    axes[2].set_xlabel("minutes")
    for ax in axes:
        for j in rep["jumps"]:
            ax.axvline(j["at_s"] / 60, color="orange", ls="--", lw=0.8)
        if rep.get("kill"):
            ax.axvline(rep["kill"]["t_s"] / 60, color="red", lw=1.0)
        if rep.get("restart_ready_s"):
            ax.axvline(rep["restart_ready_s"] / 60, color="green", lw=1.0)
        ax.legend(fontsize=8, loc="upper right")
    peers, wrong = len(rep["per_peer"]), rep["wrong"]
    fig.suptitle(
        f"tracking soak: {peers} peers at {rep['config']['rate_hz']:g} Hz, {rep['answered']} answered, "
        f"{rep['successful']} successful, {wrong} wrong\norange: odometry jumps, red: kill -9, green: the restarted "
        "service ready"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def summary_lines(rep: dict) -> list[str]:
    lat, load = rep["latency_ms"], rep["machine"]["load_1min"]
    lines = [
        f"{rep['sent']} peer frames sent, {rep['answered']} answered, {rep['successful']} successful, "
        f"{rep['wrong']} wrong (off > {WRONG_M:g} m or {WRONG_DEG:g} deg)",
        f"latency publish -> result p50 {lat['p50']:.0f} ms, p90 {lat['p90']:.0f} ms, p99 {lat['p99']:.0f} ms, "
        f"max {lat['p100']:.0f} ms; publisher lag max {rep['publisher_lag_max_s']:.2f} s",
        f"load average (1 min) during the run: min {load['min']:.2f}, mean {load['mean']:.2f}, max {load['max']:.2f}"
        f" on {rep['machine']['cpus']} CPUs",
    ]
    for p, v in rep["per_peer"].items():
        lines.append(
            f"  {p}: sent {v['sent']}, answered {v['answered']}, dropped {v['dropped']}, successful "
            f"{v['successful']}, wrong {v['wrong']}, distance {v['distance_m']} m, latency p50 "
            f"{v['latency_ms']['p50'] or float('nan'):.0f} ms"
        )
    for j in rep["jump_windows"]:
        lines.append(
            f"  jump {j['car']} ({j['dx']:g}, {j['dy']:g}) m at {j['at_s']:g} s: {j['successful']} of "
            f"{j['answers_in_window']} successful in 10 s, {j['wrong']} wrong; "
            f"first success after {j['first_success_after_s']} s"
        )
    if rep["kill"]:
        lines.append(
            f"kill -9 at {rep['kill']['t_s']:.1f} s, restarted service ready after "
            f"{(rep['restart_ready_s'] or float('nan')) - rep['kill']['t_s']:.1f} s; every peer answered again "
            f"within {rep['recovery_max_s']} s of the kill"
        )
    for s in rep["services"]:
        if "slope_mb_per_min" in s:
            lines.append(
                f"  service pid {s['pid']} ({s['how']}): RSS after warm-up {s['rss_first_mb']:.0f} -> "
                f"{s['rss_last_mb']:.0f} MB over {s['minutes']:.1f} min (min {s['rss_min_mb']:.0f}, max "
                f"{s['rss_max_mb']:.0f}), slope {s['slope_mb_per_min']:+.2f} +- {s['slope_se_mb_per_min']:.2f} MB/min"
                f"; per-minute lowest {s.get('floor_slope_mb_per_min', float('nan')):+.2f} +- "
                f"{s.get('floor_slope_se_mb_per_min', float('nan')):.2f} MB/min (flat: below "
                f"{rep['config']['rss_flat_mb_per_min']:g}); anonymous memory "
                f"{s.get('anon_slope_mb_per_min', float('nan')):+.2f} MB/min; C heap in use "
                f"{s.get('heap_in_use_slope_mb_per_min', float('nan')):+.3f} MB/min, free "
                f"{s.get('heap_free_slope_mb_per_min', float('nan')):+.3f} MB/min; Python blocks "
                f"{s.get('python_blocks_slope_per_min', float('nan')):+.0f} /min"
            )
    lines.append("checks: " + ", ".join(f"{k} {'ok' if v else 'FAILED'}" for k, v in rep["checks"].items()))
    return lines
