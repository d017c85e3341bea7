"""The benchmark's baseline computes what the engine computes (only slower), and `bb-align bench` reports what it
promises. No timing is asserted here: speed numbers live in the benchmark's recorded output."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.engine.config import AlignConfig, BevConfig, FeatureConfig
from bb_align.engine.descriptors import bvft_descriptors, dominant_orientation
from bb_align.engine.geometry import pose_error, se2, transform_points_2d
from bb_align.engine.keypoints import detect_keypoints
from bb_align.engine.loggabor import maximum_index_map
from bb_align.engine.matching import match_descriptors
from bb_align.lab.bench import baseline as bl
from test_loggabor import _segments_image

CFG = AlignConfig()


@pytest.fixture(scope="module")
def small_scene():
    img = _segments_image(size=160, seed=11)
    # The engine's exact path (every scale at full resolution); its default decimates the scales, an
    # approximation measured in test_loggabor and reported by the benchmark's MIM agreement.
    mim, amp = maximum_index_map(img, CFG.mim.model_copy(update={"coarse_scales": 0}))
    return img, mim, amp


def test_mim_matches_the_engine_on_a_small_image(small_scene):
    img, mim_engine, amp_engine = small_scene
    mim_base, amp_base = bl.log_gabor_mim(img, CFG.mim)
    assert mim_base.shape == mim_engine.shape and mim_base.dtype == np.uint8
    lit = amp_base > CFG.mim.min_amplitude
    assert lit.sum() > 2000
    # complex128 vs the engine's float32 transforms: amplitudes equal to float32 precision ...
    np.testing.assert_allclose(amp_engine, amp_base, rtol=0, atol=1e-4 * amp_base.max())
    # ... so the orientation index differs only where two orientations tie to that precision.
    assert np.mean(mim_base == mim_engine) > 0.999


def test_descriptors_equal_the_engine_for_the_same_keypoints(small_scene):
    img, mim, amp = small_scene
    rc = np.argwhere(img > 0)
    rc = rc[np.random.default_rng(1).choice(len(rc), 80, replace=False)]
    exact = CFG.features.model_copy(update={"orientation_stride": 1, "window_stride": 1})  # no engine shortcuts
    d_engine = bvft_descriptors(mim, amp, rc, exact, CFG.mim.n_orient)
    d_base = bl.bvft_descriptors(mim, amp, rc, CFG.features, CFG.mim.n_orient)
    assert d_base.shape == d_engine.shape == (80, 216)
    m = dominant_orientation(mim, amp, rc, bl.descriptor_radius(CFG.features), CFG.mim.n_orient)
    assert len(set(m.tolist())) >= 6, "the keypoints cover many dominant orientations"
    # A quarter turn (m = 7) puts every sample exactly half-way between two pixels; the engine breaks those ties
    # by floating-point noise (cos(pi/2) = 6e-17), the baseline by rounding half up. Elsewhere: identical.
    tie = m == 1 + CFG.mim.n_orient // 2
    np.testing.assert_allclose(d_base[~tie], d_engine[~tie], atol=1e-6)
    if tie.any():
        assert np.min((d_base[tie] * d_engine[tie]).sum(1)) > 0.9
    np.testing.assert_allclose(
        bl.flip_180(d_base, CFG.features)[~tie], bl.flip_180(d_engine, CFG.features)[~tie], atol=1e-6
    )


def test_432_bin_descriptors_also_agree(small_scene):
    img, mim, amp = small_scene
    cfg = FeatureConfig(merge_bins=False, orientation_stride=1, window_stride=1)
    rc = np.argwhere(img > 0)[::97][:30]
    m = dominant_orientation(mim, amp, rc, bl.descriptor_radius(cfg), 12)
    keep = m != 7
    d_engine = bvft_descriptors(mim, amp, rc[keep], cfg)
    d_base = bl.bvft_descriptors(mim, amp, rc[keep], cfg)
    assert d_base.shape[1] == 432
    np.testing.assert_allclose(d_base, d_engine, atol=1e-6)


def test_fast_keypoints_are_the_engines_without_the_cap():
    from bb_align.engine.bev import make_bev
    from bb_align.lab.sim import simulate_sequence

    agent = simulate_sequence(seed=5, n_frames=1, n_agents=1)[0].agents["0"]
    img = make_bev(agent.points, BevConfig(range_m=40.0)).image
    cfg = FeatureConfig(max_keypoints=5000)
    engine = {tuple(p) for p in detect_keypoints(img, cfg)}
    base = {tuple(p) for p in bl.fast_keypoints(img, cfg)}
    assert len(engine) > 30
    # The baseline pads the image first (as the reference does): FAST's 3-px ring (and the 3x3 non-maximum
    # suppression) then sees zeros instead of nothing near the border, so only there may the two differ.
    n = img.shape[0]

    def inner(points):
        return {(r, c) for r, c in points if min(r, c) >= 4 and max(r, c) < n - 4}

    assert inner(engine) == inner(base)
    assert len(inner(engine)) > 0.8 * len(engine)


def test_brute_force_matching_equals_the_engine():
    rng = np.random.default_rng(4)
    q = rng.random((60, 216)).astype(np.float32)
    t = rng.random((90, 216)).astype(np.float32)
    q[5] = 0  # an empty descriptor never matches
    for kwargs in ({}, {"mutual": True}, {"ratio": 0.95}):
        iq_b, it_b = bl.nn_match(q, t, **kwargs)
        iq_e, it_e = match_descriptors(q, t, **kwargs)
        np.testing.assert_array_equal(iq_b, iq_e)
        np.testing.assert_array_equal(it_b, it_e)
    assert 5 not in bl.nn_match(q, t)[0]


@pytest.mark.parametrize("yaw_deg", [-163.0, 35.0, 179.0])
def test_fixed_ransac_recovers_a_known_transform(yaw_deg):
    rng = np.random.default_rng(7)
    src = rng.uniform(-60, 60, (300, 2))
    T_true = se2(np.radians(yaw_deg), 21.0, -37.0)
    dst = transform_points_2d(T_true, src) + rng.normal(0, 0.3, (300, 2))
    outlier = rng.random(300) < 0.75
    dst[outlier] = rng.uniform(-100, 100, (outlier.sum(), 2))
    T, inliers = bl.fixed_ransac(src, dst, threshold=2.0, min_sample_dist=3.0, seed=1)
    t_err, r_err = pose_error(T, T_true)
    assert t_err < 0.2 and r_err < 0.2  # the Kabsch refit, never the half-turned solution
    assert inliers[~outlier].mean() > 0.97 and (inliers & outlier).sum() <= 3


def test_ransac_without_a_valid_sample_returns_none():
    pts = np.zeros((5, 2))
    assert bl.fixed_ransac(pts, pts, threshold=2.0, min_sample_dist=3.0, iterations=50) is None
    assert bl.fixed_ransac(pts[:1], pts[:1], threshold=2.0, min_sample_dist=0.0) is None


def test_quick_bench_reports_the_promised_keys(tmp_path):
    out = tmp_path / "bench.json"
    png = tmp_path / "bench.png"
    md = tmp_path / "bench.md"
    # A 40 m BV range (200 px images) keeps the slow baseline short; everything else is the --quick run.
    res = CliRunner().invoke(
        app,
        [
            "bench",
            "--quick",
            "--no-service",
            "--runs",
            "1",
            "--range-m",
            "40",
            "--engine-threads",
            "1",
            "--json",
            str(out),
            "--plot",
            str(png),
            "--markdown",
            str(md),
        ],
    )
    assert res.exit_code == 0, res.output
    report = json.loads(out.read_text())
    for key in ("peer_vs_cached_ego_ms_p50", "peer_vs_cached_ego_ms_p90", "cold_pair_ms_p50", "cold_pair_ms_p90"):
        assert np.isfinite(report[key]) and report[key] > 0
        assert np.isfinite(report["baseline"][key]) and report["baseline"][key] > 0
    assert report["speedup"]["peer_vs_cached_ego"] > 0 and report["speedup"]["cold_pair"] > 0
    for path in ("peer_vs_cached_ego", "cold_pair"):
        table = report["stages"][path]
        for side in ("engine", "baseline"):
            assert {"decode", "mim", "keypoints", "descriptors", "matching", "ransac", "total"} <= set(table[side])
        # the stages add up to the total (the remainder is reported as 'other', never negative beyond jitter)
        eng = table["engine"]
        assert eng["other"]["p50"] > -1.0
    assert report["machine"]["cpu_count"] >= 1 and report["machine"]["numpy"] == np.__version__
    assert len(report["load_avg"]["start"]) == 3 and "commit" in report["git"]
    assert report["memory"]["engine_tracemalloc_peak_mb"]["cold_pair"] > 0
    acc = report["accuracy"]
    assert len(acc["pairs"]) == report["workload"]["pairs"] == 2
    for row in acc["pairs"]:
        assert "t_err_m" in row["engine"] and "t_err_m" in row["baseline"]  # simulated pairs carry the truth
    assert report["service"] is None
    assert report["config"]["bev"]["range_m"] == 40.0 and report["workload"]["image_px"] == [200, 200]
    assert report["config"]["mim"]["threads"] == report["config"]["features"]["threads"] == 1  # --engine-threads
    assert report["config"]["match"]["threads"] == 1
    assert png.stat().st_size > 10_000
    assert report["memory"]["process_engine_runs"]["rss_peak_mb"] > 50
    table = md.read_text()
    assert "| peer frame vs cached ego frame |" in table and "| ransac |" in table


def test_service_throughput_over_zenoh_loopback(monkeypatch):
    from bb_align.lab.bench.throughput import ServiceBenchConfig, measure_service

    # A small BV range keeps the engine quick; the measurement path is the one the full benchmark uses. Every
    # tracked frame that waited at all is answered from its track's stream while the stream can answer it (the
    # service's settings read the environment): both kinds of answer come back, none wrong.
    monkeypatch.setenv("BBALIGN_UNMEASURED_AFTER_S", "1e-6")
    config = AlignConfig(bev=BevConfig(range_m=40.0))
    sb = ServiceBenchConfig(peer_counts=[2], seconds=2.0, warmup_s=1.0, grace_s=3.0, frames=2, workers=1)
    out = measure_service(sb, config)
    assert "errors" not in out and "error" not in out, out
    run = out["runs"]["2"]
    assert run["sent"] == 2 * 20  # 2 peers x 2 s x 10 Hz
    assert run["results"] > 0 and run["results"] + run["dropped"] == run["sent"]
    assert 0 < run["latency_ms"]["p50"] <= run["latency_ms"]["p99"]
    assert run["service_frames_dropped_total"] >= 0 and sum(run["outcomes"].values()) == run["results"]
    assert run["service_memory"]["rss_peak_mb"] > 50  # the service process itself, read from /proc
    assert "queue_wait" in run["service_timings_ms_p50"]
    assert run["sources"].get("stream", 0) > 0 and run["wrong"] == 0, (run["sources"], run["wrong"])
    assert 0 < run["measured_fps"] < run["results_fps"]  # the acquisitions and tracked frames measured


def test_staggered_peers_publish_at_their_own_phases_of_the_period():
    """Unsynchronised LiDARs: 3 peers after the ego at a quarter, half and three quarters of a 100 ms period, each
    within the period and apart; phase-locked ones all at the ego's instant."""
    from bb_align.lab.bench.throughput import phases_s

    assert phases_s(3, 0.1, stagger=True) == pytest.approx([0.0, 0.025, 0.05, 0.075])
    assert phases_s(3, 0.1, stagger=False) == [0.0] * 4


def test_bench_reported_pose_noise_is_about_the_car_not_the_world_origin():
    """A car 800 m from the world origin: its reported pose is off by the configured GNSS-class error (metres
    and degrees about the car), not by the yaw error times 800 m."""
    from bb_align.engine.geometry import se3_from_se2
    from bb_align.lab.bench.throughput import ServiceBenchConfig, reported_pose

    cfg = ServiceBenchConfig(pose_sigma_m=2.0, pose_sigma_deg=2.0)
    T_world_sensor = se3_from_se2(se2(np.radians(30.0), 800.0, -600.0))
    errors = np.array(
        [pose_error(reported_pose(T_world_sensor, cfg, car, k), T_world_sensor) for car in range(4) for k in range(50)]
    )
    # Position error per axis ~N(0, 2 m): its norm is Rayleigh(2 m), P(> 10 m) = exp(-12.5) per draw.
    assert errors[:, 0].max() < 10.0
    assert 1.0 < np.median(errors[:, 0]) < 4.0  # Rayleigh median 2.35 m
    assert 0.5 < np.median(errors[:, 1]) < 3.0 and errors[:, 1].max() < 10.0  # |N(0, 2 deg)|: median 1.35
