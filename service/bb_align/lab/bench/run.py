"""Time the engine and the baseline on one workload, stage by stage, in one process and one run.

Two paths are timed for every pair:

- ``peer_vs_cached_ego`` (the service's hot path): the ego frame's features are computed once beforehand, as the
  service's ego cache does; timed is PNG bytes in -> decode -> ``prepare`` (peer) -> ``align``.
- ``cold_pair``: nothing cached; both PNGs decoded and prepared, then aligned.

Runs are interleaved over the pairs (pass after pass) so that load from other processes spreads over all pairs;
the first ``warmup`` passes are not counted. The baseline runs the same paths on the same inputs after the
engine's warm-up. Peak memory is measured in separate, untimed calls (tracemalloc slows allocation down).
"""

from __future__ import annotations

import os
import platform
import resource
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bb_align.engine.bev import BevImage
from bb_align.engine.config import AlignConfig
from bb_align.engine.geometry import pose_error
from bb_align.engine.pipeline import Aligner

from .baseline import BaselineAligner
from .workload import BenchPair, Workload

STAGES = ("decode", "mim", "keypoints", "descriptors", "matching", "ransac", "refine", "boxes")
HOT, COLD = "peer_vs_cached_ego", "cold_pair"
PATHS = (HOT, COLD)
TARGET_HOT_P50_MS = 50.0  # issue 5: peer frame vs cached ego frame, p50, end to end
TARGET_SPEEDUP = 20.0  # issue 5: at least this many times faster than the baseline, same run
AGREE_T_M = 0.5  # engine and baseline poses agree when within these of each other
AGREE_R_DEG = 0.5


@dataclass
class Sample:
    """One timed call: its total and per-stage wall times (ms)."""

    total_ms: float
    stages_ms: dict[str, float]
    cpu_ms: float  # process CPU time over the call (all threads): steadier than wall time on a busy machine


@dataclass
class Outcome:
    success: bool
    reason: str | None
    T_ego_peer: np.ndarray
    inliers_bv: int
    inliers_box: int


@dataclass
class Measurements:
    samples: dict[str, list[Sample]] = field(default_factory=lambda: {p: [] for p in PATHS})
    outcomes: dict[str, Outcome] = field(default_factory=dict)  # pair name -> result of the last run
    ego_prepare_ms: list[float] = field(default_factory=list)  # per ego frame, once (cached afterwards)
    peak_mb: dict[str, float] = field(default_factory=dict)  # path -> tracemalloc peak (first pair)
    ego_features: list = field(default_factory=list)  # each pair's prepared ego frame (MIM kept)


# ---- one engine / baseline call each --------------------------------------------------------------------------
def _decode(png: bytes, meta: dict, stages: dict[str, float]) -> BevImage:
    t0 = time.perf_counter()
    bev = BevImage.from_png(png, **meta)
    stages["decode"] = stages.get("decode", 0.0) + (time.perf_counter() - t0) * 1e3
    return bev


def _add(stages: dict[str, float], timings: dict[str, float]) -> None:
    for k, v in timings.items():
        if k not in ("align_total", "bev"):
            stages[k] = stages.get(k, 0.0) + v


class EngineRunner:
    """The engine as the service drives it."""

    name = "engine"

    def __init__(self, config: AlignConfig):
        self.aligner = Aligner(config)
        self.config = config

    def prepare_ego(self, pair: BenchPair):
        """Everything the service caches per ego frame: features, the descriptors matched against (all
        orientation offsets) and the BV cloud the refinement uses."""
        cfg = self.config
        ego = self.aligner.prepare(BevImage.from_png(pair.ego_png, **pair.bev_meta), pair.boxes_ego, keep_maps=True)
        ego.reference_descriptors(cfg.features, cfg.mim.n_orient)
        ego.cloud(cfg.refine)
        return ego

    def hot(self, pair: BenchPair, ego) -> tuple[Sample, Outcome]:
        stages: dict[str, float] = {}
        c0, t0 = time.process_time(), time.perf_counter()
        peer = self.aligner.prepare(_decode(pair.peer_png, pair.bev_meta, stages), pair.boxes_peer)
        res = self.aligner.align(ego, peer)
        total, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        _add(stages, peer.timings_ms)
        _add(stages, res.timings_ms)
        return Sample(total, stages, cpu), _outcome(res)

    def cold(self, pair: BenchPair) -> tuple[Sample, Outcome]:
        stages: dict[str, float] = {}
        c0, t0 = time.process_time(), time.perf_counter()
        ego = self.aligner.prepare(_decode(pair.ego_png, pair.bev_meta, stages), pair.boxes_ego)
        peer = self.aligner.prepare(_decode(pair.peer_png, pair.bev_meta, stages), pair.boxes_peer)
        res = self.aligner.align(ego, peer)
        total, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        for t in (ego.timings_ms, peer.timings_ms, res.timings_ms):
            _add(stages, t)
        return Sample(total, stages, cpu), _outcome(res)


class BaselineRunner(EngineRunner):
    """The straightforward baseline through the same two paths."""

    name = "baseline"

    def __init__(self, config: AlignConfig):
        self.aligner = BaselineAligner(config)

    def prepare_ego(self, pair: BenchPair):
        return self.aligner.prepare(BevImage.from_png(pair.ego_png, **pair.bev_meta), pair.boxes_ego)


def _outcome(res) -> Outcome:
    return Outcome(
        bool(res.success),
        res.reason,
        np.asarray(res.T_ego_peer, dtype=float),
        int(res.inliers_bv),
        int(res.inliers_box),
    )


# ---- measuring ------------------------------------------------------------------------------------------------
def measure(
    runner: EngineRunner,
    pairs: list[BenchPair],
    *,
    runs: int,
    warmup: int,
    progress: Callable[[Iterable], Iterable] | None = None,
    label: str = "",
) -> Measurements:
    """``warmup`` + ``runs`` passes over all pairs, each pass timing the hot path then the cold pair per pair."""
    out = Measurements()
    egos = []
    for p in pairs:
        t_ego = time.perf_counter()
        egos.append(runner.prepare_ego(p))
        out.ego_prepare_ms.append((time.perf_counter() - t_ego) * 1e3)
    steps = [(i, k) for i in range(warmup + runs) for k in range(len(pairs))]
    for i, k in progress(steps, label) if progress else steps:
        pair = pairs[k]
        hot, outcome = runner.hot(pair, egos[k])
        cold, _ = runner.cold(pair)
        if i >= warmup:
            out.samples[HOT].append(hot)
            out.samples[COLD].append(cold)
            out.outcomes[pair.name] = outcome
    out.ego_features = egos
    # Peak traced memory (numpy buffers included) of each path: one untimed call on the first pair (every
    # pair has the same image size, so the big buffers are the same).
    for path in PATHS:
        tracemalloc.start()
        try:
            runner.hot(pairs[0], egos[0]) if path == HOT else runner.cold(pairs[0])
            out.peak_mb[path] = tracemalloc.get_traced_memory()[1] / 2**20
        finally:
            tracemalloc.stop()
    return out


def percentiles(values: Iterable[float]) -> dict[str, float]:
    v = np.asarray(list(values), dtype=float)
    if len(v) == 0:
        return {"p50": float("nan"), "p90": float("nan"), "mean": float("nan"), "n": 0}
    return {
        "p50": float(np.percentile(v, 50)),
        "p90": float(np.percentile(v, 90)),
        "mean": float(v.mean()),
        "n": int(len(v)),
    }


def stage_table(samples: list[Sample]) -> dict[str, dict[str, float]]:
    """Per stage p50/p90/mean over the samples (a stage a call did not reach counts 0), plus 'other' (the
    total minus the named stages: conversions, guards, bookkeeping) and 'total'."""
    names = list(STAGES) + sorted({k for s in samples for k in s.stages_ms} - set(STAGES))
    table = {n: percentiles(s.stages_ms.get(n, 0.0) for s in samples) for n in names}
    table["other"] = percentiles(s.total_ms - sum(s.stages_ms.values()) for s in samples)
    table["total"] = percentiles(s.total_ms for s in samples)
    table["total_cpu"] = percentiles(s.cpu_ms for s in samples)
    return table


def _ratio(a: float, b: float) -> float | None:
    return float(a / b) if b > 0 and np.isfinite(a) and np.isfinite(b) else None


# ---- accuracy cross-check -------------------------------------------------------------------------------------
def accuracy(pairs: list[BenchPair], engine: dict[str, Outcome], baseline: dict[str, Outcome]) -> dict:
    """Each pair's outcome from both, errors vs the truth, and whether the two agree."""
    rows = []
    for p in pairs:
        e, b = engine[p.name], baseline[p.name]
        row = {
            "pair": p.name,
            "distance_m": p.distance_m,
            "engine": {
                "success": e.success,
                "reason": e.reason,
                "inliers_bv": e.inliers_bv,
                "inliers_box": e.inliers_box,
            },
            "baseline": {
                "success": b.success,
                "reason": b.reason,
                "inliers_bv": b.inliers_bv,
                "inliers_box": b.inliers_box,
            },
        }
        if p.T_ego_peer is not None:
            for name, o in (("engine", e), ("baseline", b)):
                t_err, r_err = pose_error(o.T_ego_peer, p.T_ego_peer)
                row[name].update(t_err_m=t_err, r_err_deg=r_err)
        dt, dr = pose_error(e.T_ego_peer, b.T_ego_peer)
        row["engine_vs_baseline"] = {"t_m": dt, "r_deg": dr}
        row["agree"] = bool(e.success == b.success and (not e.success or (dt <= AGREE_T_M and dr <= AGREE_R_DEG)))
        rows.append(row)

    def summary(name: str) -> dict:
        ok = [r[name] for r in rows if r[name]["success"]]
        s = {"success": len(ok), "pairs": len(rows)}
        if ok and "t_err_m" in ok[0]:
            t = np.array([r["t_err_m"] for r in ok])
            r_ = np.array([r["r_err_deg"] for r in ok])
            s.update(
                t_err_median_m=float(np.median(t)),
                t_err_max_m=float(t.max()),
                r_err_median_deg=float(np.median(r_)),
                r_err_max_deg=float(r_.max()),
                under_1m_1deg=int(((t < 1.0) & (r_ < 1.0)).sum()),
            )
        return s

    return {
        "tolerance": {"t_m": AGREE_T_M, "r_deg": AGREE_R_DEG},
        "engine": summary("engine"),
        "baseline": summary("baseline"),
        "agree": int(sum(r["agree"] for r in rows)),
        "pairs": rows,
    }


def feature_agreement(engine: list, baseline: list) -> dict:
    """How closely the engine's MIM follows the exact complex128 one on the same (ego) images, and how many
    keypoints each describes (the engine caps them, the baseline does not)."""
    agree = []
    for e, b in zip(engine, baseline):
        lit = (e.mim > 0) | (b.mim > 0)
        agree.append(float(np.mean(e.mim[lit] == b.mim[lit])) if lit.any() else 1.0)
    return {
        "mim_equal_fraction_of_lit": {"min": float(np.min(agree)), "median": float(np.median(agree))},
        "keypoints_per_image": {
            "engine": float(np.mean([len(e.keypoints_rc) for e in engine])),
            "engine_max": int(max(len(e.keypoints_rc) for e in engine)),
            "baseline": float(np.mean([len(b.keypoints_rc) for b in baseline])),
            "baseline_max": int(max(len(b.keypoints_rc) for b in baseline)),
        },
    }


# ---- environment ----------------------------------------------------------------------------------------------
def git_commit(repo: Path | None = None) -> dict:
    """HEAD of the repository holding this package, and whether the engine sources differ from it."""
    repo = repo or Path(__file__).resolve().parents[3]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "service", "client"],
            cwd=repo,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": head, "dirty": bool(dirty), "dirty_files": dirty.splitlines()[:50]}


def machine_info() -> dict:
    import cv2
    import scipy

    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count()
    cpu_model = None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu_model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    threads = {
        k: os.environ[k] for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS") if k in os.environ
    }
    return {
        "cpu_count": os.cpu_count(),
        "cpus_usable": affinity,
        "cpu_model": cpu_model,
        "cv2_threads": cv2.getNumThreads(),
        "thread_env": threads,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
    }


def reset_peak_rss() -> bool:
    """Restart the kernel's peak-RSS count of this process (Linux: write 5 to /proc/self/clear_refs)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def rss_mb(since_reset: bool = False) -> dict:
    """Current and peak resident memory of this process, MB (the peak since the last reset_peak_rss when
    ``since_reset``; since the process started otherwise)."""
    out = {
        "rss_mb": None,
        "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "peak_since": "reset" if since_reset else "process start",
    }
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                out["rss_mb"] = int(line.split()[1]) / 1024.0
            elif line.startswith("VmHWM:"):
                out["rss_peak_mb"] = int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        out["peak_since"] = "process start"
    return out


# ---- the whole benchmark --------------------------------------------------------------------------------------
def run_benchmark(
    workload: Workload,
    config: AlignConfig,
    *,
    runs: int,
    warmup: int = 1,
    baseline_runs: int = 1,
    progress: Callable[[Iterable, str], Iterable] | None = None,
) -> dict:
    """Engine and baseline on the workload -> the report (a JSON-able dict; see docs/performance.md)."""
    if not workload.pairs:
        raise ValueError("the workload has no pairs")
    if runs < 1 or baseline_runs < 1 or warmup < 0:
        raise ValueError(f"runs ({runs}) and baseline_runs ({baseline_runs}) must be >= 1, warmup ({warmup}) >= 0")
    load_start = os.getloadavg()
    t_start = time.time()
    memory_before = rss_mb()
    reset = reset_peak_rss()
    engine = measure(EngineRunner(config), workload.pairs, runs=runs, warmup=warmup, progress=progress, label="engine")
    memory_engine = rss_mb(since_reset=reset)
    reset = reset_peak_rss()
    base = measure(
        BaselineRunner(config), workload.pairs, runs=baseline_runs, warmup=0, progress=progress, label="baseline"
    )
    memory_baseline = rss_mb(since_reset=reset)

    report: dict = {
        "schema": 1,
        "started_unix": t_start,
        "git": git_commit(),
        "machine": machine_info(),
        "workload": workload.describe(),
        "config": config.model_dump(mode="json"),
        "runs": runs,
        "warmup_passes": warmup,
        "baseline_runs": baseline_runs,
    }
    stages, totals = {}, {}
    for path in PATHS:
        eng_t, base_t = stage_table(engine.samples[path]), stage_table(base.samples[path])
        ratio = {k: _ratio(base_t[k]["p50"], eng_t[k]["p50"]) for k in eng_t if k in base_t}
        stages[path] = {"engine": eng_t, "baseline": base_t, "speedup_p50": ratio}
        totals[path] = (eng_t["total"], base_t["total"])
    hot_e, hot_b = totals[HOT]
    cold_e, cold_b = totals[COLD]
    report.update(
        {
            "peer_vs_cached_ego_ms_p50": hot_e["p50"],
            "peer_vs_cached_ego_ms_p90": hot_e["p90"],
            "cold_pair_ms_p50": cold_e["p50"],
            "cold_pair_ms_p90": cold_e["p90"],
            "peer_vs_cached_ego_cpu_ms_p50": stages[HOT]["engine"]["total_cpu"]["p50"],
            "cold_pair_cpu_ms_p50": stages[COLD]["engine"]["total_cpu"]["p50"],
            "ego_frame_prepare_ms_p50": percentiles(engine.ego_prepare_ms)["p50"],
            "baseline": {
                "peer_vs_cached_ego_ms_p50": hot_b["p50"],
                "peer_vs_cached_ego_ms_p90": hot_b["p90"],
                "cold_pair_ms_p50": cold_b["p50"],
                "cold_pair_ms_p90": cold_b["p90"],
                "ego_frame_prepare_ms_p50": percentiles(base.ego_prepare_ms)["p50"],
            },
            "speedup": {HOT: _ratio(hot_b["p50"], hot_e["p50"]), COLD: _ratio(cold_b["p50"], cold_e["p50"])},
            "speedup_cpu": {
                p: _ratio(stages[p]["baseline"]["total_cpu"]["p50"], stages[p]["engine"]["total_cpu"]["p50"])
                for p in PATHS
            },
            "stages": stages,
            "memory": {
                "engine_tracemalloc_peak_mb": engine.peak_mb,
                "baseline_tracemalloc_peak_mb": base.peak_mb,
                "process_before": memory_before,
                "process_engine_runs": memory_engine,
                "process_baseline_runs": memory_baseline,
            },
            "accuracy": accuracy(workload.pairs, engine.outcomes, base.outcomes),
            "features": feature_agreement(engine.ego_features, base.ego_features),
        }
    )
    report["targets"] = {
        "peer_vs_cached_ego_ms_p50_max": TARGET_HOT_P50_MS,
        "peer_vs_cached_ego_met": bool(hot_e["p50"] <= TARGET_HOT_P50_MS),
        "speedup_min": TARGET_SPEEDUP,
        "speedup_met": bool((report["speedup"][HOT] or 0) >= TARGET_SPEEDUP),
    }
    report["load_avg"] = {"start": list(load_start), "end": list(os.getloadavg())}
    report["elapsed_s"] = time.time() - t_start
    report["argv"] = sys.argv
    return report
