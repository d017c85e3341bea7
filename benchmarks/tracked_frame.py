"""What a tracked frame costs, and how the pose landscape's window scales it: the follower on a real 10 Hz run
(bb_align.lab.tracking.real_runs, with odometry and the GNSS-grade pose), every step timed after the first answer.

    python benchmarks/tracked_frame.py --data ../shared/data --out docs/tracking/tracked_frame

Per landscape window cap (``landscape.half_width_m``; a tracked frame's window is ``track.landscape_sigmas`` of its
refinement's own sigma within [``track.landscape_min_half_width_m``, the cap]; the yaw window kept): the tracked
steps' total time p50 / p90 (refinement, landscape, boxes, filter, stream), the landscape's own p50, and the steps
answered. The engine runs as a service worker does, one frame at a time (the landscape's grid is scored on two
threads); the ego frames' own work (the refinement's cloud, the landscape's fields) is done on their arrival, as
the service does, and not counted. Writes OUT.json and OUT.md.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import typer
from tqdm import tqdm

from bb_align.engine.config import AlignConfig, with_overrides
from bb_align.engine.follow import Follower
from bb_align.engine.geometry import se2, se3_from_se2
from bb_align.engine.pipeline import Aligner
from bb_align.io.clouds import load_cloud
from bb_align.lab.recording import RECORD_HELP, output_path
from bb_align.lab.tracking.real_runs import STEP_S, gnss_errors, run_poses, schedule


def timed_run(data: Path, run: str, cfg: AlignConfig, laps: int) -> dict:
    folder = data / run
    aligner, poses = Aligner(cfg), run_poses(folder)
    aligner.warm_up()
    follower, frames, plan = Follower(aligner), {}, schedule(run, laps)
    errors = gnss_errors(len(plan))
    for k in {e for e, _ in plan} | {p for _, p in plan}:  # the ego side on arrival, as the service does
        frames[(k, False)] = aligner.ready_to_track(
            aligner.prepare(load_cloud(folder / f"{k:06d}.bin"), features=False)
        )
        frames[(k, True)] = aligner.prepare(load_cloud(folder / f"{k:06d}.bin"))
    total, land, answered = [], [], 0
    for i, (e, p) in enumerate(plan):
        T_true = np.linalg.inv(poses[e]) @ poses[p]
        prior = se3_from_se2(se2(*errors[i])) @ T_true
        t0 = time.perf_counter()
        r = follower.step(
            frames[(e, False)], frames[(p, True)], STEP_S * i, O_ego=poses[e], O_peer=poses[p], T_prior=prior
        )
        ms = (time.perf_counter() - t0) * 1e3
        if r.source == "tracking":
            total.append(ms)
            land.append(r.timings_ms.get("landscape", 0.0))
            answered += bool(r.success)
    return {"tracked": len(total), "answered": answered, "total_ms": total, "landscape_ms": land}


def main(
    data: Path = typer.Option(Path("../shared/data"), exists=True, file_okay=False),
    out: Path | None = typer.Option(
        None,
        help="OUT.json and OUT.md (default: out/tracking/tracked_frame; docs/tracking/tracked_frame with --record)",
    ),
    record: bool = typer.Option(False, "--record", help=RECORD_HELP),
    runs: list[str] = typer.Option(["kitti00_run_far", "kitti08_run"], "--run"),
    widths: list[float] = typer.Option([3.2, 2.4, 1.6], "--width", help="landscape.half_width_m values"),
    laps: int = typer.Option(3, min=1, max=10),
) -> None:
    out = out or output_path("docs/tracking/tracked_frame", record)
    rows = []
    for run in runs:
        for w in tqdm(widths, desc=run, unit="window"):
            cfg = with_overrides(AlignConfig(), [f"landscape.half_width_m={w}"])
            o = timed_run(data, run, cfg, laps)
            rows.append(
                {
                    "run": run,
                    "half_width_m": w,
                    "tracked": o["tracked"],
                    "answered": o["answered"],
                    "total_p50_ms": float(np.median(o["total_ms"])),
                    "total_p90_ms": float(np.percentile(o["total_ms"], 90)),
                    "landscape_p50_ms": float(np.median(o["landscape_ms"])),
                }
            )
    command = "python benchmarks/tracked_frame.py " + " ".join(f"--run {r}" for r in runs) + f" --laps {laps}"
    lines = [
        f"Made by `{command}`.",
        "",
        "| run | landscape cap m | tracked frames | answered | tracked frame p50 / p90 ms | landscape p50 ms |",
        "| --- | ---: | ---: | ---: | --- | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['run']} | {r['half_width_m']:g} | {r['tracked']} | {r['answered']} | "
            f"{r['total_p50_ms']:.1f} / {r['total_p90_ms']:.1f} | {r['landscape_p50_ms']:.1f} |"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"command": command, "rows": rows}, indent=1) + "\n")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    typer.run(main)
