"""A hand-built scene for the simulator's tests: an ideal sensor, two walls and one car driving between them."""

from __future__ import annotations

import numpy as np

from bb_align.lab.sim.paths import straight
from bb_align.lab.sim.sensors import SensorModel
from bb_align.lab.sim.world import Shapes, Terrain, Vehicle, World

SENSOR = SensorModel(  # four beams, no noise, no dropout
    name="ideal",
    elevations_deg=(-10.0, -5.0, 0.0, 5.0),
    columns=3600,
    max_range_m=100,
    range_noise_m=0.0,
    dropout=0.0,
    far_falloff=60.0,
    elevation_jitter_deg=0.0,
)


def walls_world(speed: float) -> World:
    """Walls facing the car at x = +10 m and x = -10 m (5 m high); the car drives along +x at ``speed``."""
    sh = Shapes()
    sh.prism(10.5, 0.0, 0.5, 30.0, 0.0, 0.0, 5.0)
    sh.prism(-10.5, 0.0, 0.5, 30.0, 0.0, 0.0, 5.0)
    terrain = Terrain(np.array([-200.0, -200.0]), 2.0, np.zeros((201, 201)), np.zeros((201, 201)))
    car = Vehicle(0, 4.5, 1.8, 1.5, "car", path=straight((-100.0, 0.0), 0.0, 200.0), s0=100.0, speed=speed)
    return World([], sh.arrays(), [car], terrain, [])
