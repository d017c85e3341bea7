"""A first answer from a second of stream (`Aligner.align_stream`), without and with a prior, on real and simulated
streams.

    python benchmarks/stream_acquire.py --data ../shared/data --sweeps out/sweep7373            # -> out/
    python benchmarks/stream_acquire.py --data ../shared/data --sweeps out/sweep7373 --record   # -> docs/

- **Real KITTI 00 street, 73-80 m** (``kitti00_run_far``, run as benchmarks/track_real.py runs it: the ego drives
  frames 0-9 forward, back and forward, the peer is the car 73-80 m ahead, frames 94 / 95): each of the 20 steps
  with a second of stream behind it (steps 10-29) acquired from its last ten steps, each car's odometry its
  poses; beside it the same step's pair alone (`Aligner.align`, no prior). With the prior: the same streams and
  pairs given the step's GNSS-grade pose (the reference moved by benchmarks/track_real.py's seeded 2 m / 2 deg
  random walk), as `align_stream(frames, T_prior)` and `align(ego, peer, T_prior=...)`.
- **No overlap**: the ego's ten frames of ``kitti08_run`` against the peer's ten of ``kitti00_run_far`` (two
  cities): must be refused.
- **Simulated sweeps** (``bb-align sim --sweep``, de-skewed as a sender does): every sequence's windows of ten
  frames ending at frames 9, 19, ..., each car's odometry from its yaml, by distance band.

A wrong answer is a successful one off by more than 1 m or 1 deg. Writes OUT.json, OUT.md and OUT.png.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import typer
from tqdm import tqdm

from bb_align.engine.geometry import pose_error, se2, se3_from_se2
from bb_align.engine.pipeline import Aligner
from bb_align.engine.stream_acquire import StreamFrame
from bb_align.io.clouds import load_cloud
from bb_align.io.dataset import find_scenarios, iter_scenario_frames, parse_lidar_pose
from bb_align.io.sweeps import deskewed
from bb_align.lab.tracking.real_runs import STEP_S, gnss_errors, run_poses, schedule

WINDOW = 10  # frames: a second at 10 Hz
BANDS = ((0.0, 40.0), (40.0, 70.0), (70.0, 1e9))


def _row(name: str, r, T_true: np.ndarray, ms: float, alone=None) -> dict:
    t_err, r_err = pose_error(r.T_ego_peer, T_true)
    row = {
        "name": name,
        "distance_m": float(np.hypot(T_true[0, 3], T_true[1, 3])),
        "success": bool(r.success),
        "reason": r.reason,
        "t_err_m": t_err,
        "r_err_deg": r_err,
        "wrong": bool(r.success and not (t_err < 1.0 and r_err < 1.0)),
        "probability": float(r.confidence),
        "ms": ms,
    }
    if alone is not None:
        a_t, a_r = pose_error(alone.T_ego_peer, T_true)
        row |= {"alone_success": bool(alone.success), "alone_wrong": bool(alone.success and not (a_t < 1 and a_r < 1))}
    return row


def real_far(data: Path, aligner: Aligner) -> list[dict]:
    folder = data / "kitti00_run_far"
    poses, cache = run_poses(folder), {}

    def frame(k: int):
        if k not in cache:
            cache[k] = aligner.prepare(load_cloud(folder / f"{k:06d}.bin"))
        return cache[k]

    plan, rows = schedule("kitti00_run_far", 3), []
    errors = gnss_errors(len(plan))
    for s in tqdm(range(WINDOW, len(plan)), desc="real 73-80 m", unit="stream"):
        frames = [
            StreamFrame(frame(e), frame(p), poses[e], poses[p], STEP_S * i)
            for i, (e, p) in enumerate(plan)
            if s - WINDOW < i <= s
        ]
        e, p = plan[s]
        T_true = np.linalg.inv(poses[e]) @ poses[p]
        prior = se3_from_se2(se2(*errors[s])) @ T_true
        for label, T_prior in (("", None), (" (prior)", prior)):
            t = time.perf_counter()
            r = aligner.align_stream(frames, T_prior)
            ms = (time.perf_counter() - t) * 1e3
            alone = aligner.align(frame(e), frame(p), T_prior=T_prior)
            row = _row(f"step {s}: {e:06d} <- {p:06d}{label}", r, T_true, ms, alone)
            rows.append(row | {"prior": T_prior is not None})
    return rows


def no_overlap(data: Path, aligner: Aligner) -> list[dict]:
    """The ego on one street, the peer in another city: ten frames each, with their own odometry."""
    ego_dir, peer_dir = data / "kitti08_run", data / "kitti00_run_far"
    ego_poses, peer_poses = run_poses(ego_dir), run_poses(peer_dir)
    frames = [
        StreamFrame(
            aligner.prepare(load_cloud(ego_dir / f"{k:06d}.bin")),
            aligner.prepare(load_cloud(peer_dir / f"{k:06d}.bin")),
            ego_poses[k],
            peer_poses[k],
            STEP_S * k,
        )
        for k in range(WINDOW)
    ]
    t = time.perf_counter()
    r = aligner.align_stream(frames)
    ms = (time.perf_counter() - t) * 1e3
    return [
        {"name": "kitti08_run 0-9 <- kitti00_run_far 0-9", "success": bool(r.success), "reason": r.reason, "ms": ms}
    ]


def sweeps(root: Path, aligner: Aligner, every: int) -> list[dict]:
    rows = []
    for name, path in find_scenarios(root):
        groups = list(iter_scenario_frames(name, path))
        frames: list[StreamFrame] = []
        for k, g in enumerate(tqdm(groups, desc=name, unit="frame", leave=False)):
            ego, peer = g.ego, g.peers[0]
            frames.append(
                StreamFrame(
                    aligner.prepare(*deskewed(ego, ego.load_points(), ego.detections)),
                    aligner.prepare(*deskewed(peer, peer.load_points(), peer.detections)),
                    parse_lidar_pose(ego.extra["odometry_pose"]),
                    parse_lidar_pose(peer.extra["odometry_pose"]),
                    float(peer.extra.get("timestamp_s", STEP_S * k)),
                )
            )
            if k + 1 >= WINDOW and (k + 1) % every == 0:
                T_true = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
                t = time.perf_counter()
                r = aligner.align_stream(frames[-WINDOW:])
                ms = (time.perf_counter() - t) * 1e3
                rows.append(_row(f"{name} frame {k}", r, T_true, ms))
            if len(frames) > WINDOW:
                frames.pop(0)  # only the window is kept in memory
    return rows


def by_band(rows: list[dict]) -> dict:
    out = {}
    for lo, hi in BANDS:
        band = [r for r in rows if lo <= r["distance_m"] < hi]
        name = f"{lo:g}-{hi:g} m" if hi < 1e9 else f"{lo:g}+ m"
        out[name] = {
            "streams": len(band),
            "successful": sum(r["success"] for r in band),
            "wrong": sum(r["wrong"] for r in band),
        }
    return out


def main(
    data: Path = typer.Option(Path("../shared/data"), exists=True, file_okay=False, help="../shared/data"),
    sweeps_root: list[Path] = typer.Option([], "--sweeps", exists=True, file_okay=False, help="bb-align sim --sweep"),
    every: int = typer.Option(10, min=1, help="simulated: a window ending every this many frames"),
    out: Path | None = typer.Option(None, help="OUT.json, OUT.md, OUT.png (default out/stream_acquire)"),
    record: bool = typer.Option(False, "--record", help="write to docs/real_pairs/stream_acquire instead"),
) -> None:
    out = out or Path("docs/real_pairs/stream_acquire" if record else "out/stream_acquire")
    aligner = Aligner()
    real = real_far(data, aligner)
    negative = no_overlap(data, aligner)
    sim = {str(root): sweeps(root, aligner, every) for root in sweeps_root}
    command = f"python benchmarks/stream_acquire.py --data {data}" + "".join(f" --sweeps {r}" for r in sweeps_root)
    ms = [r["ms"] for r in real] + [r["ms"] for rows in sim.values() for r in rows]
    summary = {
        f"real_far{suffix}": {
            "streams": len(part),
            "successful": sum(r["success"] for r in part),
            "wrong": sum(r["wrong"] for r in part),
            "one_frame_alone_successful": sum(r["alone_success"] for r in part),
            "one_frame_alone_wrong": sum(r["alone_wrong"] for r in part),
            "worst_successful": [
                max((r["t_err_m"] for r in part if r["success"]), default=None),
                max((r["r_err_deg"] for r in part if r["success"]), default=None),
            ],
        }
        for suffix, part in (("", [r for r in real if not r["prior"]]), ("_prior", [r for r in real if r["prior"]]))
    } | {
        "no_overlap": negative,
        "sweeps": {k: by_band(rows) for k, rows in sim.items()},
        "stream_ms_p50": float(np.median(ms)),
        "stream_ms_p90": float(np.percentile(ms, 90)),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    body = {"command": command, "summary": summary, "real_far": real, "sweeps": sim}
    out.with_suffix(".json").write_text(json.dumps(body, indent=1) + "\n")
    lines = [
        f"Made by `{command}`. A stream: the last {WINDOW} frames of each car (a second at 10 Hz) with their "
        "odometry; with the prior: the step's GNSS-grade pose (a 2 m / 2 deg random walk about the reference).",
        "",
        "| set | streams | successful | wrong | one frame alone: successful / wrong |",
        "| --- | ---: | ---: | ---: | --- |",
    ]
    for key, label in (("real_far", "no prior"), ("real_far_prior", "with the prior")):
        rf = summary[key]
        lines.append(
            f"| real KITTI 00 street, 73-80 m, {label} | {rf['streams']} | {rf['successful']} | {rf['wrong']} | "
            f"{rf['one_frame_alone_successful']} / {rf['one_frame_alone_wrong']} |"
        )
    for n in negative:
        lines.append(f"| no overlap: {n['name']} | 1 | {int(n['success'])} | {int(n['success'])} | |")
    for root, bands in summary["sweeps"].items():
        for band, o in bands.items():
            lines.append(f"| {root}, {band} | {o['streams']} | {o['successful']} | {o['wrong']} | |")
    for key, label in (("real_far", "no prior"), ("real_far_prior", "with the prior")):
        worst = summary[key]["worst_successful"]
        if worst[0] is not None:
            lines += ["", f"Worst successful real answer, {label}: {worst[0]:.2f} m / {worst[1]:.2f} deg."]
    lines += [f"A stream acquisition: p50 {summary['stream_ms_p50']:.0f} ms, p90 {summary['stream_ms_p90']:.0f} ms."]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    plot(real, sim, out.with_suffix(".png"))
    print("\n".join(lines))


def plot(real: list[dict], sim: dict[str, list[dict]], path: Path) -> None:
    """Each stream's error against its distance, successful and refused."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    rows = real + [r for v in sim.values() for r in v]
    for ok, style, label in ((True, "o", "successful"), (False, "x", "refused")):
        pick = [r for r in rows if r["success"] == ok]
        ax.scatter([r["distance_m"] for r in pick], [min(r["t_err_m"], 20.0) for r in pick], marker=style, label=label)
    ax.axhline(1.0, color="0.6", ls=":", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("distance between the cars (m)")
    ax.set_ylabel("position error of the answer (m, capped at 20)")
    ax.set_title("acquisition from a second of stream (real: without and with a prior)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    typer.run(main)
