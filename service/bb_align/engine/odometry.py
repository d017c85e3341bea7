"""Is an odometry step a car's motion? A relocalisation or reset moves a car's odometry pose by metres in one frame
while its frames say nothing of it; a track predicting from it would refine from a stale pose.

Two bounds, per car. Against the car's recent motion (its last two poses): the step must be the recent twist
(speed and yaw rate, an arc) continued, within what an acceleration a car's tyres allow (about 1 g) and the
odometry's own step noise can change; a relocalisation of a few metres breaks it whatever the car's speed. With
one earlier pose only: no faster than any road car drives or turns.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Sequence

import numpy as np

from .config import TrackConfig
from .geometry import se2_exp, se2_log, se2_params, wrap_angle

Pose = tuple[float, np.ndarray]  # (stamp s of the car's own frame, its 3x3 odometry pose)


def odometry_jump(cfg: TrackConfig, seen: Sequence[Pose], now: Pose, car: str = "car") -> str | None:
    """Why one car's odometry pose ``now`` cannot follow from its earlier frames' ``seen`` (oldest first; the last
    two are used) by the car's motion, if so: a relocalisation or reset. Times are the car's own frames' stamps."""
    return judge_step(cfg, seen, now, car)[0]


def judge_step(cfg: TrackConfig, seen: Sequence[Pose], now: Pose, car: str = "car") -> tuple[str | None, float]:
    """``odometry_jump``'s verdict, and the largest relocalisation (m) the step's check could take for motion (0
    when only the speed check ran: less than two earlier poses, or the acceleration check off)."""
    if not seen or now[0] <= seen[-1][0]:
        return None, 0.0
    (t0, O0), (t1, O1) = seen[-1], now
    dt1 = t1 - t0
    yaw, tx, ty = se2_params(np.linalg.inv(O0) @ O1)
    speed, rate = np.hypot(tx, ty) / dt1, abs(np.degrees(wrap_angle(yaw))) / dt1
    if speed > cfg.max_odometry_speed_m_s or rate > cfg.max_odometry_yaw_rate_deg_s:
        return f"the {car}'s odometry jumped ({np.hypot(tx, ty):.1f} m, {np.degrees(yaw):.1f} deg in {dt1:.2f} s)", 0.0
    if len(seen) < 2 or cfg.max_odometry_accel_m_s2 is None:
        return None, 0.0
    off_m, off_deg, bound_m, bound_deg = motion_residual(cfg, seen[-2], seen[-1], now)
    if off_m > bound_m or off_deg > bound_deg:
        why = (
            f"the {car}'s odometry jumped ({off_m:.1f} m, {off_deg:.1f} deg off its motion in {dt1:.2f} s; a car "
            f"accelerates {bound_m:.2f} m, {bound_deg:.1f} deg at most)"
        )
        return why, bound_m
    return None, bound_m


class OdometryWatch:
    """Each car's last two odometry poses, each at its own frame's stamp: is the cars' next pose their motion?

    A car's frame seen again (the ego frame of the last peer frame, paired once more) adds nothing; a jump, a frame
    older than the last or a stream without odometry starts that car's motion afresh. Frames not stepped (a busy
    service replaced them unread) are ``observe``d: the next step is then judged against 0.1 s of motion, not the
    whole gap, and a jump among them is reported by the next ``check``."""

    def __init__(self, cfg: TrackConfig):
        self.cfg = cfg
        self.seen: dict[str, deque[Pose]] = {}
        # per car, since its last recorded step: a jump among the observed frames, the largest unchecked step (m)
        self.observed: dict[str, tuple[str | None, float]] = {}
        # the last check's poses and verdict: a tracked frame is checked twice with nothing recorded between (the
        # follower's stream memory, then the track's step); observe and record forget it
        self._checked: tuple[tuple, tuple] | None = None

    def observe(self, car: str, poses: Iterable[Pose]) -> None:
        """The odometry of ``car``'s frames that will not be stepped, oldest first (those not newer than the last
        one seen are ignored): each judged as a step, a jump remembered until the next step records."""
        self._checked = None
        for stamp, O in poses:
            seen = self.seen.setdefault(car, deque(maxlen=2))
            if seen and stamp <= seen[-1][0]:
                continue
            why, bound_m = judge_step(self.cfg, seen, (stamp, O), car)
            jumped, unchecked_m = self.observed.get(car, (None, 0.0))
            self.observed[car] = (jumped or why, max(unchecked_m, bound_m))
            if why:
                seen.clear()
            seen.append((stamp, np.asarray(O, float)))

    def last_stamp(self, car: str) -> float | None:
        """The stamp of ``car``'s latest pose seen (stepped or observed), None before any."""
        seen = self.seen.get(car)
        return seen[-1][0] if seen else None

    def check(self, poses: dict[str, Pose]) -> tuple[tuple[str, str] | None, float]:
        """((car, why) when a car's pose in ``poses`` ({car: (stamp, pose)}) is a jump, else None; the largest
        relocalisation (m) the check could have taken for motion: after a long gap the acceleration a car may have
        used grows with its square). Nothing is recorded."""
        key = tuple((car, t, np.asarray(O, float).tobytes()) for car, (t, O) in poses.items())
        if self._checked is not None and self._checked[0] == key:
            return self._checked[1]
        self._checked = (key, verdict := self._check(poses))
        return verdict

    def _check(self, poses: dict[str, Pose]) -> tuple[tuple[str, str] | None, float]:
        unchecked_m = 0.0
        for car, now in poses.items():
            why, bound_m = judge_step(self.cfg, self.seen.get(car, ()), now, car)
            jumped, observed_m = self.observed.get(car, (None, 0.0))
            bound_m = max(bound_m, observed_m)
            if jumped or why:
                return (car, jumped or why), bound_m
            unchecked_m = max(unchecked_m, bound_m)
        return None, unchecked_m

    def record(self, poses: dict[str, Pose] | None, jumped: str | None = None) -> None:
        """Keep ``poses`` as the cars' latest; the car that ``jumped`` starts its motion afresh; None (a frame
        without odometry): every car does."""
        self._checked = None
        if poses is None:
            self.seen.clear()
            self.observed.clear()
            return
        for car, (stamp, O) in poses.items():
            self.observed.pop(car, None)
            seen = self.seen.setdefault(car, deque(maxlen=2))
            if seen and stamp == seen[-1][0]:
                continue
            if car == jumped or (seen and stamp < seen[-1][0]):
                seen.clear()
            seen.append((stamp, np.asarray(O, float)))


def motion_residual(cfg: TrackConfig, before: tuple, prev: tuple, now: tuple) -> tuple[float, float, float, float]:
    """One car's step prev -> now against the twist of before -> prev continued (each a (stamp, 3x3 pose)): its
    residual (m, deg) and what the bounded acceleration (over the two steps' mid-times) and the step noise allow."""
    (tb, Ob), (t0, O0), (t1, O1) = before, prev, now
    dt0, dt1 = max(t0 - tb, 1e-3), max(t1 - t0, 1e-3)
    twist = se2_log(np.linalg.inv(Ob) @ O0) / dt0
    yaw, rx, ry = se2_params(np.linalg.inv(se2_exp(twist * dt1)) @ np.linalg.inv(O0) @ O1)
    reach = dt1 * (dt0 + dt1) / 2.0  # the change of the mean velocity between the two steps, per unit acceleration
    return (
        float(np.hypot(rx, ry)),
        abs(float(np.degrees(wrap_angle(yaw)))),
        cfg.max_odometry_accel_m_s2 * reach + cfg.odometry_step_noise_m,
        cfg.max_odometry_yaw_accel_deg_s2 * reach + cfg.odometry_step_noise_deg,
    )
