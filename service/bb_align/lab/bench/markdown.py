"""The benchmark report as Markdown tables: what ``bb-align bench`` prints, and writes with ``--markdown OUT`` (for
docs/performance.md and the README)."""

from __future__ import annotations

from .run import COLD, HOT


def _ms(v: float | None) -> str:
    if v is None or v != v:
        return "-"
    return f"{v:.0f}" if v >= 100 else f"{v:.1f}" if v >= 1 else f"{v:.2f}"


def _x(v: float | None) -> str:
    return "-" if not v else f"{v:.0f}x" if v >= 10 else f"{v:.1f}x"


def _kp(features: dict, side: str) -> str:
    kp = features["keypoints_per_image"]
    return f"{kp[side]:.0f} mean, {kp.get(side + '_max', kp[side]):.0f} max"


def load_bounds(path) -> dict:
    """The lower bounds ``benchmarks/stage_bounds.py --record`` wrote (docs/stage_bounds.json) as
    {"source", "hot_path_p50_ms", "stages": {stage: {"bound_ms", "best_library", "today_p50_ms"}}}; ValueError naming
    the file and what is wrong when it is not such a file."""
    import json
    from pathlib import Path

    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: not a readable JSON file ({e.__class__.__name__})") from None
    stages = data.get("stages") if isinstance(data, dict) else None
    if not isinstance(stages, dict) or not stages:
        raise ValueError(f"{path}: no 'stages' table (write it with benchmarks/stage_bounds.py --record)")
    out = {}
    for name, row in stages.items():
        bound = row.get("bound_ms") if isinstance(row, dict) else None
        if not isinstance(bound, (int, float)) or not bound > 0:
            raise ValueError(f"{path}: stages.{name}.bound_ms must be a positive number, got {bound!r}")
        out[name] = {
            "bound_ms": float(bound),
            "best_library": str(row.get("best_library", "")),
            "today_p50_ms": row.get("today_p50_ms"),
        }
    return {"source": str(path), "hot_path_p50_ms": data.get("hot_path_p50_ms"), "stages": out}


def bounds_markdown(stage_p50_ms: dict[str, float], bounds: dict) -> str:
    """The hot path's stages beside their lower bounds: stage, this run's p50, the bound, the gap (p50 / bound), the
    tool the bound was measured with; stages without a bound are not listed."""
    when = bounds.get("hot_path_p50_ms")
    out = [
        f"Hot-path stages against their lower bounds ({bounds['source']}, measured by benchmarks/stage_bounds.py"
        + ("" if when is None else f" when the hot path took {when} ms")
        + "):",
        "",
        "| stage | engine hot p50 | lower bound | gap | bound measured with |",
        "|---|---:|---:|---:|---|",
    ]
    for name, row in bounds["stages"].items():
        if name not in stage_p50_ms:
            continue
        p50, bound = stage_p50_ms[name], row["bound_ms"]
        out.append(f"| {name} | {_ms(p50)} ms | {_ms(bound)} ms | {_x(p50 / bound)} | {row['best_library']} |")
    return "\n".join(out) + "\n"


def report_markdown(report: dict) -> str:
    git = report.get("git") or {}
    m = report["machine"]
    load = report["load_avg"]
    wl = report["workload"]
    out = [
        f"Command: `{report.get('command', 'bb-align bench')}` at commit `{(git.get('commit') or '?')[:12]}`"
        f"{' (with uncommitted changes under service/ or client/)' if git.get('dirty') else ''}; "
        f"{m['cpus_usable']} CPUs "
        f"({m.get('cpu_model') or 'unknown CPU'}), load average {load['start'][0]:.1f} at the start and "
        f"{load['end'][0]:.1f} at the end (other jobs shared the machine); numpy {m['numpy']}, scipy "
        f"{m['scipy']}, OpenCV {m['opencv']}.",
        f"Workload: {wl['pairs']} {wl['source']} pairs, {wl['image_px'][0]}x{wl['image_px'][1]} px BV images "
        f"({report['config']['bev']['range_m']:g} m range, {report['config']['bev']['resolution_m']:g} m/px); engine "
        f"{report['runs']} timed passes after {report['warmup_passes']} warm-up, baseline {report['baseline_runs']}.",
        "",
        "| path | engine p50 | engine p90 | engine CPU p50 | baseline p50 | speed-up (p50) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for key, title in ((HOT, "peer frame vs cached ego frame"), (COLD, "cold pair (both prepared)")):
        e, b = report["stages"][key]["engine"], report["stages"][key]["baseline"]
        out.append(
            f"| {title} | {_ms(e['total']['p50'])} ms | {_ms(e['total']['p90'])} ms | "
            f"{_ms(e['total_cpu']['p50'])} ms | {_ms(b['total']['p50'])} ms | {_x(report['speedup'][key])} |"
        )
    out += [
        "",
        "Per stage, p50 ms (the hot path's stages are the peer's; the cold pair's add both frames):",
        "",
        "| stage | engine hot | baseline hot | ratio | engine cold | baseline cold | ratio |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    hot, cold = report["stages"][HOT], report["stages"][COLD]
    for name in hot["engine"]:
        if name == "total_cpu":
            continue
        row = [name]
        for st in (hot, cold):
            row += [
                _ms(st["engine"][name]["p50"]),
                _ms(st["baseline"].get(name, {}).get("p50")),
                _x(st["speedup_p50"].get(name)),
            ]
        out.append("| " + " | ".join(row) + " |")
    if report.get("bounds"):
        hot_p50 = {k: v["p50"] for k, v in hot["engine"].items() if isinstance(v, dict) and "p50" in v}
        out += ["", bounds_markdown(hot_p50, report["bounds"]).rstrip("\n")]
    acc = report["accuracy"]
    out += [
        "",
        "| accuracy (vs simulator truth) | succeeded | median error | max error (succeeded) |",
        "|---|---:|---:|---:|",
    ]
    for name in ("engine", "baseline"):
        s = acc[name]
        err = f"{s['t_err_median_m']:.3f} m / {s['r_err_median_deg']:.3f} deg" if "t_err_median_m" in s else "-"
        mx = f"{s['t_err_max_m']:.3f} m / {s['r_err_max_deg']:.3f} deg" if "t_err_max_m" in s else "-"
        out.append(f"| {name} | {s['success']}/{s['pairs']} | {err} | {mx} |")
    out.append(
        f"\nEngine and baseline agree on {acc['agree']}/{len(acc['pairs'])} pairs (same success, poses within "
        f"{acc['tolerance']['t_m']} m and {acc['tolerance']['r_deg']} deg)."
    )
    feat = report["features"]
    out.append(
        f"The engine's MIM equals the complex128 baseline's on "
        f"{100 * feat['mim_equal_fraction_of_lit']['median']:.2f}% of lit pixels (median image, worst "
        f"{100 * feat['mim_equal_fraction_of_lit']['min']:.2f}%); keypoints per ego image: engine "
        f"{_kp(feat, 'engine')}, baseline {_kp(feat, 'baseline')}."
    )
    mem = report["memory"]
    out.append(
        f"Memory: tracemalloc peak per call, engine {mem['engine_tracemalloc_peak_mb'][HOT]:.1f} MB (hot) / "
        f"{mem['engine_tracemalloc_peak_mb'][COLD]:.1f} MB (cold), baseline "
        f"{mem['baseline_tracemalloc_peak_mb'][HOT]:.1f} / {mem['baseline_tracemalloc_peak_mb'][COLD]:.1f} MB; "
        f"bench process RSS peak {mem['process_engine_runs']['rss_peak_mb']:.0f} MB during the engine "
        f"runs, {mem['process_baseline_runs']['rss_peak_mb']:.0f} MB during the baseline runs (interpreter, "
        f"libraries and workload included: {mem['process_before']['rss_mb'] or 0:.0f} MB before them)."
    )
    service = report.get("service")
    if service and service.get("runs"):
        out += [
            "",
            f"Service over Zenoh on loopback ({service['workers']} workers, every car at "
            f"{service['rate_hz']:g} Hz, {service['seconds']:g} s measured after {service['warmup_s']:g} s, "
            f"{service.get('poses', 'reported poses')}):",
            "",
            "| peers | offered /s | results /s | aligned | dropped | latency p50 | latency p99 | service CPU | "
            "service RSS peak | sustained |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        ]
        for n, r in sorted(service["runs"].items(), key=lambda kv: int(kv[0])):
            out.append(
                f"| {n} | {r['offered_fps']:.0f} | {r['results_fps']:.1f} | "
                f"{100 * r['success_fraction']:.0f}% | {r['dropped']} ({100 * r['drop_fraction']:.0f}%) | "
                f"{_ms(r['latency_ms']['p50'])} ms | "
                f"{_ms(r['latency_ms']['p99'])} ms | {r['service_cpu_cores'] or 0:.2f} cores | "
                f"{r['service_memory']['rss_peak_mb'] or 0:.0f} MB | {'yes' if r['sustained'] else 'no'} |"
            )
    if service and (service.get("error") or service.get("errors")):
        problems = (
            [service["error"]]
            if service.get("error")
            else [f"{n} peer(s): {e.splitlines()[-1] if e.strip() else e}" for n, e in service["errors"].items()]
        )
        out += ["", "Service: not measured: " + "; ".join(problems)]
    return "\n".join(out) + "\n"
