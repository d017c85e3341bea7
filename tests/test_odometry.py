"""Is an odometry step a car's motion (engine.odometry)? Real 10 Hz poses never trip it; a relocalisation of a few
metres always does, at any speed and with dropped frames."""

from __future__ import annotations

import numpy as np
import pytest

from bb_align.engine.config import TrackConfig
from bb_align.engine.geometry import se2, se2_exp, se2_log
from bb_align.engine.odometry import OdometryWatch, odometry_jump
from bb_align.lab.real_drives import real_drives

DT = 0.1


def test_se2_exp_is_the_limit_of_small_steps_and_log_inverts_it():
    rng = np.random.default_rng(0)
    for xi in [*rng.uniform(-2, 2, (20, 3)), np.array([1e-12, 3.0, -1.0]), np.array([0.0, 0.0, 0.0])]:
        n = 20000  # brute force: the twist applied in n equal small steps
        brute = np.linalg.matrix_power(se2(*(xi / n)), n)
        np.testing.assert_allclose(se2_exp(xi), brute, atol=2e-3 * (1 + np.abs(xi).max()))
        np.testing.assert_allclose(se2_log(se2_exp(xi)), xi, atol=1e-9)


def _check(poses: list[np.ndarray], stamps, strides, cfg=None) -> list[int]:
    """Frames (index of the third pose) flagged as jumps when the track sees every s0-th then s1-th pose."""
    cfg, flagged = cfg or TrackConfig(), []
    s0, s1 = strides
    for k in range(s0 + s1, len(poses)):
        a, b = k - s0 - s1, k - s1
        if odometry_jump(cfg, [(stamps[a], poses[a]), (stamps[b], poses[b])], (stamps[k], poses[k])):
            flagged.append(k)
    return flagged


STRIDES = [(1, 1), (1, 2), (2, 1), (1, 3), (2, 2), (1, 5), (5, 5)]  # frames dropped before and between


def test_real_10hz_poses_never_trip_it(shared_data):
    # KITTI 08 (6.8 minutes of a residential drive: turns, stops, starts) and two Argoverse 2 logs, seen with frames
    # dropped as a busy service drops them.
    runs = real_drives(shared_data)
    assert len(runs["KITTI 08"][0]) == 4071 and len(runs) == 3
    for name, (poses, stamps) in runs.items():
        for strides in STRIDES:
            assert _check(poses, stamps, strides) == [], (name, strides)


def _drive(n: int, speed: float, yaw_rate_deg: float = 0.0, accel: float = 0.0) -> list[np.ndarray]:
    """A car's true poses at 10 Hz from the origin: a unicycle with constant yaw rate and acceleration."""
    out, pose, v = [], np.eye(3), speed
    for _ in range(n):
        out.append(pose)
        sub = 10  # integrate within the frame
        for _ in range(sub):
            pose = pose @ se2_exp(np.array([np.radians(yaw_rate_deg), v, 0.0]) * DT / sub)
            v = max(0.0, v + accel * DT / sub)
    return out


@pytest.mark.parametrize(
    "speed, yaw_rate_deg, accel",
    [(30.0, 0.0, 0.0), (14.0, 30.0, 0.0), (20.0, 0.0, -9.0), (0.0, 0.0, 4.0), (8.0, -40.0, -6.0)],
)
def test_a_car_driving_hard_is_motion(speed, yaw_rate_deg, accel):
    poses = _drive(40, speed, yaw_rate_deg, accel)
    stamps = np.arange(40) * DT
    for strides in STRIDES:
        assert _check(poses, stamps, strides) == [], strides


@pytest.mark.parametrize("speed", [0.0, 10.0, 30.0])
@pytest.mark.parametrize("strides", [(1, 1), (1, 2), (2, 2), (1, 3)])
def test_a_relocalisation_of_a_few_metres_is_a_jump_at_any_speed(speed, strides):
    # The tracking soak's case: the odometry re-anchored by (4, 4) m (5.7 m). With a frame dropped at 30 m/s the
    # step is 11 m in 0.2 s (57 m/s): under any speed bound, it is the acceleration that gives it away.
    poses = _drive(30, speed, 10.0)
    jumped = [se2(0.0, 4.0, 4.0) @ T if k >= 20 else T for k, T in enumerate(poses)]
    stamps = np.arange(30) * DT
    s0, s1 = strides
    flagged = _check(jumped, stamps, strides)
    # flagged on the first frame seen after the jump, and on no other where both steps are motion
    first = next(k for k in range(s0 + s1, 30) if k >= 20 and k - s1 < 20)
    assert first in flagged
    clean = [k for k in range(s0 + s1, 30) if not (k - s0 - s1 < 20 <= k)]
    assert not set(flagged) & set(clean), flagged
    # a heading reset alone (12 deg about the car) is one too
    turned = [T @ se2(np.radians(12.0), 0.0, 0.0) if k >= 20 else T for k, T in enumerate(poses)]
    assert first in _check(turned, stamps, strides)


def test_each_car_is_checked_at_its_own_frames_times():
    # The service pairs each peer frame with the nearest ego frame: at times the ego's newest frame has not landed
    # and the one before is paired again, then two ego frames pass in one peer step. On the peer's clock the ego
    # would stop dead and leap (a 1.5 m jump at 15 m/s); on its own frames' stamps it drives smoothly.
    rng = np.random.default_rng(7)
    ego, peer = _drive(60, 15.0, 5.0), _drive(60, 10.0)
    paired = [max(0, k - int(rng.integers(0, 2))) for k in range(60)]  # the ego frame paired with peer frame k
    for with_ego_stamps in (True, False):
        watch, jumps = OdometryWatch(TrackConfig()), []
        for k, e in enumerate(paired):
            poses = {"ego": ((e if with_ego_stamps else k) * DT, ego[e]), "peer": (k * DT, peer[k])}
            jump, _ = watch.check(poses)
            jumps += [k] if jump else []
            watch.record(poses, jump[0] if jump else None)
        assert (jumps == []) == with_ego_stamps, jumps
    # and the relocalisation is still seen, on the first peer step whose ego frame has it
    watch, seen_at = OdometryWatch(TrackConfig()), None
    for k, e in enumerate(paired):
        O_e = se2(0.0, 4.0, 4.0) @ ego[e] if e >= 30 else ego[e]
        poses = {"ego": (e * DT, O_e), "peer": (k * DT, peer[k])}
        if (jump := watch.check(poses)[0]) and seen_at is None:
            seen_at = (k, jump)
        watch.record(poses, jump[0] if jump else None)
    assert seen_at[0] == next(k for k, e in enumerate(paired) if e >= 30) and seen_at[1][0] == "ego", seen_at


def _stepped_every(poses: list[np.ndarray], every: int, observe: bool) -> list[tuple[int, str | None, float]]:
    """A service stepping one frame in ``every`` of one car (the others replaced unread, their odometry observed or
    not): (frame, the check's jumped car or None, its unchecked metres) at each stepped frame."""
    watch, out = OdometryWatch(TrackConfig()), []
    for k in range(0, len(poses), every):
        if observe:
            watch.observe("peer", [(j * DT, poses[j]) for j in range(max(0, k - every + 1), k)])
        now = {"peer": (k * DT, poses[k])}
        jump, unchecked_m = watch.check(now)
        out.append((k, jump[0] if jump else None, unchecked_m))
        watch.record(now, jump[0] if jump else None)
    return out


def test_observed_frames_keep_the_check_on_the_car_s_every_step():
    # A car at 25 m/s stepped once a second (nine frames in ten replaced unread by a busy service). Unobserved, each
    # step's check can vouch for no more than what 1 g allows in a second (5 m and more: the service would run the
    # full method to confirm every such frame); with the skipped frames' odometry observed, every step is a 0.1 s
    # step: the bound is the 10 Hz one (1 g over 0.1 s plus the step noise: 0.35 m).
    poses = _drive(61, 25.0, 8.0)
    blind = _stepped_every(poses, 10, observe=False)
    seen = _stepped_every(poses, 10, observe=True)
    cfg = TrackConfig()
    ten_hz = cfg.max_odometry_accel_m_s2 * DT * DT + cfg.odometry_step_noise_m
    assert all(jumped is None for _, jumped, _ in blind + seen)
    assert min(m for k, _, m in blind if k >= 20) > cfg.max_unchecked_jump_m
    assert max(m for _, _, m in seen) == pytest.approx(ten_hz)
    # a relocalisation of 3 m on a skipped frame (frame 34: the stepped frames are 30 and 40) is caught at the
    # next step, although the stepped frame itself continues the motion after the jump; unobserved it is not
    jumped = [se2(0.0, 3.0, 0.0) @ T if k >= 34 else T for k, T in enumerate(poses)]
    assert [k for k, car, _ in _stepped_every(jumped, 10, observe=True) if car] == [40]
    assert [k for k, car, _ in _stepped_every(jumped, 10, observe=False) if car] == []


def test_observed_frames_older_than_the_last_step_change_nothing():
    poses = _drive(10, 12.0)
    watch = OdometryWatch(TrackConfig())
    for k in range(6):
        watch.record({"peer": (k * DT, poses[k])})
    watch.observe("peer", [(k * DT, se2(0.0, 9.0, 0.0) @ poses[k]) for k in range(6)])  # stale, and absurd
    assert watch.check({"peer": (6 * DT, poses[6])}) == (None, pytest.approx(0.35))


def test_a_repeated_check_answers_as_a_fresh_one_until_the_watch_learns_more():
    # The track checks each frame twice with nothing recorded between; the second answer is remembered, never
    # stale: after observe or record the same poses are judged afresh (here: a jump observed in between).
    poses = _drive(10, 12.0)
    watch, fresh = OdometryWatch(TrackConfig()), OdometryWatch(TrackConfig())
    for k in range(5):
        watch.record({"peer": (k * DT, poses[k])})
        fresh.record({"peer": (k * DT, poses[k])})
    now = {"peer": (5 * DT, poses[5])}
    assert watch.check(now) == watch.check(now) == fresh.check(now) == (None, pytest.approx(0.35))
    jump = [(4.5 * DT, se2(0.0, 4.0, 0.0) @ poses[5])]
    watch.observe("peer", jump)
    fresh.observe("peer", jump)
    assert watch.check(now)[0] is not None
    assert watch.check(now) == fresh.check(now)
    watch.record(now, jumped="peer")
    assert watch.check({"peer": (6 * DT, poses[6])}) == (None, 0.0)  # one pose since the jump: speed check only
