"""A hand-built scene for the simulator's tests: two walls and one car driving between them."""

from __future__ import annotations

import numpy as np

from bb_align.lab.sim.paths import straight
from bb_align.lab.sim.world import Shapes, Terrain, Vehicle, World


def walls_world(speed: float) -> World:
    """Walls facing the car at x = +10 m and x = -10 m (5 m high); the car drives along +x at ``speed``."""
    sh = Shapes()
    sh.prism(10.5, 0.0, 0.5, 30.0, 0.0, 0.0, 5.0)
    sh.prism(-10.5, 0.0, 0.5, 30.0, 0.0, 0.0, 5.0)
    terrain = Terrain(np.array([-200.0, -200.0]), 2.0, np.zeros((201, 201)), np.zeros((201, 201)))
    car = Vehicle(0, 4.5, 1.8, 1.5, "car", path=straight((-100.0, 0.0), 0.0, 200.0), s0=100.0, speed=speed)
    return World([], sh.arrays(), [car], terrain, [])
