"""``bb-align bench``: engine vs baseline stage timings, accuracy cross-check, memory, and service throughput."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer


def _progress(items, label: str):
    from tqdm import tqdm

    return tqdm(list(items), desc=label, file=sys.stderr, leave=False, dynamic_ncols=True)


def _summary(report: dict) -> str:
    from .run import COLD, HOT

    lines = []
    for key, title in ((HOT, "peer frame vs cached ego frame"), (COLD, "cold pair")):
        st = report["stages"][key]
        lines.append(f"{title}: engine p50 {st['engine']['total']['p50']:.1f} ms, p90 "
                     f"{st['engine']['total']['p90']:.1f} ms | baseline p50 {st['baseline']['total']['p50']:.0f} ms"
                     f" | speed-up {report['speedup'][key] or float('nan'):.1f}x (CPU time: engine "
                     f"{st['engine']['total_cpu']['p50']:.1f} ms, {report['speedup_cpu'][key] or float('nan'):.1f}x)")
        lines.append(f"  {'stage':<12} {'engine p50':>11} {'p90':>8} {'baseline p50':>13} {'ratio':>7}")
        for name, row in st["engine"].items():
            if name == "total_cpu":
                continue
            b = st["baseline"].get(name, {}).get("p50", float("nan"))
            r = st["speedup_p50"].get(name)
            lines.append(f"  {name:<12} {row['p50']:>11.2f} {row['p90']:>8.2f} {b:>13.1f} "
                         f"{(f'{r:.1f}x' if r else '-'):>7}")
    acc = report["accuracy"]
    for name in ("engine", "baseline"):
        s = acc[name]
        extra = (f", median error {s['t_err_median_m']:.3f} m / {s['r_err_median_deg']:.3f} deg"
                 if "t_err_median_m" in s else "")
        lines.append(f"accuracy {name}: {s['success']}/{s['pairs']} succeeded{extra}")
    lines.append(f"engine and baseline agree on {acc['agree']}/{len(acc['pairs'])} pairs (success, and pose within "
                 f"{acc['tolerance']['t_m']} m / {acc['tolerance']['r_deg']} deg)")
    mim, kp = report["features"]["mim_equal_fraction_of_lit"], report["features"]["keypoints_per_image"]
    lines.append(f"features: engine MIM equals the complex128 baseline's on {100 * mim['median']:.2f}% of lit pixels "
                 f"(median image; worst {100 * mim['min']:.2f}%); keypoints per ego image: engine {kp['engine']:.0f} "
                 f"(max {kp['engine_max']}), baseline {kp['baseline']:.0f} (max {kp['baseline_max']})")
    mem = report["memory"]
    lines.append(f"memory: tracemalloc peak engine {mem['engine_tracemalloc_peak_mb'][HOT]:.1f} MB hot / "
                 f"{mem['engine_tracemalloc_peak_mb'][COLD]:.1f} MB cold, baseline "
                 f"{mem['baseline_tracemalloc_peak_mb'][COLD]:.1f} MB cold; process RSS peak "
                 f"{mem['process_engine_runs']['rss_peak_mb']:.0f} MB during the engine runs (before them "
                 f"{mem['process_before']['rss_mb'] or 0:.0f} MB)")
    service = report.get("service")
    if service and service.get("runs"):
        lines.append(f"service over Zenoh ({service['workers']} workers, peers at {service['rate_hz']:g} Hz, "
                     f"{service['seconds']:g} s each, {service['poses']}):")
        for peers, r in sorted(service["runs"].items(), key=lambda kv: int(kv[0])):
            lines.append(f"  {peers} peer(s): offered {r['offered_fps']:.1f}/s, results {r['results_fps']:.1f}/s, "
                         f"dropped {r['dropped']} ({100 * r['drop_fraction']:.0f}%), latency p50 "
                         f"{r['latency_ms']['p50']:.0f} ms p99 {r['latency_ms']['p99']:.0f} ms, "
                         f"{100 * r['success_fraction']:.0f}% aligned, service CPU {r['service_cpu_cores'] or 0:.2f} "
                         f"cores, RSS peak {r['service_memory']['rss_peak_mb'] or 0:.0f} MB, sustained: "
                         f"{r['sustained']}")
    if service and (service.get("error") or service.get("errors")):
        problems = [service["error"]] if service.get("error") else [
            f"{n} peer(s): {e.splitlines()[-1] if e.strip() else e}" for n, e in service["errors"].items()]
        lines.append("service: not measured: " + "; ".join(problems))
    load = report["load_avg"]
    lines.append(f"load average start {load['start'][0]:.2f}, end {load['end'][0]:.2f} on "
                 f"{report['machine']['cpus_usable']} CPUs; commit {(report['git'].get('commit') or '?')[:12]}"
                 f"{' (uncommitted changes under service/ or client/)' if report['git'].get('dirty') else ''}")
    return "\n".join(lines)


def bench(
    json_out: Optional[Path] = typer.Option(None, "--json", help="write the full report as JSON here"),
    runs: Optional[int] = typer.Option(None, min=1, help="timed passes over the workload [10; --quick 3]"),
    quick: bool = typer.Option(False, "--quick", help="2 pairs, 3 runs, short service runs (1 and 4 peers)"),
    plot: Optional[Path] = typer.Option(None, "--plot", help="write the stage-breakdown figure (PNG) here"),
    markdown: Optional[Path] = typer.Option(None, "--markdown", help="write the tables as Markdown here"),
    no_service: bool = typer.Option(False, "--no-service", help="skip the service throughput part"),
    data: Optional[Path] = typer.Option(None, "--data", exists=True, file_okay=False,
                                       help="real scans in the OPV2V/V2V4Real layout instead of the simulator"),
    max_pairs: int = typer.Option(12, min=1, help="with --data: at most this many ego/peer pairs"),
    baseline_runs: int = typer.Option(1, min=1, help="timed passes of the (slow) baseline"),
    warmup: int = typer.Option(1, min=0, help="untimed engine passes first"),
    peers: Optional[str] = typer.Option(None, help="service runs: comma-separated peer counts [1,4,8; --quick 1,4]"),
    service_seconds: Optional[float] = typer.Option(None, min=1.0, help="measured seconds per service run [10]"),
    rate_hz: float = typer.Option(10.0, min=0.5, max=50.0, help="frame rate of the ego and every peer"),
    workers: int = typer.Option(2, min=1, max=16, help="service engine worker threads"),
    pose_sigma_m: float = typer.Option(2.0, min=0.0, help="service runs: reported-pose noise, metres (1 sigma)"),
    pose_sigma_deg: float = typer.Option(2.0, min=0.0, help="service runs: reported-pose yaw noise, degrees"),
    no_pose: bool = typer.Option(False, "--no-pose", help="service runs: frames carry no reported pose"),
    range_m: Optional[float] = typer.Option(None, help="BV half width R in metres [config default, 80]"),
    resolution_m: Optional[float] = typer.Option(None, help="BV cell size in metres [config default, 0.4]"),
    engine_threads: Optional[int] = typer.Option(
        None, min=1, max=16, help="threads inside one engine call (MIM orientations, descriptor keypoints, "
        "matching queries) [config default, 2]; 1 times the engine on one core"),
) -> None:
    """Time the engine per stage against the in-benchmark baseline (same inputs, same run), check they agree,
    and measure the service's sustained throughput with 1, 4 and 8 peers over Zenoh on loopback."""
    from bb_align.engine.config import AlignConfig

    from .run import run_benchmark
    from .workload import data_workload, sim_workload

    config = AlignConfig()
    bev_over = {k: v for k, v in (("range_m", range_m), ("resolution_m", resolution_m)) if v is not None}
    if bev_over:
        try:
            config = config.model_copy(update={"bev": type(config.bev)(**{**config.bev.model_dump(), **bev_over})})
        except ValueError as e:
            raise typer.BadParameter(str(e)) from None
    if engine_threads is not None:
        config = config.model_copy(update={
            "mim": config.mim.model_copy(update={"threads": engine_threads}),
            "features": config.features.model_copy(update={"threads": engine_threads}),
            "match": config.match.model_copy(update={"threads": engine_threads})})
    runs = runs or (3 if quick else 10)
    if peers is None:
        peer_counts = [1, 4] if quick else [1, 4, 8]
    else:
        try:
            peer_counts = sorted({int(p) for p in peers.split(",") if p.strip()})
        except ValueError:
            raise typer.BadParameter(f"--peers must be comma-separated integers, got {peers!r}") from None
        if not peer_counts or min(peer_counts) < 1 or max(peer_counts) > 32:
            raise typer.BadParameter(f"--peers counts must be within 1..32, got {peers!r}")
    seconds = service_seconds or (3.0 if quick else 10.0)

    typer.echo("building the workload ...", err=True)
    if data is not None:
        workload = data_workload(data, config, max_pairs=2 if quick else max_pairs,
                                 progress=lambda it: _progress(it, "workload"))
    else:
        workload = sim_workload(config, quick=quick, progress=lambda it: _progress(it, "workload"))
    report = run_benchmark(workload, config, runs=runs, warmup=warmup, baseline_runs=baseline_runs,
                           progress=_progress)
    report["service"] = None
    if not no_service:
        from .throughput import ServiceBenchConfig, measure_service

        sb = ServiceBenchConfig(peer_counts=peer_counts, seconds=seconds, rate_hz=rate_hz, workers=workers,
                                frames=3 if quick else 6, send_pose=not no_pose, pose_sigma_m=pose_sigma_m,
                                pose_sigma_deg=pose_sigma_deg)
        report["service"] = measure_service(sb, config, progress=_progress)
    report["command"] = "bb-align " + " ".join(sys.argv[1:])
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(report, indent=1, default=float))
    if plot is not None:
        from .plot import plot_report

        plot_report(report, plot)
    if markdown is not None:
        from .markdown import report_markdown

        markdown.parent.mkdir(parents=True, exist_ok=True)
        markdown.write_text(report_markdown(report))
    typer.echo(_summary(report))
    if json_out is not None:
        typer.echo(f"report: {json_out}")
    if plot is not None:
        typer.echo(f"plot: {plot}")
    if markdown is not None:
        typer.echo(f"markdown: {markdown}")


def register(app: typer.Typer) -> None:
    app.command("bench")(bench)
