"""The stream's evidence (bb_align.engine.evidence) and the answer rule's probability, against hand-worked values,
brute force and simulated truths with a known correlation between frames."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, stats

from bb_align.engine.covariance import probability_in_disc, probability_within
from bb_align.engine.evidence import OffsetSample, SharedError, StreamEvidence
from bb_align.engine.geometry import log_left, se2

CHI2_3_95 = stats.chi2.ppf(0.95, 3)
NO_DRIFT = np.zeros((3, 3))


@pytest.mark.parametrize("sx, sy, rho", [(0.5, 0.3, 0.0), (0.85, 0.3, 0.4), (0.2, 0.2, 0.0), (1.0, 0.05, -0.3)])
def test_disc_probability_matches_a_two_dimensional_integral(sx, sy, rho):
    cov = np.array([[sx**2, rho * sx * sy], [rho * sx * sy, sy**2]])
    pdf = stats.multivariate_normal(np.zeros(2), cov).pdf
    brute, _ = integrate.dblquad(
        lambda y, x: pdf([x, y]), -1.0, 1.0, lambda x: -np.sqrt(1 - x * x), lambda x: np.sqrt(1 - x * x)
    )
    assert probability_in_disc(cov, 1.0) == pytest.approx(brute, abs=1e-6)


def test_probability_within_is_a_lower_bound_on_the_joint_probability():
    """Monte Carlo of a covariance with yaw and position strongly correlated: the product of the marginals (the
    Gaussian correlation inequality) never exceeds the joint share, and is close to it when they are independent."""
    rng = np.random.default_rng(0)
    s = np.array([np.radians(0.6), 0.6, 0.3])
    for corr in (0.0, 0.9):
        C = np.diag(s) @ np.array([[1, corr, 0], [corr, 1, 0], [0, 0, 1]]) @ np.diag(s)
        e = rng.multivariate_normal(np.zeros(3), C, size=400_000)
        joint = np.mean((np.abs(e[:, 0]) <= np.radians(1.0)) & (np.hypot(e[:, 1], e[:, 2]) <= 1.0))
        p = probability_within(C, 1.0, 1.0)
        assert p <= joint + 3e-3
        if corr == 0.0:
            assert p == pytest.approx(joint, abs=3e-3)


def _stream(rho=0.0, window_s=1.0, max_frames=10):
    return StreamEvidence(window_s, max_frames, rho, gate_chi2=16.27)


def test_equal_frames_fuse_to_their_mean_with_the_design_effect():
    """Hand-worked: four frames 0.1 s apart, equal covariance C, offsets 0, 0.1, 0.2, 0.3 m along x from X0: the
    fused offset is their mean, 0.15 m; its covariance C / 4 x (1 + rho x 3)."""
    C = np.diag([np.radians(0.3) ** 2, 0.5**2, 0.3**2])
    X0 = se2(0.2, 50.0, 3.0)
    for rho in (0.0, 0.5, 0.9):
        ev = _stream(rho)
        for k in range(4):
            ev.add(OffsetSample(0.1 * k, se2(0.0, 0.1 * k, 0.0) @ X0, C, NO_DRIFT))
        f = ev.fused(0.3)
        assert f.frames == 4
        np.testing.assert_allclose(log_left(f.X, X0), [0.0, 0.15, 0.0], atol=1e-9)
        np.testing.assert_allclose(f.covariance, C / 4 * (1 + 3 * rho), rtol=1e-9)


def test_frames_that_share_their_errors_must_agree_more_closely():
    """Hand-worked: two frames 0.95 m apart along x with 1-sigma 0.5 m: assumed independent they agree (their
    difference has variance 0.25 + 0.25, d2 1.8); with rho 0.9 the difference's variance is a tenth of that (d2
    18 > 16.27): the older frame is not evidence about the newer one's pose."""
    C = np.diag([np.radians(0.3) ** 2, 0.5**2, 0.3**2])
    X0 = se2(0.0, 60.0, 0.0)
    for rho, frames in ((0.0, 2), (0.9, 1)):
        ev = _stream(rho)
        ev.add(OffsetSample(0.0, X0, C, NO_DRIFT))
        ev.add(OffsetSample(0.1, se2(0.0, 0.95, 0.0) @ X0, C, NO_DRIFT))
        assert ev.fused(0.1).frames == frames


def test_an_odometry_that_drifts_does_not_drag_the_answer_behind():
    """A peer whose odometry drifts 0.3 m a frame (it lies, or it is broken): each frame's own measurement of the
    offset is right for its moment. With rho 0.9 the window keeps the newest two or three frames, so the answer
    stays within a frame's drift of the newest; a window of ten would lag it by 1.35 m."""
    C = np.diag([np.radians(0.3) ** 2, 0.4**2, 0.3**2])
    X0 = se2(0.1, 75.0, -2.0)
    ev = _stream(0.9)
    for k in range(10):
        ev.add(OffsetSample(0.1 * k, se2(0.0, 0.3 * k, 0.0) @ X0, C, NO_DRIFT))
    f = ev.fused(0.9)
    assert f.frames <= 3
    assert abs(log_left(f.X, se2(0.0, 2.7, 0.0) @ X0)[1]) <= 0.3


def test_a_frame_older_than_the_window_or_a_disagreement_is_not_evidence():
    C = np.diag([np.radians(0.2) ** 2, 0.2**2, 0.2**2])
    X0 = se2(0.0, 70.0, 0.0)
    ev = _stream()
    for k in range(5):  # the peer's odometry was re-anchored 3 m before frame 5: the old frames disagree
        ev.add(OffsetSample(0.1 * k, X0, C, NO_DRIFT))
    for k in range(5, 8):
        ev.add(OffsetSample(0.1 * k, se2(0.0, 3.0, 0.0) @ X0, C, NO_DRIFT))
    f = ev.fused(0.7)
    assert f.frames == 3 and len(ev.samples) == 3
    np.testing.assert_allclose(log_left(f.X, X0), [0.0, 3.0, 0.0], atol=1e-9)
    assert ev.fused(0.7 + 1.01) is None  # all older than window_s


def test_drift_weighs_older_frames_less():
    """Two frames 1 s apart: the older one's covariance has grown by the drift rate times its age."""
    C = np.diag([1e-6, 0.1**2, 0.1**2])
    drift = np.diag([0.0, 0.1**2, 0.1**2])  # per second
    ev = _stream(window_s=2.0)
    X0 = se2(0.0, 60.0, 0.0)
    ev.add(OffsetSample(0.0, se2(0.0, 0.3, 0.0) @ X0, C, drift))
    ev.add(OffsetSample(1.0, X0, C, drift))
    f = ev.fused(1.0)
    # Weights 1 / (0.01 + 0.01) and 1 / 0.01: the fused x is 0.3 x 1/3 = 0.1 m from X0.
    assert log_left(f.X, X0)[1] == pytest.approx(0.1, abs=1e-9)


@pytest.mark.parametrize("rho_true", [0.3, 0.7])
def test_fused_covariance_covers_errors_that_repeat_from_frame_to_frame(rho_true):
    """Frames whose errors share a common part (correlation rho_true between any two, as the same buildings give):
    with the true rho the fused error lies inside the 95 % ellipsoid 95 % of the time; assumed independent
    (rho 0) the fusion is over-confident."""
    rng = np.random.default_rng(int(rho_true * 10))
    C = np.diag([np.radians(0.4) ** 2, 0.5**2, 0.3**2])
    L, X0, n, trials = np.linalg.cholesky(C), se2(0.1, 75.0, -2.0), 10, 1500
    inside = {rho_true: 0, 0.0: 0}
    for _ in range(trials):
        common = rng.normal(size=3)
        streams = {rho: _stream(rho) for rho in inside}
        for k in range(n):
            e = L @ (np.sqrt(rho_true) * common + np.sqrt(1 - rho_true) * rng.normal(size=3))
            for ev in streams.values():
                ev.add(OffsetSample(0.1 * k, se2(*e) @ X0, C, NO_DRIFT))
        for rho, ev in streams.items():
            f = ev.fused(0.1 * (n - 1))
            d = log_left(f.X, X0)
            inside[rho] += float(d @ np.linalg.solve(f.covariance, d)) <= CHI2_3_95
    assert inside[rho_true] / trials == pytest.approx(0.95, abs=0.02)
    assert inside[0.0] / trials < 0.8


def test_covariances_wider_than_the_errors_share_less_in_their_own_units():
    """Frames whose stated covariance is twice their errors' sigma (as the landscape's are, docs/calibration.md) and
    whose errors correlate 0.8: in the stated covariance's units two frames share 0.8 / 4 = 0.2, and fused with
    rho 0.2 the error still lies inside its 95 % ellipsoid at least 95 % of the time (Monte Carlo); the agreement
    gate is a separate share, here the stated covariances' whole."""
    rng = np.random.default_rng(3)
    C = np.diag([np.radians(0.6) ** 2, 1.0**2, 0.5**2])  # stated
    L_true, X0, n, trials, corr = np.linalg.cholesky(C / 4.0), se2(0.0, 80.0, 1.0), 10, 1500, 0.8
    inside = 0
    for _ in range(trials):
        common, ev = rng.normal(size=3), StreamEvidence(1.0, 10, corr / 4.0, gate_chi2=16.27, agreement=1.0)
        for k in range(n):
            e = L_true @ (np.sqrt(corr) * common + np.sqrt(1 - corr) * rng.normal(size=3))
            ev.add(OffsetSample(0.1 * k, se2(*e) @ X0, C, NO_DRIFT))
        f = ev.fused(0.1 * (n - 1))
        assert f.frames == n
        d = log_left(f.X, X0)
        inside += float(d @ np.linalg.solve(f.covariance, d)) <= CHI2_3_95
    assert inside / trials >= 0.95


def test_the_agreement_share_is_its_own_setting():
    """Hand-worked: two frames 0.95 m apart along x, 1-sigma 0.5 m, nothing shared (rho 0) but asked to agree
    within a tenth of their covariances: d2 = 0.95^2 / (0.1 x 0.5) = 18 > 16.27, the older frame is dropped."""
    C = np.diag([np.radians(0.3) ** 2, 0.5**2, 0.3**2])
    X0 = se2(0.0, 60.0, 0.0)
    for agreement, frames in ((1.0, 2), (0.1, 1)):
        ev = StreamEvidence(1.0, 10, 0.0, gate_chi2=16.27, agreement=agreement)
        ev.add(OffsetSample(0.0, X0, C, NO_DRIFT))
        ev.add(OffsetSample(0.1, se2(0.0, 0.95, 0.0) @ X0, C, NO_DRIFT))
        assert ev.fused(0.1).frames == frames


def test_shared_error_decays_with_what_the_cars_moved():
    """Hand-worked: near 0.6 within 10 m, then 0.2 + 0.4 exp(-(d - 10) / 10): 0.6 at 0 and 10 m, 0.2 + 0.4 / e at
    20 m, 0.2 far away; without a far value, 0.6 everywhere."""
    m = SharedError(0.6, 0.2, 10.0, 10.0)
    np.testing.assert_allclose(m.rho(np.array([0.0, 10.0, 20.0, 1e4])), [0.6, 0.6, 0.2 + 0.4 / np.e, 0.2])
    np.testing.assert_allclose(SharedError(0.6).rho(np.array([0.0, 1e4])), [0.6, 0.6])
    # The larger of the two cars' moves counts: the ego stood still, the peer moved 20 m.
    places = [np.array([[0.0, 0.0], [5.0, 0.0]]), np.array([[0.0, 0.0], [5.0, 20.0]])]
    assert m.matrix(places)[0, 1] == pytest.approx(0.2 + 0.4 / np.e)


def test_unequal_frames_fuse_by_the_sandwich():
    """Brute force: two frames, covariances C1 and C2 = 4 C1, errors sharing rho in their own units; the
    information-weighted estimate's covariance, sampled, matches the fused one (not the equal-weight design
    effect, which is wider for unequal frames), and the fused one is never finer than the independent fusion."""
    rng = np.random.default_rng(5)
    C1 = np.diag([np.radians(0.3) ** 2, 0.4**2, 0.2**2])
    C2, rho, X0 = 4.0 * C1, 0.5, se2(0.05, 70.0, 1.0)
    S1, S2 = np.linalg.cholesky(C1), np.linalg.cholesky(C2)
    ev = StreamEvidence(1.0, 10, rho, gate_chi2=16.27, agreement=1.0)
    ev.add(OffsetSample(0.0, X0, C1, NO_DRIFT))
    ev.add(OffsetSample(0.1, X0, C2, NO_DRIFT))
    f = ev.fused(0.1)
    z1 = rng.normal(size=(200_000, 3))
    z2 = rho * z1 + np.sqrt(1 - rho**2) * rng.normal(size=(200_000, 3))  # E[z1 z2^T] = rho I
    W1, W2 = np.linalg.inv(C1), np.linalg.inv(C2)
    P = np.linalg.inv(W1 + W2)
    est = (z1 @ S1.T @ W1.T + z2 @ S2.T @ W2.T) @ P.T
    sampled = np.cov(est.T)
    np.testing.assert_allclose(np.diag(f.covariance), np.diag(sampled), rtol=0.02)
    scale = np.sqrt(np.outer(np.diag(sampled), np.diag(sampled)))
    np.testing.assert_allclose(f.covariance / scale, sampled / scale, atol=0.01)  # off-diagonal: 0 both
    assert np.all(np.linalg.eigvalsh(f.covariance - P) >= -1e-15)
    assert np.all(np.diag(f.covariance) < np.diag(P * (1 + rho)))


def test_frames_from_places_apart_accumulate_and_still_cover_their_errors():
    """Simulated truth: a car pair moving 2 m a frame, each frame's error shares 0.6 with the frames of its 10 m
    stretch of road and nothing with the others (a common part per stretch); 40 frames fused with the place model
    (near 0.6, far 0.2) keep the 95 % promise and are a third sharper than the same frames fused as if taken in one
    place (rho 0.6 throughout, which can never be worth more than 1 / 0.6 frames)."""
    rng = np.random.default_rng(11)
    C = np.diag([np.radians(0.5) ** 2, 0.5**2, 0.4**2])
    L, X0, n, trials = np.linalg.cholesky(C), se2(0.0, 90.0, 0.0), 40, 600
    model = SharedError(0.6, 0.2, 10.0, 10.0)
    inside, var_place, var_same = 0, [], []
    for _ in range(trials):
        stretches = rng.normal(size=(n // 5 + 1, 3))
        by_place = StreamEvidence(5.0, 50, model, gate_chi2=16.27, agreement=1.0)
        same = StreamEvidence(5.0, 50, 0.6, gate_chi2=16.27, agreement=1.0)
        for k in range(n):
            e = L @ (np.sqrt(0.6) * stretches[k // 5] + np.sqrt(0.4) * rng.normal(size=3))
            places = np.array([[2.0 * k, 0.0], [2.0 * k + 90.0, 0.0]])
            for ev in (by_place, same):
                ev.add(OffsetSample(0.1 * k, se2(*e) @ X0, C, NO_DRIFT, places))
        f, g = by_place.fused(0.1 * (n - 1)), same.fused(0.1 * (n - 1))
        d = log_left(f.X, X0)
        inside += float(d @ np.linalg.solve(f.covariance, d)) <= CHI2_3_95
        var_place.append(f.covariance[1, 1])
        var_same.append(g.covariance[1, 1])
    assert inside / trials >= 0.95
    assert np.median(var_place) < 2.0 / 3.0 * np.median(var_same)
