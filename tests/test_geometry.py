import numpy as np
import pytest

from bb_align.engine.geometry import (
    kabsch_2d,
    pose_error,
    rotation_rpy,
    se2,
    se2_params,
    se3_from_se2,
    transform_points_2d,
    wrap_angle,
)


def test_se2_round_trip_and_composition():
    T_a_b = se2(0.3, 1.0, -2.0)
    T_b_c = se2(-1.1, 4.0, 0.5)
    yaw, tx, ty = se2_params(T_a_b @ T_b_c)
    assert yaw == pytest.approx(0.3 - 1.1)
    # Hand-worked: t = R(0.3) @ (4, 0.5) + (1, -2)
    c, s = np.cos(0.3), np.sin(0.3)
    assert (tx, ty) == pytest.approx((c * 4 - s * 0.5 + 1.0, s * 4 + c * 0.5 - 2.0))


def test_kabsch_recovers_known_transform_with_noise():
    rng = np.random.default_rng(1)
    src = rng.uniform(-50, 50, (200, 2))
    T_true = se2(np.radians(137.0), -12.0, 33.0)
    dst = transform_points_2d(T_true, src) + rng.normal(0, 0.05, src.shape)
    t_err, r_err = pose_error(kabsch_2d(src, dst), T_true)
    assert t_err < 0.02 and r_err < 0.01


def test_kabsch_never_returns_the_half_turn():
    # The reference's solver returned 180-degree-wrong poses about half of the time; ours must not, at any yaw.
    rng = np.random.default_rng(2)
    src = rng.uniform(-20, 20, (10, 2))
    for yaw in np.linspace(-179, 180, 37):
        T_true = se2(np.radians(yaw), 3.0, -4.0)
        t_err, r_err = pose_error(kabsch_2d(src, transform_points_2d(T_true, src)), T_true)
        assert t_err < 1e-9 and r_err < 1e-9


def test_eq1_rotation_matches_independent_composition():
    roll, pitch, yaw = 0.02, -0.03, 1.2
    Rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    Ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    np.testing.assert_allclose(rotation_rpy(roll, pitch, yaw), Rz @ Ry @ Rx, atol=1e-12)
    T = se3_from_se2(se2(yaw, 5.0, 6.0), tz=0.4, roll=roll, pitch=pitch)
    np.testing.assert_allclose(T[:3, 3], [5.0, 6.0, 0.4])
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_wrap_angle():
    np.testing.assert_allclose(
        wrap_angle(np.array([np.pi, -np.pi, 3 * np.pi, 0.1 - 2 * np.pi])), [np.pi, np.pi, np.pi, 0.1], atol=1e-12
    )
