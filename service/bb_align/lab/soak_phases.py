"""The soak's phases after the attack mix: authenticated streams without and with a keyless flood, then odd-shaped
signed frames; and what they share: the cars' tick loop, the service's counters read between phases, a timeline.

Each phase is measured by the difference of the service's own counters (/metrics, /v1/peers) read after the
previous phase drained and after this one drained, so nothing of one phase is counted in the next.
"""

from __future__ import annotations

import re
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, Field

from .flood import FloodConfig, FloodProcess
from .soak_attacks import ATTACKS, REFUSED_AT_DECODE, SIGNED_BY_THE_CAR, Sender

UNVERIFIED = "(unverified)"  # the service's label of drops before the gate knew the sender
LANES = ("ego", "signed", "unverified")


# ---- the service's counters ------------------------------------------------------------------------------------
def read_metrics(rest: str, token: str | None = None, timeout: float = 10.0) -> dict[str, float]:
    """Every sample of the service's /metrics, by its name with labels."""
    import httpx

    headers = {"authorization": f"Bearer {token}"} if token else {}
    out: dict[str, float] = {}
    for line in httpx.get(rest + "/metrics", timeout=timeout, headers=headers).text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


def metric_sum(metrics: dict[str, float], prefix: str, **labels: str) -> float:
    total = 0.0
    for name, v in metrics.items():
        if name.startswith(prefix + "{") or name == prefix:
            if all(f'{k}="{val}"' in name for k, val in labels.items()):
                total += v
    return total


def label_values(metrics: dict[str, float], prefix: str, label: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for name, v in metrics.items():
        if name.startswith(prefix + "{"):
            m = re.search(f'{label}="([^"]*)"', name)
            if m:
                out[m.group(1)] = out.get(m.group(1), 0.0) + v
    return out


@dataclass
class Snapshot:
    """The service's counters at one moment (after a phase drained)."""

    t: float  # time.perf_counter()
    metrics: dict[str, float]
    peers: dict[str, dict]
    cpu_s: float | None
    rss_mb: float | None

    @classmethod
    def take(cls, target) -> Snapshot:
        import httpx

        peers = httpx.get(target.rest + "/v1/peers", timeout=10).json()
        rss = target.memory_mb()["rss_mb"]
        return cls(time.perf_counter(), read_metrics(target.rest), peers, target.cpu_seconds(), rss)

    def peer(self, vid: str, name: str) -> int:
        return self.peers.get(vid, {}).get(name, 0)


def quiesce(target, grace_s: float) -> bool:
    """Wait (bounded) until nothing waits for the gate or a worker and every accepted stream frame has a result
    or a counted drop (so no frame is being aligned); True when reached."""
    import httpx

    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline:
        m = read_metrics(target.rest)
        peers = httpx.get(target.rest + "/v1/peers", timeout=10).json()
        settled = all(p["frames_accepted"] == p["results"] + p["frames_dropped"] for p in peers.values())
        if m.get("bbalign_queued_jobs", 1) == 0 and m.get("bbalign_intake_messages", 1) == 0 and settled:
            time.sleep(0.5)  # the last results on their way over loopback
            return True
        time.sleep(0.25)
    return False


# ---- the cars --------------------------------------------------------------------------------------------------
class Traffic:
    """Every car's frame once per tick at ``rate_hz``. All frames of a tick carry the tick's number as seq (one
    counter for the whole run, so each sender's (stamp, seq) keeps growing across phases); a share of the peers'
    messages can be attacks (the ego's never)."""

    def __init__(self, cars, pubs, raw, sender: Sender, *, ego_id: str, prefix: str, rate_hz: float, rng):
        self.cars, self.pubs, self.raw, self.sender = cars, pubs, raw, sender
        self.ego_id, self.prefix, self.rate_hz, self.rng = ego_id, prefix, rate_hz, rng
        self.seq = 0
        self.sent_at: dict[tuple[str, int], tuple[float, str]] = {}  # (vehicle id, seq) -> (publish time, phase)
        self.sent: dict[str, Counter] = defaultdict(Counter)  # phase -> kind -> messages
        self.valid_per_peer: dict[str, Counter] = defaultdict(Counter)  # phase -> vehicle id -> valid frames
        self.signed_attacks: dict[str, Counter] = defaultdict(Counter)  # phase -> vehicle id -> attacks it signed
        self.decoded_keys: set[tuple[str, int]] = set()  # (vehicle id, seq) of the REFUSED_AT_DECODE attacks sent
        self.oversized_every_s = 5.0
        self._last_oversized = -1e9

    def run(
        self,
        phase: str,
        seconds: float,
        attack_share: float = 0.0,
        *,
        crashed: Callable[[], str | None] = lambda: None,
        progress: bool = True,
    ) -> str | None:
        """Publish for ``seconds``; returns why it stopped early (e.g. the service exited), else None."""
        from tqdm import tqdm

        t0 = time.perf_counter()
        n = int(round(seconds * self.rate_hz))
        ticks = tqdm(range(n), desc=phase, unit="tick", disable=None if progress else True, mininterval=1.0)
        for i in ticks:
            delay = t0 + i / self.rate_hz - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            why = crashed()
            if why:
                ticks.close()
                return why
            self._tick(phase, attack_share)
        ticks.close()
        return None

    def _tick(self, phase: str, attack_share: float) -> None:
        import zenoh

        k, stamp = self.seq, time.time()
        self.seq += 1
        for car in self.cars:
            frame = car.frames[k % len(car.frames)]
            vid = car.vehicle_id
            if vid == self.ego_id:
                self.pubs[vid].publish(self.sender.valid(frame, stamp, k))
                self.sent[phase]["valid_ego"] += 1
                continue
            if attack_share > 0 and self.rng.random() < attack_share:
                kind = self._attack_kind(vid)
                chunk, data = self.sender.attack(kind, frame, stamp, k)
                if chunk == vid:  # the car's own session: arrives after its earlier frames
                    self.pubs[chunk].publish(data)
                else:
                    self.raw.put(
                        f"{self.prefix}/frames/{chunk}", data, congestion_control=zenoh.CongestionControl.BLOCK
                    )
                self.sent[phase][kind] += 1
                if kind in SIGNED_BY_THE_CAR:
                    self.signed_attacks[phase][vid] += 1
                if kind in REFUSED_AT_DECODE:  # admitted as the car's frame: its answer is a result
                    self.sent_at[(vid, k)] = (time.perf_counter(), phase)
                    self.decoded_keys.add((vid, k))
                continue
            self.pubs[vid].publish(self.sender.valid(frame, stamp, k))
            self.sent_at[(vid, k)] = (time.perf_counter(), phase)
            self.sent[phase]["valid"] += 1
            self.valid_per_peer[phase][vid] += 1

    def _attack_kind(self, vid: str) -> str:
        kind = ATTACKS[int(self.rng.integers(len(ATTACKS) - 1))]  # oversized: paced separately
        now = time.perf_counter()
        if now - self._last_oversized > self.oversized_every_s:
            kind, self._last_oversized = "oversized", now
        if kind == "replay" and vid not in self.sender.last_valid:
            kind = "unsigned"
        return kind


# ---- a timeline for the plot -----------------------------------------------------------------------------------
@dataclass
class Timeline:
    """The service's cumulative counters once per ``period_s`` (a background thread), and the phases' spans."""

    rest: str
    period_s: float = 1.0
    t0: float = field(default_factory=time.perf_counter)
    samples: list[dict] = field(default_factory=list)
    phases: list[tuple[str, float, float]] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> Timeline:
        self._thread = threading.Thread(target=self._run, name="soak-timeline", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                m = read_metrics(self.rest)
            except Exception:  # the service is busy or gone; the gap shows in the plot
                continue
            dropped = label_values(m, "bbalign_frames_dropped_total", "peer")
            self.samples.append(
                {
                    "t": time.perf_counter() - self.t0,
                    "admitted": metric_sum(m, "bbalign_messages_total"),
                    "rejected": metric_sum(m, "bbalign_frames_rejected_total"),
                    "queue_dropped": sum(v for p, v in dropped.items() if p != UNVERIFIED),
                    **{f"lane_{lane}": metric_sum(m, "bbalign_intake_dropped_total", lane=lane) for lane in LANES},
                }
            )

    def phase(self, name: str, start: float, end: float) -> None:
        self.phases.append((name, start - self.t0, end - self.t0))

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(15)


# ---- authenticated streams, without and with a keyless flood ----------------------------------------------------
class FloodPhase(BaseModel):
    """The baseline / flood comparison and the targets the flood is held to. The two alternate in ``blocks``
    pairs (baseline, flood, baseline, flood, ...) so that both see the same background load of a shared machine."""

    seconds: float = Field(60.0, gt=0, description="total length of the baseline, and of the flood (the same)")
    blocks: int = Field(3, ge=1, le=100, description="baseline/flood pairs the two are split into, alternating")
    lead_s: float = Field(1.0, ge=0, description="the flood runs this long before a flood block's first frame")
    flooder: FloodConfig = Field(default_factory=FloodConfig)
    max_lost_share: float = Field(0.01, ge=0, le=1, description="authenticated frames lost to the flood, at most")
    min_results_ratio: float = Field(0.9, ge=0, description="results/s under flood / without, at least")

    @property
    def block_s(self) -> float:
        return self.seconds / self.blocks


@dataclass
class Block:
    """One stretch of authenticated streams (with or without the flood) between two drained snapshots."""

    name: str  # e.g. "flood-2": the traffic's phase name
    kind: str  # "baseline" or "flood"
    seconds: float
    before: Snapshot
    after: Snapshot
    flooder: dict | None = None
    arrived: bool = True  # every frame sent passed the gate (or was counted as dropped there) before ``after``
    waited_s: float = 0.0  # how long that took after the cars' last frame


@dataclass
class PhaseRunner:
    """Runs stream blocks: the cars' traffic for a while (optionally under the flood), then waits until the
    service drained and reads its counters."""

    target: object
    traffic: Traffic
    timeline: Timeline
    crashed: Callable[[], str | None]
    grace_s: float
    progress: bool = True
    crash: str | None = None
    arrive_s: float = 10.0  # longest wait for a block's last frames (well below the service's peer_idle_s)

    def block(self, name: str, kind: str, seconds: float, flood: Callable[[], FloodProcess] | None = None, lead_s=0.0):
        before = Snapshot.take(self.target)
        flooder = flood() if flood is not None else None
        try:
            time.sleep(lead_s if flooder is not None else 0.0)  # the flood is at full rate before the first frame
            t = time.perf_counter()
            self.crash = self.traffic.run(name, seconds, crashed=self.crashed, progress=self.progress)
            self.timeline.phase(name, t, time.perf_counter())
            stats = flooder.finish() if flooder is not None else None
        finally:
            if flooder is not None:
                flooder.stop()
        t_end = time.perf_counter()
        arrived = self._arrived(name, before)
        waited = time.perf_counter() - t_end
        quiesce(self.target, self.grace_s)
        return Block(name, kind, seconds, before, Snapshot.take(self.target), stats, arrived, waited)

    def _arrived(self, name: str, before: Snapshot) -> bool:
        """Wait (bounded) until every frame the cars sent in this block passed the gate or was counted as dropped
        there: under a flood the last ones can still be on their way (Zenoh's FIFO is not a counter we can read).
        False when some never arrived: they count as lost."""
        sent = self.traffic.valid_per_peer[name]
        ego_sent = self.traffic.sent[name]["valid_ego"]
        deadline = time.monotonic() + self.arrive_s
        while time.monotonic() < deadline:
            now = Snapshot.take(self.target)
            ego = metric_sum(now.metrics, "bbalign_frames_received_total", kind="ego") - metric_sum(
                before.metrics, "bbalign_frames_received_total", kind="ego"
            )
            got = {
                vid: sum(now.peer(vid, k) - before.peer(vid, k) for k in ("frames_accepted", "intake_dropped"))
                for vid in sent
            }
            if ego >= ego_sent and all(got[vid] >= n for vid, n in sent.items()):
                return True
            time.sleep(0.25)
        return False

    def flood_comparison(self, cfg: FloodPhase, flood: Callable[[], FloodProcess]) -> list[Block]:
        blocks = []
        for i in range(cfg.blocks):
            for kind in ("baseline", "flood"):
                name = f"{kind}-{i + 1}"
                blocks.append(self.block(name, kind, cfg.block_s, flood if kind == "flood" else None, cfg.lead_s))
                if self.crash:
                    return blocks
        return blocks


def stream_report(block: Block, traffic: Traffic, results: Counter) -> dict:
    """One block from the counters' differences: what the cars sent, what the gate took, every drop by lane and
    by signed id, results."""
    s0, s1, name = block.before, block.after, block.name
    d = lambda prefix, **labels: metric_sum(s1.metrics, prefix, **labels) - metric_sum(s0.metrics, prefix, **labels)  # noqa: E731
    sent = traffic.sent[name]
    peers = {}
    for vid, n in sorted(traffic.valid_per_peer[name].items()):
        delta = {k: s1.peer(vid, k) - s0.peer(vid, k) for k in ("frames_accepted", "intake_dropped", "frames_dropped")}
        peers[vid] = {"sent": n, **delta, "results_received": results[vid]}
    rejected0 = label_values(s0.metrics, "bbalign_frames_rejected_total", "error")
    rejected1 = label_values(s1.metrics, "bbalign_frames_rejected_total", "error")
    door0 = label_values(s0.metrics, "bbalign_door_refused_total", "error")
    door1 = label_values(s1.metrics, "bbalign_door_refused_total", "error")
    return {
        "seconds": block.seconds,
        "ego_sent": sent["valid_ego"],
        "ego_accepted": d("bbalign_frames_received_total", kind="ego"),
        "per_peer": peers,
        "results": sum(results.values()),
        "intake_dropped_by_lane": {lane: d("bbalign_intake_dropped_total", lane=lane) for lane in LANES},
        "dropped_unverified": d("bbalign_frames_dropped_total", peer=UNVERIFIED),
        "rejected": {e: v - rejected0.get(e, 0.0) for e, v in rejected1.items() if v - rejected0.get(e, 0.0)},
        "refused_at_the_door": {e: v - door0.get(e, 0.0) for e, v in door1.items() if v - door0.get(e, 0.0)},
        "service_cpu_s": None if s0.cpu_s is None or s1.cpu_s is None else s1.cpu_s - s0.cpu_s,
        "wall_s": s1.t - s0.t,
        "rss_mb": [s0.rss_mb, s1.rss_mb],
        "flooder": block.flooder,
        "arrived": block.arrived,
        "last_frames_waited_s": block.waited_s,
    }


def _add(a: dict, b: dict) -> dict:
    """Field-wise sum of two nested count dicts."""
    out = dict(a)
    for k, v in b.items():
        out[k] = _add(a.get(k, {}), v) if isinstance(v, dict) else a.get(k, 0) + v
    return out


def combine(kind: str, blocks: list[Block], traffic: Traffic, results: dict, latency: dict) -> dict:
    """The blocks of one kind added up: frames sent, accepted and lost, drops by lane and charged to signed ids,
    results per second, the service's CPU, and (flood) what the flooder sent."""
    parts = [stream_report(b, traffic, results.get(b.name, Counter())) for b in blocks if b.kind == kind]
    total: dict = {}
    for part in parts:
        skip = ("rss_mb", "flooder", "service_cpu_s", "arrived", "last_frames_waited_s")
        total = _add(total, {k: v for k, v in part.items() if k not in skip})
    cpu = [p["service_cpu_s"] for p in parts]
    peers = total.get("per_peer", {})
    peer_sent = sum(p["sent"] for p in peers.values())
    peer_accepted = sum(p["frames_accepted"] for p in peers.values())
    out = {
        "blocks": len(parts),
        "seconds": total.get("seconds", 0.0),
        "ego": {"sent": total["ego_sent"], "accepted": total["ego_accepted"]},
        "peers": {"sent": peer_sent, "accepted": peer_accepted},
        "per_peer": peers,
        "results": total["results"],
        "results_per_s": total["results"] / total["seconds"],
        "results_per_s_by_block": [p["results"] / p["seconds"] for p in parts],
        "latency_ms": percentiles([v for b in blocks if b.kind == kind for v in latency.get(b.name, [])]),
        "intake_dropped_by_lane": total["intake_dropped_by_lane"],
        "intake_dropped_charged_to_signed_ids": sum(p["intake_dropped"] for p in peers.values()),
        "dropped_unverified": total["dropped_unverified"],
        "latest_only_dropped": sum(p["frames_dropped"] for p in peers.values()),
        "rejected": total.get("rejected", {}),
        "refused_at_the_door": total.get("refused_at_the_door", {}),
        "service_cpu_cores": None if None in cpu else sum(cpu) / total["wall_s"],
        "rss_mb_by_block": [p["rss_mb"] for p in parts],
        "last_frames_waited_s_by_block": [p["last_frames_waited_s"] for p in parts],
        "every_frame_arrived": all(p["arrived"] for p in parts),
    }
    for part in (out["ego"], out["peers"]):
        part["lost"] = part["sent"] - part["accepted"]
    floods = [p["flooder"] for p in parts if p["flooder"]]
    if floods:
        msgs: dict = {"messages": {}, "bytes": {}}
        for f in floods:
            msgs = _add(msgs, {"messages": f["messages"], "bytes": f["bytes"]})
        elapsed = sum(f["elapsed_s"] for f in floods)
        n, nbytes = sum(msgs["messages"].values()), sum(msgs["bytes"].values())
        out["flooder"] = {
            **msgs,
            "total_messages": n,
            "elapsed_s": elapsed,
            "msg_per_s": n / elapsed,
            "mb_per_s": nbytes / elapsed / 1e6,
            "cpu_cores": sum(f["cpu_cores"] * f["elapsed_s"] for f in floods) / elapsed,
        }
    return out


def flood_checks(baseline: dict, flood: dict, cfg: FloodPhase) -> tuple[dict, dict]:
    """(comparison, checks) of the flood blocks against the baseline blocks."""
    share = lambda part: part["lost"] / part["sent"] if part["sent"] else 0.0  # noqa: E731
    ratio = flood["results_per_s"] / baseline["results_per_s"] if baseline["results_per_s"] else None
    lanes = flood["intake_dropped_by_lane"]
    comparison = {
        "ego_lost_share": share(flood["ego"]),
        "peer_lost_share": share(flood["peers"]),
        "results_per_s": {"baseline": baseline["results_per_s"], "flood": flood["results_per_s"]},
        "results_ratio": ratio,
        "service_cpu_cores": {"baseline": baseline["service_cpu_cores"], "flood": flood["service_cpu_cores"]},
    }
    checks = {
        "flood_ego_frames_lost_within_target": comparison["ego_lost_share"] <= cfg.max_lost_share,
        "flood_peer_frames_lost_within_target": comparison["peer_lost_share"] <= cfg.max_lost_share,
        "flood_results_per_s_within_target": ratio is not None and ratio >= cfg.min_results_ratio,
        # a drop charged to a signed id must be one of that id's own frames, never junk under its key
        "flood_junk_never_charged_to_a_signed_id": all(
            p["intake_dropped"] <= p["sent"] - p["frames_accepted"] for p in flood["per_peer"].values()
        )
        and lanes["ego"] <= flood["ego"]["lost"],
        "flood_reached_the_service": sum(flood["rejected"].values()) + flood["dropped_unverified"] > 0,
    }
    return comparison, checks


def start_flood(target, prefix: str, cars, credentials: dict, cfg: FloodPhase, recorded=()) -> FloodProcess:
    """The keyless flooder on every car's frame key, with each car's public certificate copied from the air and
    ``recorded`` genuine frames to replay."""
    targets = {
        c.vehicle_id: getattr(credentials.get(c.vehicle_id), "certificate_bytes", None) for c in cars
    }  # None: HMAC cars carry no certificate
    config = cfg.flooder.model_copy(update={"duration_s": cfg.lead_s + cfg.block_s + 0.5})
    proc = FloodProcess(target.zenoh_endpoint, prefix, targets, config, list(recorded))
    proc.start()
    return proc


# ---- odd-shaped signed frames ----------------------------------------------------------------------------------
class OddShape(BaseModel):
    name: str
    range_m: float
    resolution_m: float
    declared_range_m: float | None = Field(None, description="claim this range instead (a PNG of the wrong size)")


def _default_shapes() -> list[OddShape]:
    shapes = [  # (name, range_m, resolution_m): the engine serves 100 m at 0.4 m/px (500 px)
        ("served 100m/0.4", 100.0, 0.4),
        ("small 40m/0.4", 40.0, 0.4),
        ("fine 30m/0.1 (600px)", 30.0, 0.1),
        ("fine 100m/0.2 (1000px)", 100.0, 0.2),
        ("odd 63.7m/0.33", 63.7, 0.33),
        ("coarse 80m/0.8", 80.0, 0.8),
        ("coarse 50m/1.0", 50.0, 1.0),
        ("beyond: 150m/0.4 (750px)", 150.0, 0.4),
        ("beyond: 250m/5.0 (upscaled 1250px)", 250.0, 5.0),
        ("beyond: 120m/0.1 (2400px)", 120.0, 0.1),
        ("beyond: 2m/0.4 (10px)", 2.0, 0.4),
    ]
    out = [OddShape(name=n, range_m=r, resolution_m=c) for n, r, c in shapes]
    return out + [OddShape(name="png 300px declared as 500px", range_m=60.0, resolution_m=0.4, declared_range_m=100.0)]


class OddShapesPhase(BaseModel):
    shapes: list[OddShape] = Field(default_factory=_default_shapes)
    repeats: int = Field(3, ge=1, le=100, description="rounds over the shapes")
    timeout_s: float = Field(60.0, gt=0, description="longest wait for one frame's answer")
    max_rss_growth_mb: float = Field(400.0, gt=0, description="service RSS growth over the phase, at most")


def _odd_frame(car, shape: OddShape):
    from bb_align_client.encode import make_frame

    points, boxes = car.cloud
    try:
        frame = make_frame(points, boxes, vehicle_id=car.vehicle_id, stamp=0.0, range_m=shape.range_m,
                           resolution_m=shape.resolution_m)  # fmt: skip
    except Exception as e:  # the sender's own encoder refuses it (e.g. a side beyond uint16): say so
        return None, f"{type(e).__name__}: {e}"
    if shape.declared_range_m is not None:
        frame = frame.model_copy(update={"bev": frame.bev.model_copy(update={"range_m": shape.declared_range_m})})
    return frame, None


class _EgoTicker(threading.Thread):
    """Keeps the ego's frames coming at ``rate_hz`` (a peer frame needs an ego frame near it in time)."""

    def __init__(self, publish: Callable[[float, int], None], rate_hz: float, seq0: int):
        super().__init__(name="soak-ego", daemon=True)
        self.publish, self.rate_hz, self.seq = publish, rate_hz, seq0
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.wait(1.0 / self.rate_hz):
            self.publish(time.time(), self.seq)
            self.seq += 1


def run_odd_shapes(target, traffic: Traffic, cfg: OddShapesPhase, *, progress: bool = True) -> dict:
    """A series of odd-shaped frames from the peer nearest the ego, signed with its key, each asked for its answer (the
    align queryable: a Result, or the refusal with its field and limit); service RSS before, after each, at end."""
    from tqdm import tqdm

    from bb_align_client import ServiceError

    ego = next(c for c in traffic.cars if c.vehicle_id == traffic.ego_id)
    peers = [c for c in traffic.cars if c.vehicle_id != traffic.ego_id]
    # the peer nearest the ego: at the served shape its frames align, so each odd shape's effect shows
    car = min(peers, key=lambda c: np.linalg.norm(c.T_world_sensor[0][:2, 3] - ego.T_world_sensor[0][:2, 3]))
    peer = traffic.pubs[car.vehicle_id]
    ego_frame = ego.frames[0]
    ticker = _EgoTicker(
        lambda stamp, seq: traffic.pubs[ego.vehicle_id].publish(traffic.sender.valid(ego_frame, stamp, seq)),
        traffic.rate_hz,
        traffic.seq,
    )
    rss_start = target.memory_mb()["rss_mb"]
    rows = []
    ticker.start()
    try:
        time.sleep(0.5)  # the ego's frames are in the cache
        seq = traffic.seq
        items = [(r, s) for r in range(cfg.repeats) for s in cfg.shapes]
        for rnd, shape in tqdm(items, desc="odd shapes", unit="frame", disable=None if progress else True):
            frame, why = _odd_frame(car, shape)
            row = {"round": rnd, "shape": shape.name, "range_m": shape.range_m, "resolution_m": shape.resolution_m}
            if frame is None:
                rows.append({**row, "outcome": "not encodable", "detail": why})
                continue
            data = traffic.sender.signed(frame.model_copy(update={"stamp": time.time(), "seq": seq}))
            seq += 1
            t0 = time.perf_counter()
            try:
                res = peer.request_align(data, traffic.ego_id, timeout=cfg.timeout_s)
                outcome = {"outcome": "success" if res.success else res.reason}
            except ServiceError as e:
                outcome = {"outcome": f"refused: {e.body.error}", "field": e.body.field, "limit": e.body.limit}
            except TimeoutError:
                outcome = {"outcome": "no answer"}
            rows.append(
                {
                    **row,
                    "image_px": int.from_bytes(frame.png[16:20], "big"),  # the PNG header's width
                    "bytes": len(data),
                    **outcome,
                    "seconds": time.perf_counter() - t0,
                    "rss_mb": target.memory_mb()["rss_mb"],
                }
            )
        traffic.seq = max(seq, ticker.seq) + 1
    finally:
        ticker.stop.set()
        ticker.join(10)
    rss_end = target.memory_mb()["rss_mb"]
    rss = [r["rss_mb"] for r in rows if r.get("rss_mb") is not None]
    growth = None if rss_start is None or rss_end is None else rss_end - rss_start
    return {
        "frames": len(rows),
        "outcomes": dict(Counter(r["outcome"] for r in rows)),
        "rows": rows,
        "rss_mb": {"start": rss_start, "end": rss_end, "max": max(rss, default=None), "growth": growth},
        "seconds_max": max((r.get("seconds", 0.0) for r in rows), default=None),
        "checks": {
            "odd_shapes_every_frame_answered": all(r["outcome"] != "no answer" for r in rows),
            "odd_shapes_rss_growth_within_bound": None if growth is None else growth <= cfg.max_rss_growth_mb,
        },
    }


def results_by_phase(
    items: list[tuple[float, bytes]], sent_at: dict
) -> tuple[dict[str, Counter], dict, dict, set[tuple[str, int]]]:
    """Results received, per phase of the frame they answer: per peer, latencies (ms) and outcomes (success or
    the failure reason); and the (vehicle id, seq) of the frames answered ``invalid_frame`` (refused when a worker
    decoded them)."""
    from bb_align.protocol import Refusal, load_answer

    counts: dict[str, Counter] = defaultdict(Counter)
    latency: dict[str, list[float]] = defaultdict(list)
    outcomes: dict[str, Counter] = defaultdict(Counter)
    refused_decoding: set[tuple[str, int]] = set()
    for t_recv, data in items:
        r = load_answer(data)
        if isinstance(r, Refusal):  # a refusal told to the sender of a signed frame: see refusal_notices
            continue
        sent = sent_at.get((r.peer_id, r.peer_seq))
        if sent is None:
            continue
        counts[sent[1]][r.peer_id] += 1
        latency[sent[1]].append((t_recv - sent[0]) * 1e3)
        outcomes[sent[1]]["success" if r.success else r.reason] += 1
        if r.reason == "invalid_frame":
            refused_decoding.add((r.peer_id, r.peer_seq))
    return counts, latency, outcomes, refused_decoding


def refusal_notices(items: list[tuple[float, bytes]]) -> Counter:
    """The refusals the service told senders on their results keys, by error (only signed frames may get one)."""
    from bb_align.protocol import Refusal, load_answer

    out: Counter = Counter()
    for _, data in items:
        r = load_answer(data)
        if isinstance(r, Refusal):
            out[r.refused.error] += 1
    return out


def percentiles(values: list[float]) -> dict:
    q = lambda p: float(np.percentile(values, p)) if values else None  # noqa: E731
    return {"p50": q(50), "p99": q(99), "n": len(values)}
