"""`bb-align sim` and `bb-align eval`: make a simulated V2V dataset, and measure the engine on any dataset in the
OPV2V / V2V4Real layout."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import typer

from bb_align.io.defaults import DESKEW_DEFAULT, DESKEW_HELP


def _git_commit() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            cwd=Path(__file__).resolve().parent,
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", "service"],
            capture_output=True,
            text=True,
            timeout=5,
            cwd=Path(__file__).resolve().parent,
        )
        if out.returncode != 0:
            return None
        return out.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def _fmt(v, pct=False):
    if v is None:
        return "  fail"
    return f"{100 * v:5.1f}%" if pct else f"{v:6.2f}"


def _print_summary(s: dict) -> None:
    echo = typer.echo
    echo(
        f"pairs {s['pairs']}  success {_fmt(s['success_rate'], True)}  <1m&1deg {_fmt(s['frac_under_1m_1deg'], True)}"
        f"  median t {_fmt(s['median_t_err_m'])} m  median r {_fmt(s['median_r_err_deg'])} deg"
    )
    echo(
        "success at lambda m & deg (1 / 2 / 3): "
        + " / ".join(_fmt(s["success_at_m"][k], True) for k in ("1", "2", "3"))
        + "   mRTE "
        + " / ".join(_fmt(s["mRTE_m"][k]) for k in ("1", "2", "3"))
        + " m   mRRE "
        + " / ".join(_fmt(s["mRRE_deg"][k]) for k in ("1", "2", "3"))
        + " deg"
    )
    w = s["within_70m"]
    if w.get("pairs"):
        echo(f"within 70 m: {w['pairs']} pairs, <1m&1deg {_fmt(w['frac_under_1m_1deg'], True)}")
    echo("distance   pairs  success  <1m&1deg  | stage1 <1m&1deg | graph <1m&1deg")
    for k, b in s["by_distance"].items():
        if not b.get("pairs"):
            continue
        s1 = s["stage1_only"]["by_distance"][k]
        g = s["baseline_graph_matching"]["by_distance"][k]
        echo(
            f"{k:>8} m {b['pairs']:6d}  {_fmt(b['success_rate'], True)}   {_fmt(b['frac_under_1m_1deg'], True)}"
            f"   |     {_fmt(s1['frac_under_1m_1deg'], True)}      |    {_fmt(g['frac_under_1m_1deg'], True)}"
        )
    echo(
        "late-fusion AP@0.5 / AP@0.7 (all ranges): "
        + ", ".join(
            f"{pose} {_fmt(v['all']['ap@0.5'])} / {_fmt(v['all']['ap@0.7'])}" for pose, v in s["detection_ap"].items()
        )
    )
    used = s.get("detections_used", {})
    echo("detections (agent frames): " + ", ".join(f"{k} {v}" for k, v in used.items()))
    if used.get("none"):
        echo(
            f"note: {used['none']} agent frames had no detections: stage 2 skipped for them "
            "(give --detections DIR, or --simulate-detections to simulate them from the labels)"
        )
    echo("failures: " + ", ".join(f"{k} {v}" for k, v in s["failure_reasons"].items()))


def write_sample_pair(out_dir: Path, seed: int, distance_m: float) -> list[Path]:
    """One simulated two-car frame as the files `bb-align align` reads, and the true T_ego_peer beside them."""
    import numpy as np

    from bb_align.engine.geometry import se2_params
    from bb_align.io.clouds import save_boxes_json

    from ..sim.scenario import simulate_sequence

    frame = simulate_sequence(seed=seed, n_frames=1, n_agents=2, distance_m=distance_m)[0]
    ego, peer = frame.agents["0"], frame.agents["1"]
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / n for n in ("ego.npy", "peer.npy", "ego_boxes.json", "peer_boxes.json", "truth.json")]
    np.save(paths[0], ego.points.astype(np.float32))
    np.save(paths[1], peer.points.astype(np.float32))
    save_boxes_json(paths[2], ego.boxes)
    save_boxes_json(paths[3], peer.boxes)
    T_ego_peer = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
    yaw, tx, ty = se2_params(T_ego_peer)
    truth = {"yaw_deg": round(np.degrees(yaw), 3), "tx": round(tx, 3), "ty": round(ty, 3)}
    truth["T_ego_peer"] = T_ego_peer.round(6).tolist()
    paths[4].write_text(json.dumps(truth, indent=1) + "\n")
    return paths


def register(app: typer.Typer) -> None:
    @app.command("sim")
    def sim_cmd(
        out_dir: Path = typer.Argument(..., file_okay=False, help="dataset root to write (OPV2V layout)"),
        scenarios: int = typer.Option(200, "--scenarios", min=1, help="number of scenarios"),
        seed: int = typer.Option(0, "--seed", help="benchmark seed (everything is deterministic for it)"),
        frames: int = typer.Option(1, "--frames", min=1, help="consecutive frames per scenario (0.1 s apart)"),
        agents: int = typer.Option(2, "--agents", min=2, max=8, help="cars per scenario (lowest id = ego)"),
        min_distance: float = typer.Option(4.0, "--min-distance", min=0, help="closest spacing, metres"),
        max_distance: float = typer.Option(100.0, "--max-distance", min=1, max=300, help="farthest spacing, m"),
        distortion: bool = typer.Option(True, "--distortion/--no-distortion", help="self-motion distortion"),
        fleet: str | None = typer.Option(
            None,
            "--fleet",
            show_default=False,
            help="LiDAR models the cars draw from, all different while possible (comma list; one name: every car "
            "the same; an unknown name lists the models) [default: hdl64,vlp32c,os1_64,pandar40]",
        ),
        workers: int = typer.Option(2, "--workers", min=1, help="processes"),
        sweep: bool = typer.Option(
            False,
            "--sweep",
            help="two-car sequences whose spacing sweeps ~5-120 m (receding, approaching, overtaking, oncoming, "
            "crossing, in turn; with --family crossing: crossings only) with odometry and GNSS poses in each yaml, "
            "for `bb-align track` (--frames: e.g. 150)",
        ),
        pair: bool = typer.Option(
            False,
            "--pair",
            help="one two-car pair as plain files for `bb-align align`: ego.npy, peer.npy, ego_boxes.json, "
            "peer_boxes.json and truth.json (T_ego_peer), the cars --max-distance apart",
        ),
        family: str = typer.Option(
            "mixed",
            "--family",
            help="mixed: the benchmark's streets; street: one car following another on a straight residential street "
            "(defaults 60-100 m); turn: the peer has turned into a crossing street ahead (defaults 40-70 m); crossing: "
            "the peer anywhere on a crossing street, the ego within 30 m of the crossing (defaults 50-100 m)",
        ),
        dair: bool = typer.Option(
            False,
            "--dair",
            help="V2I scenes (a vehicle and a roadside LiDAR 4-5 m up, 120 deg FOV) in the DAIR-V2X-C layout, "
            "lidar_i2v corrupted by 4 m / 4 deg, the truth in OUT_DIR/bb_align_sim_truth.json; --min/--max-distance: "
            "vehicle-to-pole distance along the road (defaults 8-60 m with --dair)",
        ),
    ) -> None:
        """Simulate V2V LiDAR scenarios (heterogeneous sensors, distortion, detections) into OUT_DIR."""
        from ..sim.scenario import SimConfig
        from ..sim.writer import write_benchmark

        if pair:
            for name in write_sample_pair(out_dir, seed=seed, distance_m=max_distance):
                typer.echo(str(name))
            return

        if dair:
            from ..sim.v2i import V2IConfig, write_v2i_root

            lo = 8.0 if min_distance == 4.0 else min_distance
            hi = 60.0 if max_distance == 100.0 else max_distance
            if hi <= lo:
                raise typer.BadParameter("--max-distance must be larger than --min-distance")
            base = write_v2i_root(out_dir, scenarios, frames, seed, V2IConfig(min_distance_m=lo, max_distance_m=hi))
            typer.echo(f"wrote {scenarios} V2I scenes x {frames} frame(s) in the DAIR-V2X-C layout to {base}")
            return
        if sweep:
            from ..sim.sweep import SWEEP_KINDS, write_sweeps

            if frames < 2:
                raise typer.BadParameter("--sweep needs --frames of 2 or more (e.g. 150: 15 s)")
            if family not in ("mixed", "crossing"):
                raise typer.BadParameter(f"--sweep takes --family mixed or crossing, got {family!r}")
            kinds = ("crossing",) if family == "crossing" else SWEEP_KINDS
            names = write_sweeps(out_dir, scenarios, frames, seed=seed, workers=workers, kinds=kinds)
            typer.echo(f"wrote {len(names)} swept sequences x {frames} frames x 2 agents to {out_dir}")
            return

        from ..sim.streets import FAMILIES

        if family not in FAMILIES:
            raise typer.BadParameter(f"--family must be one of {', '.join(FAMILIES)}, got {family!r}")
        if family != "mixed" and (min_distance, max_distance) == (4.0, 100.0):  # the flags' defaults
            min_distance, max_distance = {"street": (60.0, 100.0), "turn": (40.0, 70.0), "crossing": (50.0, 100.0)}[
                family
            ]
        if max_distance <= min_distance:
            raise typer.BadParameter("--max-distance must be larger than --min-distance")
        from ..sim.sensors import DEFAULT_FLEET, SENSOR_MODELS

        models = DEFAULT_FLEET if fleet is None else tuple(m.strip() for m in fleet.split(",") if m.strip())
        unknown = [m for m in models if m not in SENSOR_MODELS]
        if not models or unknown:
            raise typer.BadParameter(f"--fleet: unknown model(s) {unknown}; choose from {', '.join(SENSOR_MODELS)}")
        cfg = SimConfig(
            min_distance_m=min_distance, max_distance_m=max_distance, distortion=distortion, fleet=models, family=family
        )
        names = write_benchmark(
            out_dir, scenarios, seed=seed, frames=frames, n_agents=agents, config=cfg, workers=workers
        )
        typer.echo(f"wrote {len(names)} scenarios x {frames} frame(s) x {agents} agents to {out_dir}")

    @app.command("eval")
    def eval_cmd(
        root: Path = typer.Argument(
            ..., exists=True, file_okay=False, help="dataset root (OPV2V / V2V4Real layout, or DAIR-V2X-C)"
        ),
        json_out: Path | None = typer.Option(None, "--json", help="write the summary JSON here"),
        plots: Path | None = typer.Option(None, "--plots", file_okay=False, help="write PNG figures here"),
        records_out: Path | None = typer.Option(None, "--records", help="write every pair's record (JSON lines)"),
        pose_noise: str = typer.Option("2,2", "--pose-noise", help="sigma_t (m), sigma_theta (deg) for the AP test"),
        prior: bool = typer.Option(False, "--prior", help="also give the engine that noisy pose as a GNSS prior"),
        limit: int | None = typer.Option(None, "--limit", min=1, help="evaluate at most this many pairs"),
        workers: int = typer.Option(2, "--workers", min=1, help="processes"),
        seed: int = typer.Option(0, "--seed", help="seed of the pose noise and of simulated detections"),
        detections: Path | None = typer.Option(
            None,
            "--detections",
            exists=True,
            file_okay=False,
            help="per-frame detection files DIR/<scenario>/<agent>/<timestamp>.npy|.json|.txt "
            "(instead of the yaml's 'detections'; format in README)",
        ),
        simulate_detections: bool = typer.Option(
            False,
            "--simulate-detections",
            help="simulate every agent's detections from its ground-truth labels (detector model); without it, "
            "agents with no detections have none and stage 2 is skipped",
        ),
        deskew: bool = typer.Option(DESKEW_DEFAULT, "--deskew/--no-deskew", help=DESKEW_HELP),
        system_error_offset: bool = typer.Option(
            False,
            "--system-error-offset",
            help="DAIR-V2X-C: score against lidar_i2v shifted by each frame's system_error_offset "
            "(default: lidar_i2v as stored, as V2X-Reg++ scores)",
        ),
    ) -> None:
        """Run the engine on every ego/peer pair under ROOT and report the paper's metrics.

        On a DAIR-V2X-C root the vehicle is the ego, the roadside unit the peer, the reference is lidar_i2v and
        the boxes are the labels unless --detections DIR (DIR/vehicle-side/<id>.json, infrastructure-side/...).

        Detections come from the yaml's 'detections', from --detections DIR, or (only with
        --simulate-detections) from the ground truth; the summary says which ('detections_used')."""
        from bb_align.io.commands import parse_pose_noise

        from .plots import write_plots
        from .runner import EvalConfig, evaluate_dataset
        from .summary import summarize

        if plots is not None:  # fail now, not after the whole evaluation
            from bb_align.io.plot import pyplot

            pyplot()
        sigma_t, sigma_deg = parse_pose_noise(pose_noise)
        if detections is not None and simulate_detections:
            raise typer.BadParameter("give --detections DIR or --simulate-detections, not both")
        cfg = EvalConfig(
            deskew=deskew,
            pose_noise_t_m=sigma_t,
            pose_noise_deg=sigma_deg,
            seed=seed,
            use_prior=prior,
            simulate_detections=simulate_detections,
            detections_dir=None if detections is None else str(detections),
            system_error_offset=system_error_offset,
        )
        commit = _git_commit()  # the engine version measured (taken before the run: others may commit meanwhile)
        try:
            records = evaluate_dataset(root, cfg, limit=limit, workers=workers)
        except (ValueError, FileNotFoundError) as exc:
            raise typer.BadParameter(str(exc)) from exc
        summary = summarize(records)
        from bb_align.io.dataset import is_dair_root

        dair = is_dair_root(root)
        summary["meta"] = {
            "root": str(root),
            "layout": "dair-v2x-c" if dair else "opv2v",
            "reference": (
                ("lidar_i2v+system_error_offset" if system_error_offset else "lidar_i2v") if dair else "lidar_pose"
            ),
            "commit": commit,
            "pose_noise": [sigma_t, sigma_deg],
            "prior": prior,
            "seed": seed,
            "detections": "simulated from ground truth"
            if simulate_detections
            else str(detections or ("labels" if dair else "yaml")),
            "align_config": cfg.align.model_dump(),
        }
        _print_summary(summary)
        if json_out is not None:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps(summary, indent=2))
            typer.echo(f"summary: {json_out}")
        if records_out is not None:
            records_out.parent.mkdir(parents=True, exist_ok=True)
            with open(records_out, "w") as fh:
                for r in records:
                    fh.write(json.dumps(r.to_dict()) + "\n")
            typer.echo(f"records: {records_out}")
        if plots is not None:
            paths = write_plots(records, plots)
            typer.echo(f"plots: {len(paths)} PNGs in {plots}")
