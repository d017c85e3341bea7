"""`bb-align bench`'s report beside the stage lower bounds, and its peers-vs-throughput figure, on stub measurement
dicts (no engine, no service: the printing and plotting paths only; the numbers come from the stubs)."""

from __future__ import annotations

import json

import cv2
import pytest
from typer.testing import CliRunner

from bb_align.lab.bench.markdown import bounds_markdown, load_bounds, report_markdown
from bb_align.lab.bench.plot import plot_report
from bb_align.lab.bench.run import COLD, HOT

BOUNDS_JSON = {
    "hot_path_p50_ms": 101.5,
    "stages": {
        "mim": {"today_p50_ms": 30.0, "bound_ms": 12.0, "best_library": "OpenCV DFT"},
        "matching": {"today_p50_ms": 8.0, "bound_ms": 4.0, "best_library": "one float32 GEMM"},
        "landscape": {"today_p50_ms": 13.0, "bound_ms": 6.5, "best_library": "compiled"},
    },
}


def _pct(p50: float) -> dict:
    return {"p50": p50, "p90": p50 * 1.2, "mean": p50, "n": 3}


def _stub_report(bounds: dict | None, peers: dict[int, tuple[float, float]]) -> dict:
    """The keys report_markdown and plot_report read; stage p50s mim 24.0, matching 6.0, landscape 13.0 ms."""
    engine = {"mim": _pct(24.0), "matching": _pct(6.0), "landscape": _pct(13.0), "total": _pct(60.0)}
    engine["total_cpu"] = _pct(90.0)
    base = {k: _pct(v["p50"] * 10) for k, v in engine.items()}
    stages = {p: {"engine": engine, "baseline": base, "speedup_p50": dict.fromkeys(engine, 10.0)} for p in (HOT, COLD)}
    runs = {
        str(n): {
            "offered_fps": 10.0 * n,
            "results_fps": res,
            "success_fraction": 0.8,
            "dropped": 0,
            "drop_fraction": 0.0,
            "latency_ms": {"p50": lat, "p90": lat * 1.2, "p99": lat * 1.5},
            "service_cpu_cores": 1.5,
            "service_memory": {"rss_peak_mb": 400.0},
            "sustained": True,
        }
        for n, (res, lat) in peers.items()
    }
    acc_side = {"success": 2, "pairs": 2}
    return {
        "machine": {"cpus_usable": 2, "cpu_model": "stub", "numpy": "x", "scipy": "x", "opencv": "x"},
        "load_avg": {"start": [1.0, 1.0, 1.0], "end": [1.0, 1.0, 1.0]},
        "workload": {"pairs": 2, "source": "sim", "image_px": [500, 500]},
        "config": {"bev": {"range_m": 100.0, "resolution_m": 0.4}},
        "runs": 3,
        "warmup_passes": 1,
        "baseline_runs": 1,
        "stages": stages,
        "speedup": {HOT: 10.0, COLD: 10.0},
        "accuracy": {
            "engine": acc_side,
            "baseline": acc_side,
            "agree": 2,
            "pairs": [{}, {}],
            "tolerance": {"t_m": 0.5, "r_deg": 0.5},
        },
        "features": {
            "mim_equal_fraction_of_lit": {"median": 1.0, "min": 1.0},
            "keypoints_per_image": {"engine": 300, "baseline": 300},
        },
        "memory": {
            "engine_tracemalloc_peak_mb": {HOT: 1.0, COLD: 1.0},
            "baseline_tracemalloc_peak_mb": {HOT: 1.0, COLD: 1.0},
            "process_engine_runs": {"rss_peak_mb": 1.0},
            "process_baseline_runs": {"rss_peak_mb": 1.0},
            "process_before": {"rss_mb": 1.0},
        },
        "service": {"runs": runs, "rate_hz": 10.0, "workers": 2, "seconds": 3.0, "warmup_s": 2.0} if runs else None,
        "bounds": bounds,
    }


@pytest.fixture
def bounds_file(tmp_path):
    path = tmp_path / "stage_bounds.json"
    path.write_text(json.dumps(BOUNDS_JSON))
    return path


def _table_rows(text: str) -> dict[str, list[str]]:
    rows = {}
    for line in text.splitlines():
        if line.startswith("| ") and "lower bound" not in line:
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[0]] = cells[1:]
    return rows


def test_the_stage_table_prints_the_given_p50s_bounds_and_gaps(bounds_file):
    bounds = load_bounds(bounds_file)
    text = report_markdown(_stub_report(bounds, {}))
    assert "against their lower bounds" in text and "101.5 ms" in text
    section = text[text.index("against their lower bounds") :]
    rows = _table_rows(section[: section.index("accuracy")])
    # this run's p50 beside the recorded bound, gap = p50 / bound (24/12, 6/4, 13/6.5)
    assert rows["mim"] == ["24.0 ms", "12.0 ms", "2.0x", "OpenCV DFT"]
    assert rows["matching"] == ["6.0 ms", "4.0 ms", "1.5x", "one float32 GEMM"]
    assert rows["landscape"] == ["13.0 ms", "6.5 ms", "2.0x", "compiled"]


def test_bounds_only_for_stages_the_run_has():
    stages = {"mim": {"bound_ms": 10.0, "best_library": "cv"}, "ransac": {"bound_ms": 1.0, "best_library": "np"}}
    text = bounds_markdown({"mim": 30.0}, {"source": "x.json", "stages": stages})
    rows = _table_rows(text)
    assert set(rows) == {"mim"} and rows["mim"][:3] == ["30.0 ms", "10.0 ms", "3.0x"]


def test_a_bad_bounds_file_is_named_with_its_problem(tmp_path):
    bad = tmp_path / "b.json"
    bad.write_text(json.dumps({"stages": {"mim": {"bound_ms": -1}}}))
    with pytest.raises(ValueError, match=r"b\.json: stages\.mim\.bound_ms must be a positive number"):
        load_bounds(bad)
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="not a readable JSON file"):
        load_bounds(bad)
    bad.write_text("{}")
    with pytest.raises(ValueError, match="no 'stages' table"):
        load_bounds(bad)


def test_cli_refuses_a_bad_bounds_file_in_one_line(tmp_path):
    from bb_align.cli import app

    bad = tmp_path / "b.json"
    bad.write_text("[]")
    res = CliRunner().invoke(app, ["bench", "--no-service", "--bounds", str(bad)])
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert "--bounds" in res.output and "no 'stages' table" in res.output


def test_the_figure_draws_the_peers_curve_and_decodes(tmp_path, bounds_file):
    peers = {1: (10.0, 60.0), 4: (38.0, 80.0), 8: (52.0, 95.0), 16: (41.0, 120.0)}
    path = plot_report(_stub_report(load_bounds(bounds_file), peers), tmp_path / "bench.png")
    img = cv2.imread(str(path))
    assert img is not None and img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 600
    # three panels (two stage panels and the curve): the figure is three times as wide as the two-panel one
    two = cv2.imread(str(plot_report(_stub_report(None, {}), tmp_path / "two.png")))
    assert img.shape[1] > 1.4 * two.shape[1]
