"""The simulator's realism statistics on hand-built scenes whose answer is known."""

from __future__ import annotations

import numpy as np

from bb_align.lab.sim.realism import landscape_at_truth


def _scene(cross_walls_x: tuple[float, ...]) -> np.ndarray:
    """A flat street between two 4 m facades at y = +-8 m running far beyond both sensors' range, and optional side
    walls (facades of side streets) across y = 8-20 m at the given x; points every 0.2 m, ground every metre."""
    g = np.arange(-100.0, 100.0, 1.0)
    gx, gy = np.meshgrid(g, g)
    parts = [np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)]
    u, z = np.meshgrid(np.arange(-250.0, 250.0, 0.2), np.arange(0.4, 4.0, 0.4))
    for y in (-8.0, 8.0):
        parts.append(np.stack([u.ravel(), np.full(u.size, y), z.ravel()], 1))
    v, z = np.meshgrid(np.arange(8.0, 20.0, 0.2), np.arange(0.4, 4.0, 0.4))
    for x in cross_walls_x:
        parts.append(np.stack([np.full(v.size, x), v.ravel(), z.ravel()], 1))
    return np.concatenate(parts).astype(np.float32)


def test_landscape_at_truth_sees_a_corridor_only_where_nothing_crosses_the_street():
    """The peer 20 m ahead of the ego on the same street (T_ego_peer a pure shift): with nothing across the street
    the images cannot say where along it the peer is (a corridor), nor can one short side wall (its few pixels barely
    move the score); four side walls across it pin the pose along the street."""
    T_ego_peer = np.eye(4)
    T_ego_peer[0, 3] = 20.0

    def pair(walls):
        scene = _scene(walls)
        return scene, scene - np.array([20.0, 0.0, 0.0], np.float32)

    bounded, sigma = landscape_at_truth(*pair(()), T_ego_peer)
    assert not bounded and sigma == np.inf
    assert not landscape_at_truth(*pair((7.0,)), T_ego_peer)[0]
    bounded, sigma = landscape_at_truth(*pair((-23.0, 7.0, 31.0, 44.0)), T_ego_peer)
    assert bounded and sigma < 1.0  # 0.43 m here: within the engine's default 1 m answer bound
