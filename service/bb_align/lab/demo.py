"""``bb-align demo``: a simulated N-car scene driven through a running service over Zenoh.

Each simulated car is a :class:`bb_align_client.ZenohPeer` (agent 0 publishes under the service's ego id); every
frame carries a GNSS-like reported pose (paper noise: sigma 2 m on x, y and 2 deg on yaw) from which the service
takes only roll, pitch and tz. A live table shows, per peer frame, the true and recovered T_ego_peer, the error
of the recovered pose and of the reported poses, the latency from publishing the frame to receiving its result,
and the frame's size against its raw points.

Frames are stamped with the scene's own time (each LiDAR's mid-sweep time, on a clock started at the first
frame), as a car stamps its sweeps with sensor time, and no frame is published before its stamp: a service that
answers slowly makes the demo run slower than real time, never its stamps lie about the scene's motion. With
``odometry`` every car also sends its odometry (the swept sequences' model: scale error, yaw bias, noise), and
``faults`` re-anchor or skew one car's odometry (bb_align.lab.tracking.faults). The summary counts the wrong
successes: a successful answer off the scene's truth by more than 1 m or 1 deg.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.live import Live
from rich.table import Table
from tqdm import tqdm

from bb_align.engine.geometry import pose_error, se2_params

GNSS_SIGMA_M = 2.0
GNSS_SIGMA_DEG = 2.0
DT_S = 0.1
WRONG_M, WRONG_DEG = 1.0, 1.0  # a successful answer farther than this from the truth is a wrong success


def _noisy(T_world_sensor: np.ndarray, rng) -> np.ndarray:
    T = T_world_sensor.copy()
    T[:2, 3] += rng.normal(0, GNSS_SIGMA_M, 2)
    a = math.radians(rng.normal(0, GNSS_SIGMA_DEG))
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    T[:3, :3] = Rz @ T[:3, :3]
    return T


def _row(result, truth: dict, sent: dict, received_at: float) -> dict:
    """One table row: the result against the truth of the exact ego and peer frames it used."""
    seq, peer, ego, ego_seq = result.peer_seq, result.peer_id, result.ego_id, result.ego_seq
    row = {
        "seq": seq,
        "peer": peer,
        "ego_seq": ego_seq,
        "success": result.success,
        "reason": result.reason,
        "inliers_bv": result.inliers_bv,
        "inliers_box": result.inliers_box,
        "latency_ms": (received_at - sent[(peer, seq)]["t"]) * 1e3,
        "service_ms": result.latency_ms,
        "bytes": result.bytes_received,
        "raw_points_bytes": result.raw_points_bytes,
        "service_steps_ms": {
            "queue_wait": result.timings_ms.get("queue_wait", 0.0),
            "peer_prepare": sum(v for k, v in result.timings_ms.items() if k.startswith("peer_")),
            "ego_features": result.timings_ms.get("ego_features", 0.0),
            "align": result.timings_ms.get("align_total", 0.0),
        },
    }
    if ego_seq is not None and (ego, ego_seq) in sent:
        T_true = np.linalg.inv(truth[(ego_seq, ego)]) @ truth[(seq, peer)]
        T_gnss = np.linalg.inv(sent[(ego, ego_seq)]["reported"]) @ sent[(peer, seq)]["reported"]
        yaw, tx, ty = se2_params(T_true)
        row.update(true=[math.degrees(yaw), tx, ty], gnss_err=list(pose_error(T_gnss, T_true)))
        if result.T_ego_peer is not None:
            row.update(est=[result.yaw_deg, result.tx, result.ty], err=list(pose_error(result.matrix(), T_true)))
    return row


def _table(rows: list[dict], title: str, last: int = 18) -> Table:
    t = Table(
        title=title,
        caption="pose = yaw deg, x m, y m of T_ego_peer; err = metres / degrees; latency = publish -> result received",
    )
    for col in (
        "seq",
        "peer",
        "true pose",
        "recovered pose",
        "err",
        "GNSS err",
        "inliers",
        "status",
        "latency ms",
        "bytes (vs raw)",
    ):
        t.add_column(col, justify="left" if col in ("peer", "status") else "right")
    fmt3 = lambda v: "-" if v is None else f"{v[0]:6.1f} {v[1]:6.1f} {v[2]:6.1f}"  # noqa: E731
    fmt2 = lambda v: "-" if v is None else f"{v[0]:.2f}/{v[1]:.2f}"  # noqa: E731
    for r in rows[-last:]:
        ratio = f" ({r['bytes'] / r['raw_points_bytes']:.1%})" if r.get("raw_points_bytes") else ""
        t.add_row(
            str(r["seq"]),
            r["peer"],
            fmt3(r.get("true")),
            fmt3(r.get("est")),
            fmt2(r.get("err")),
            fmt2(r.get("gnss_err")),
            f"{r['inliers_bv']}/{r['inliers_box']}",
            "ok" if r["success"] else f"[red]{r['reason']}[/red]",
            f"{r['latency_ms']:.0f}",
            f"{r['bytes']}{ratio}",
        )
    return t


def plot_demo(rows: list[dict], path: Path) -> None:
    """Per peer frame: recovered vs GNSS-only translation error, and publish -> result latency."""
    from bb_align.io.plot import pyplot

    plt = pyplot()

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for peer in sorted({r["peer"] for r in rows}):
        rs = [r for r in rows if r["peer"] == peer and "err" in r]
        seq = [r["seq"] for r in rs]
        ax1.plot(seq, [r["err"][0] for r in rs], "o-", label=f"{peer} recovered")
        ax1.plot(seq, [r["gnss_err"][0] for r in rs], "x--", label=f"{peer} reported (GNSS) poses")
        ax2.plot(
            [r["seq"] for r in rows if r["peer"] == peer],
            [r["latency_ms"] for r in rows if r["peer"] == peer],
            "o-",
            label=peer,
        )
    ax1.set_ylabel("translation error (m)")
    ax1.set_yscale("symlog", linthresh=0.1)
    ax1.legend(fontsize=8)
    ax2.set_ylabel("publish -> result (ms)")
    ax2.set_xlabel("frame")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def is_wrong(row: dict) -> bool:
    """A successful answer off the truth by more than WRONG_M or WRONG_DEG (or with no truth to check it by)."""
    return bool(row["success"]) and ("err" not in row or row["err"][0] > WRONG_M or row["err"][1] > WRONG_DEG)


def summarize(rows: list[dict], n_sent: int) -> dict:
    ok = [r for r in rows if r["success"]]
    wrong = [r for r in ok if is_wrong(r)]
    lat = np.array([r["latency_ms"] for r in rows]) if rows else np.zeros(0)
    svc = np.array([r["service_ms"] for r in rows if r["service_ms"] is not None])
    err_t = np.array([r["err"][0] for r in ok if "err" in r])
    err_r = np.array([r["err"][1] for r in ok if "err" in r])
    q = lambda a, p: float(np.percentile(a, p)) if len(a) else None  # noqa: E731
    raw = [r for r in rows if r.get("raw_points_bytes")]
    return {
        "peer_frames_sent": n_sent,
        "results": len(rows),
        "success": len(ok),
        "wrong_success": len(wrong),
        "wrong_seqs": [[r["peer"], r["seq"]] for r in wrong],
        "err_t_m_max": q(np.array([r["err"][0] for r in ok if "err" in r]), 100),
        "err_r_deg_max": q(np.array([r["err"][1] for r in ok if "err" in r]), 100),
        "err_t_m_median": q(err_t, 50),
        "err_r_deg_median": q(err_r, 50),
        "err_t_m_p90": q(err_t, 90),
        "err_r_deg_p90": q(err_r, 90),
        "latency_ms_median": q(lat, 50),
        "latency_ms_p90": q(lat, 90),
        "latency_ms_max": q(lat, 100),
        "service_latency_ms_median": q(svc, 50),
        "service_steps_ms_median": {
            k: q(np.array([r["service_steps_ms"][k] for r in rows]), 50)
            for k in ("queue_wait", "peer_prepare", "ego_features", "align")
        }
        if rows
        else {},
        "bytes_per_frame_mean": float(np.mean([r["bytes"] for r in rows])) if rows else None,
        "raw_points_bytes_mean": float(np.mean([r["raw_points_bytes"] for r in raw])) if raw else None,
        "ratio_vs_points_mean": float(np.mean([r["bytes"] / r["raw_points_bytes"] for r in raw])) if raw else None,
    }


def _encode_scene(scenario, names: dict, n_frames: int, bev: dict, rng, make_frame, odometry=None, faults=()):
    """Simulate and build every frame up front (so publishing keeps its pace): per frame, (name, Frame, scene time
    in s) with the ego first; the true and the reported (noisy) poses by (seq, name). A frame's stamp is its scene
    time on the clock the publisher starts. ``odometry``: agent id -> PoseSensors (each car's odometry), or None.
    Each sweep is de-skewed with its car's motion, as a sender does (README: De-skew your sweeps)."""
    from bb_align.io.sweeps import deskew_boxes

    frames, truth, reported = [], {}, {}
    order = ["0"] + [a for a in scenario.agent_ids if a != "0"]
    for i in tqdm(range(n_frames), desc="simulating and encoding", unit="frame"):
        frame = scenario.frame(i, DT_S)
        msgs = []
        for aid in order:
            agent, name = frame.agents[aid], names[aid]
            truth[(i, name)] = agent.T_world_sensor
            reported[(i, name)] = _noisy(agent.T_world_sensor, rng)
            O = None
            if odometry is not None:
                O = odometry[aid].step(agent.T_world_sensor)[0]
                for fault in faults:
                    O = fault.apply(name, i, O)
            # A sender with odometry de-skews its sweep, and its detector runs on the de-skewed cloud (README).
            motion = {} if agent.twist is None else {"velocity": agent.twist[:2], "yaw_rate": agent.twist[2]}
            boxes = agent.boxes
            if motion and len(boxes):
                boxes = deskew_boxes(np.asarray(boxes, float), motion["velocity"], motion["yaw_rate"], agent.period_s)
            msgs.append(
                (
                    aid,
                    make_frame(
                        agent.points,
                        boxes,
                        **motion,
                        vehicle_id=name,
                        stamp=0.0,
                        seq=i,
                        pose=reported[(i, name)],
                        odometry=O,
                        scores=np.clip(agent.scores, 0, 1),
                        **bev,
                    ),
                    float(agent.time_s),
                )
            )
        frames.append(msgs)
    return frames, truth, reported


def demo_signers(ego_id: str, n_agents: int, credential: Path | None, ca_cert: Path | None, key: str | None):
    """``run_demo``'s keys: per-vehicle Ed25519 credentials from the ego credential's fleet directory (the cars'
    own DIR/<car>.cred, or issued by DIR/ca.key) and the authority to verify answers with; else the fleet HMAC
    key; else nothing (a service in the demo profile)."""
    if credential is None:
        return {"key": key}
    from bb_align.protocol import Credential

    from .harness import fleet_credentials

    ego = Credential.load(credential)
    if ego.vehicle_id != ego_id:
        raise ValueError(f"{credential} is {ego.vehicle_id!r}'s credential, but the ego id is {ego_id!r}")
    directory = Path(credential).parent
    cars = fleet_credentials(directory, [f"car{a}" for a in range(1, n_agents)])
    return {"key": {ego_id: ego, **cars}, "trust": ca_cert or directory / "ca.pub"}


def run_demo(
    *,
    connect: list[str],
    ego_id: str = "ego",
    n_agents: int = 2,
    n_frames: int = 10,
    seed: int = 0,
    distance_m: float | None = 30.0,
    rate_hz: float = 0.0,
    timeout_s: float = 30.0,
    prefix: str = "bbalign",
    range_m: float | None = None,
    json_out: Path | None = None,
    plot: Path | None = None,
    console: Console | None = None,
    key: str | dict | None = None,
    trust: Path | None = None,
    odometry: bool = False,
    faults: tuple = (),
) -> dict:
    """Publish a simulated scene frame by frame (lockstep when rate_hz is 0, else paced) and tabulate the
    service's results against the truth. Every wait is bounded by timeout_s. ``key``: vehicle name -> its
    Credential (Ed25519; ``trust``: the authority's ca.pub, to verify the answers), or the fleet HMAC key for
    every car; None when the service takes unsigned frames (demo profile). ``odometry``: the cars send their
    odometry; ``faults``: OdometryFaults applied to it (bb_align.lab.tracking.faults)."""
    from bb_align.protocol import pack
    from bb_align_client import FrameRefused, ZenohPeer
    from bb_align_client.encode import make_frame

    from .sim import Scenario

    console = console or Console(width=max(Console().width, 170))
    scenario = Scenario(seed, n_agents, distance_m)
    names = {aid: (ego_id if aid == "0" else f"car{aid}") for aid in scenario.agent_ids}
    sensors = None
    if odometry or faults:
        from .sim.sweep import PoseSensors, SweepConfig

        sensors = {
            a: PoseSensors(np.random.default_rng([seed, 98, k]), SweepConfig(), DT_S)
            for k, a in enumerate(scenario.agent_ids)
        }
    frames, truth, reported = _encode_scene(
        scenario,
        names,
        n_frames,
        {} if range_m is None else {"range_m": range_m},
        np.random.default_rng([seed, 99]),
        make_frame,
        sensors,
        faults,
    )
    sent: dict = {}  # (name, seq) -> {"t": publish time, "reported": pose}
    rows: list[dict] = []
    n_sent = 0
    keys = key if isinstance(key, dict) else dict.fromkeys(names.values(), key)
    cars = {
        aid: ZenohPeer(
            name, connect=connect, prefix=prefix, key=keys[name], trust=trust, verify_answers=keys[name] is not None
        )
        for aid, name in names.items()
    }
    title = f"bb-align demo: {n_agents} cars, seed {seed}, via {', '.join(connect)}"

    def collect(deadline: float, expected: set, live) -> None:
        while True:
            try:
                res = stream.get(timeout=max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                return
            except FrameRefused as e:  # one of the cars' frames was refused: say why, wait no longer for it
                console.print(f"[red]{e.refusal.peer_id} frame {e.peer_seq} refused: {e}[/red]")
                expected.discard((e.refusal.peer_id, e.peer_seq))
                continue
            if (res.peer_id, res.peer_seq) not in sent:  # not this run's frame
                continue
            rows.append(_row(res, truth, sent, time.perf_counter()))
            live.update(_table(rows, title))
            expected.discard((res.peer_id, res.peer_seq))
            if not expected:
                return

    try:
        for car in cars.values():
            car.open()
        stream = cars["1"].poses(ego_id, "*")
        if not all(car.wait_for_subscriber(10.0) for car in cars.values()):
            console.print(
                f"[red]no service subscribes to {prefix}/frames/* via {connect}; is `bb-align serve` running?[/red]"
            )
            return summarize(rows, 0)
        time.sleep(0.2)  # let the pose subscription reach the service too
        pending: set = set()
        with Live(_table(rows, title), console=console, refresh_per_second=4) as live:
            t0 = time.monotonic()
            clock0 = time.time()  # the cars' common clock at the scene's start: stamps are scene time on it
            for i, msgs in enumerate(frames):
                # A sweep is published once it was captured, never before: the service checks stamps against its
                # own clock (the lead it allows is small), and a sender faster than real time has no real sensor.
                time.sleep(max(0.0, t0 + max(t for _, _, t in msgs) - time.monotonic()))
                for aid, frame, t_scene in msgs:
                    data = pack(frame.model_copy(update={"stamp": clock0 + t_scene}))
                    sent[(names[aid], i)] = {"t": time.perf_counter(), "reported": reported[(i, names[aid])]}
                    cars[aid].publish(data)
                    if aid != "0":
                        n_sent += 1
                        pending.add((names[aid], i))
                if rate_hz == 0:  # lockstep: this frame's results (or the timeout) before the next frame
                    collect(time.monotonic() + timeout_s, pending, live)
                    pending.clear()
                else:  # paced: results as they come until this frame's slot ends
                    slot_end = t0 + (i + 1) / rate_hz
                    collect(slot_end, pending, live)
                    time.sleep(max(0.0, slot_end - time.monotonic()))
            if pending:  # paced: the stragglers (frames the service dropped never come)
                collect(time.monotonic() + min(timeout_s, 5.0), pending, live)
    finally:
        for car in cars.values():
            car.close()
    summary = summarize(rows, n_sent)
    console.print(_summary_text(summary))
    if json_out is not None:
        Path(json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(json_out).write_text(json.dumps({"summary": summary, "rows": rows}, indent=1))
        console.print(f"rows and summary: {json_out}")
    if plot is not None and rows:
        Path(plot).parent.mkdir(parents=True, exist_ok=True)
        plot_demo(rows, Path(plot))
        console.print(f"plot: {plot}")
    return summary


def _summary_text(s: dict) -> str:
    f = lambda v, spec: "-" if v is None else format(v, spec)  # noqa: E731
    return (
        f"{s['results']}/{s['peer_frames_sent']} peer frames answered, {s['success']} successful, "
        f"{s['wrong_success']} of them wrong (off > {WRONG_M:g} m or {WRONG_DEG:g} deg; worst "
        f"{f(s['err_t_m_max'], '.2f')} m / {f(s['err_r_deg_max'], '.2f')} deg); error median "
        f"{f(s['err_t_m_median'], '.2f')} m / {f(s['err_r_deg_median'], '.2f')} deg; "
        f"latency publish->result median {f(s['latency_ms_median'], '.0f')} ms, "
        f"p90 {f(s['latency_ms_p90'], '.0f')} ms (service-side median "
        f"{f(s['service_latency_ms_median'], '.0f')} ms); frame {f(s['bytes_per_frame_mean'], '.0f')} B vs raw "
        f"points {f(s['raw_points_bytes_mean'], '.0f')} B ({f(s['ratio_vs_points_mean'], '.2%')})"
    )
