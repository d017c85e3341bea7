import numpy as np

from bb_align.engine.config import RansacConfig
from bb_align.engine.geometry import pose_error, se2, transform_points_2d
from bb_align.engine.matching import match_descriptors
from bb_align.engine.ransac import rigid_ransac


def _correspondences(n=300, outlier_frac=0.8, seed=0, yaw_deg=-163.0):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-60, 60, (n, 2))
    T_true = se2(np.radians(yaw_deg), 21.0, -37.0)
    dst = transform_points_2d(T_true, src) + rng.normal(0, 0.3, (n, 2))
    out = rng.random(n) < outlier_frac
    dst[out] = rng.uniform(-100, 100, (out.sum(), 2))
    return src, dst, T_true, ~out


def test_recovers_known_transform_with_80_percent_outliers():
    src, dst, T_true, good = _correspondences()
    fit = rigid_ransac(src, dst, RansacConfig(inlier_threshold_m=2.0, min_sample_dist_m=3.0), seed=3)
    t_err, r_err = pose_error(fit.T_dst_src, T_true)
    assert t_err < 0.15 and r_err < 0.15
    # Inliers are the true correspondences (a random outlier may land within 2 m by chance).
    assert fit.inliers[good].mean() > 0.97
    assert (fit.inliers & ~good).sum() <= 3
    assert fit.ambiguity < 0.3


def test_seeded_and_reproducible():
    src, dst, _, _ = _correspondences(seed=5)
    a = rigid_ransac(src, dst, RansacConfig(min_sample_dist_m=0.0), seed=11)
    b = rigid_ransac(src, dst, RansacConfig(min_sample_dist_m=0.0), seed=11)
    np.testing.assert_array_equal(a.T_dst_src, b.T_dst_src)
    assert a.iterations == b.iterations


def test_adaptive_iterations_stop_early_on_clean_data():
    src, dst, T_true, _ = _correspondences(outlier_frac=0.0)
    fit = rigid_ransac(src, dst, RansacConfig(min_sample_dist_m=0.0, min_iterations=100, max_iterations=10000))
    assert fit.iterations < 1000
    assert pose_error(fit.T_dst_src, T_true)[0] < 0.1


def test_two_equally_supported_poses_are_flagged_ambiguous():
    rng = np.random.default_rng(0)
    src = rng.uniform(-50, 50, (200, 2))
    dst = np.empty_like(src)
    dst[:100] = transform_points_2d(se2(0.5, 10, 0), src[:100])
    dst[100:] = transform_points_2d(se2(0.5 + np.pi, -10, 5), src[100:])  # a half-turn look-alike
    fit = rigid_ransac(src, dst, RansacConfig(inlier_threshold_m=1.0, min_sample_dist_m=0.0))
    assert fit.ambiguity > 0.8


def test_degenerate_inputs():
    assert rigid_ransac(np.zeros((1, 2)), np.zeros((1, 2)), RansacConfig(inlier_threshold_m=1.0)) is None
    same = np.zeros((10, 2))
    assert rigid_ransac(same, same, RansacConfig(inlier_threshold_m=1.0, min_sample_dist_m=1.0)) is None


def test_matching_nearest_mutual_ratio():
    q = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 0]], np.float32)
    t = np.array([[0.9, 0.1, 0], [0, 1, 0], [0.8, 0.2, 0]], np.float32)
    iq, it = match_descriptors(q, t)
    assert iq.tolist() == [0, 1] and it.tolist() == [0, 1]  # the empty query never matches
    iq, it = match_descriptors(q, t, ratio=0.4)  # query 0: 0.14 vs 0.28 to its runner-up -> dropped
    assert iq.tolist() == [1]
    iq, it = match_descriptors(np.array([[1, 0, 0], [0.95, 0.05, 0]], np.float32), t[:1], mutual=True)
    assert iq.tolist() == [1]  # t[0] is nearer query 1 (0.07) than query 0 (0.14): only 1 is mutual


def test_matching_in_query_blocks_equals_brute_force():
    """Threaded blocks of query rows give each query's true nearest neighbour (checked one query at a time)."""
    rng = np.random.default_rng(4)
    q = rng.random((101, 16)).astype(np.float32)
    t = rng.random((57, 16)).astype(np.float32)
    truth = np.array([np.argmin(((t - row) ** 2).sum(1)) for row in q])
    for threads in (1, 2, 3):
        iq, it = match_descriptors(q, t, threads=threads)
        assert iq.tolist() == list(range(101)) and it.tolist() == truth.tolist()


def test_prior_gating_keeps_consistent_candidates_only():
    from bb_align.engine.matching import match_with_prior

    xy_q = np.array([[10.0, 0.0], [0.0, 30.0]])
    xy_t = np.array([[10.5, 0.2], [40.0, 40.0], [0.3, 30.2], [-50.0, 0.0]])
    # Query 0 is nearest (in descriptor space) to train 1, then train 0; query 1 to train 3, then train 2.
    q = np.array([[1, 0, 0, 0], [0, 0, 1, 0]], np.float32)
    t = np.array([[0.9, 0.1, 0, 0], [1, 0, 0, 0], [0, 0, 0.9, 0.1], [0, 0, 1, 0]], np.float32)
    i_q, i_t = match_with_prior(q, t, xy_q, xy_t, np.eye(3), max_translation=2.0, max_yaw_rad=np.radians(2), top_k=2)
    assert sorted(zip(i_q.tolist(), i_t.tolist())) == [(0, 0), (1, 2)]
    i_q, _ = match_with_prior(q, t, xy_q, xy_t, np.eye(3), max_translation=2.0, max_yaw_rad=0.01, top_k=1)
    assert len(i_q) == 0  # the single nearest candidates are both inconsistent with the prior
