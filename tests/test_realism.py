"""The simulator's realism statistics on hand-built scenes whose answer is known."""

from __future__ import annotations

import numpy as np

from bb_align.engine.config import BevConfig
from bb_align.lab.sim.realism import LATERAL_BANDS, landscape_at_truth, shared_by_lateral


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


def test_shared_by_lateral_counts_what_only_one_car_sees():
    """The peer 40 m ahead on the street between two facades at 8 m: the facades between the cars (20-60 m from the
    peer towards the ego) lie in the 7-10 m band and both cars see them (shared 1). A wall only the peer's cloud has,
    25 m from the street's axis between the cars, is in the 20-40 m band, shared by nobody; the ego has no pixel
    there. Nothing lies in the bands between."""
    T_ego_peer = np.eye(4)
    T_ego_peer[0, 3] = 40.0
    scene = _scene(())
    v, z = np.meshgrid(np.arange(-5.0, 15.0, 0.2), np.arange(0.4, 4.0, 0.4))  # world x -5..15: 25-45 m from the peer
    only_peer = np.stack([v.ravel(), np.full(v.size, 25.0), z.ravel()], 1).astype(np.float32)
    pts_peer = np.concatenate([scene, only_peer]) - np.array([40.0, 0.0, 0.0], np.float32)
    rows = shared_by_lateral(scene, pts_peer, T_ego_peer)
    by_band = {tuple(r["band_m"]): r for r in rows}
    assert [tuple(r["band_m"]) for r in rows] == [tuple(b) for b in LATERAL_BANDS]
    facade, lone = by_band[(7, 10)], by_band[(20, 40)]
    assert facade["peer_px"] > 100 and facade["shared"] == 1.0 and facade["ego_px"] == facade["peer_px"]
    res = BevConfig().resolution_m
    assert lone["peer_px"] == round(20.0 / res)  # 20 m of wall, one pixel wide
    assert lone["shared"] == 0.0 and lone["ego_px"] == 0
    for band in ((0, 4), (4, 7), (10, 14), (14, 20)):
        assert by_band[band]["peer_px"] == by_band[band]["ego_px"] == 0


def _alias_anatomy():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "alias_anatomy.py"
    spec = importlib.util.spec_from_file_location("bench_alias_anatomy_t", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_alias_anatomy_counts_keypoint_support_as_worked_by_hand():
    """Three peer keypoints, a pose moving them 10 m along x: the first's nearest candidate is its true partner, the
    second's true partner is only its second candidate, the third has an ego keypoint 1 m off its image (within the
    2 m threshold) that is none of its candidates."""
    bench = _alias_anatomy()
    kp_ego = np.array([[10.0, 0.0], [15.0, 5.0], [50.0, 50.0], [31.0, 0.0]])
    kp_peer = np.array([[0.0, 0.0], [5.0, 5.0], [20.0, 0.0]])
    cand = np.array([[0, 2], [2, 1], [2, 0]])
    T = np.array([[1.0, 0.0, 10.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    s = bench.support(T, kp_peer, kp_ego, cand, 2.0)
    assert (s["geometric"], s["top1"], s["topk"]) == (3, 1, 2)
    assert s["mask"].tolist() == [True, True, False]


def test_alias_anatomy_classifies_low_things_walls_and_crowns():
    """Ground everywhere, a 1.5 m high box (a car), a 6 m straight wall and a 6 m round crown on a trunk."""
    bench = _alias_anatomy()
    g = np.arange(-10.0, 30.0, 0.25)
    gx, gy = np.meshgrid(g, g)
    parts = [np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)]
    bx, by, bz = np.meshgrid(np.arange(0.0, 4.5, 0.1), np.arange(0.0, 1.8, 0.1), np.arange(0.2, 1.5, 0.1))
    parts.append(np.stack([bx.ravel(), by.ravel(), bz.ravel()], 1))
    wx, wz = np.meshgrid(np.arange(-10.0, 30.0, 0.1), np.arange(0.2, 6.0, 0.2))
    parts.append(np.stack([wx.ravel(), np.full(wx.size, 20.0), wz.ravel()], 1))
    a, r, z = np.meshgrid(np.linspace(0, 2 * np.pi, 60), np.linspace(0.2, 2.5, 12), np.arange(2.5, 6.0, 0.3))
    parts.append(np.stack([15 + (r * np.cos(a)).ravel(), 5 + (r * np.sin(a)).ravel(), z.ravel()], 1))
    pts = np.concatenate(parts)
    xy = np.array([[2.0, 0.9], [5.0, 20.0], [15.0, 5.0]])
    assert bench.classify(pts, xy).tolist() == ["low", "wall", "tall"]
