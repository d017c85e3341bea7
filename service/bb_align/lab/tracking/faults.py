"""Odometry faults for probing a track: a car's odometry re-anchored (a relocalisation, a reset) or drifting away
on purpose (a peer lying about its own motion), from a given frame on.

    fault = OdometryFault.parse("ego:15:4,4")         # the ego's odometry re-anchored by (4, 4) m from frame 15
    O_sent = fault.apply("ego", i, O_odom_sensor)      # what the car sends at frame i (4x4)

A jump moves the car's odometry frame: every later pose is ``se2(0, dx, dy) @ O`` (as a relocalisation shifts
every later pose by the same correction). A lie (``ramp``) grows the shift by (dx, dy) each frame from the first
one on: a steady false velocity, each step far below any jump detector.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bb_align.engine.geometry import se2, se3_from_se2


@dataclass(frozen=True)
class OdometryFault:
    car: str  # the sender's name (the ego's id or a peer's)
    from_frame: int
    dx: float
    dy: float
    ramp: bool = False  # a lie: the shift grows by (dx, dy) per frame

    @classmethod
    def parse(cls, text: str, ramp: bool = False) -> OdometryFault:
        """``CAR:FRAME:DX,DY`` (metres), e.g. ``ego:15:4,4``; ValueError naming what is wrong."""
        parts = text.split(":")
        if len(parts) != 3:
            raise ValueError(f"odometry fault {text!r}: expected CAR:FRAME:DX,DY (e.g. ego:15:4,4)")
        car, frame, shift = parts
        try:
            first = int(frame)
            dx, dy = (float(v) for v in shift.split(","))
        except ValueError:
            raise ValueError(f"odometry fault {text!r}: FRAME is an integer, DX,DY two numbers in metres") from None
        if first < 0 or not np.isfinite([dx, dy]).all():
            raise ValueError(f"odometry fault {text!r}: FRAME must be >= 0 and DX, DY finite")
        return cls(car, first, dx, dy, ramp)

    def shift(self, car: str, frame: int) -> tuple[float, float]:
        """The (dx, dy) in the car's odometry frame applied at ``frame``."""
        if car != self.car or frame < self.from_frame:
            return 0.0, 0.0
        k = frame - self.from_frame + 1 if self.ramp else 1
        return k * self.dx, k * self.dy

    def apply(self, car: str, frame: int, O: np.ndarray) -> np.ndarray:
        """The odometry pose (4x4 T_odom_sensor) the car sends at ``frame``."""
        dx, dy = self.shift(car, frame)
        if dx == 0.0 and dy == 0.0:
            return O
        return se3_from_se2(se2(0.0, dx, dy)) @ np.asarray(O, dtype=float)
