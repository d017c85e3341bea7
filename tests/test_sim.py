"""Simulator: the ray caster on a hand-built scene (wall ranges, ground ranges, the tear that self-motion
distortion puts behind a moving car), the detector model, determinism, and a round trip through the reader."""

from __future__ import annotations

import numpy as np
import pytest

from bb_align.io.dataset import iter_frames
from bb_align.lab.sim import DetectionModel, Scenario, SimConfig, detect, simulate_sequence
from bb_align.lab.sim.paths import straight
from bb_align.lab.sim.raycast import Mount, cast_sweep
from bb_align.lab.sim.sensors import SENSOR_MODELS
from bb_align.lab.sim.streets import generate_world
from bb_align.lab.sim.world import Shapes, Terrain, Vehicle, World
from bb_align.lab.sim.writer import scenario_distance, scenario_seed, write_scenario
from sim_support import SENSOR, walls_world


def test_ray_caster_ranges_on_a_hand_built_scene():
    sweep = cast_sweep(walls_world(0.0), 0, SENSOR, Mount(height_m=2.0), 0.0, np.random.default_rng(0))
    p = sweep.points
    np.testing.assert_allclose(sweep.T_world_sensor[:3, 3], [0, 0, 2])
    front = (p[:, 0] > 5) & (np.abs(p[:, 1]) < 5)
    rear = (p[:, 0] < -5) & (np.abs(p[:, 1]) < 5)
    # every beam of these columns meets the wall face before the ground (the -10 deg beam at z = 0.24 m)
    assert front.sum() == rear.sum() > 4 * 100
    np.testing.assert_allclose(p[front, 0], 10.0, atol=1e-4)
    np.testing.assert_allclose(p[rear, 0], -10.0, atol=1e-4)
    # ground, where no wall stands: the -10 and -5 deg beams meet it 2 / tan(10 deg) = 11.34 m and
    # 2 / tan(5 deg) = 22.86 m away
    ground = sweep.owner == -2
    assert ground.any()
    np.testing.assert_allclose(p[ground, 2], -2.0, atol=1e-4)
    d = np.hypot(p[ground, 0], p[ground, 1])
    expected = 2 / np.tan(np.radians([10.0, 5.0]))
    np.testing.assert_allclose(np.abs(d[:, None] - expected).min(axis=1), 0.0, atol=1e-3)
    assert (np.abs(d - expected[0]) < 1e-3).any() and (np.abs(d - expected[1]) < 1e-3).any()


@pytest.mark.parametrize("distortion", [True, False])
def test_self_motion_distortion_tears_the_scan_behind_a_moving_car(distortion):
    # 10 m/s, 10 Hz: the sweep starts facing backwards 0.05 s before mid-sweep (car 0.5 m behind its mid-sweep
    # pose: rear wall 9.5 m away) and ends facing backwards 0.05 s after (10.5 m away); the front wall is
    # swept at mid-sweep (10 m).
    sweep = cast_sweep(
        walls_world(10.0), 0, SENSOR, Mount(height_m=2.0), 0.0, np.random.default_rng(0), distortion=distortion
    )
    p = sweep.points
    front = (p[:, 0] > 5) & (np.abs(p[:, 1]) < 0.3)
    rear_start = (p[:, 0] < -5) & (p[:, 1] > 0) & (p[:, 1] < 0.3)  # azimuth just under +180: fired first
    rear_end = (p[:, 0] < -5) & (p[:, 1] < 0) & (p[:, 1] > -0.3)  # azimuth just over -180: fired last
    assert front.any() and rear_start.any() and rear_end.any()
    np.testing.assert_allclose(p[front, 0], 10.0, atol=0.01)
    if distortion:
        np.testing.assert_allclose(p[rear_start, 0], -9.5, atol=0.01)
        np.testing.assert_allclose(p[rear_end, 0], -10.5, atol=0.01)
    else:
        np.testing.assert_allclose(p[rear_start | rear_end, 0], -10.0, atol=1e-4)


def test_detection_model_keeps_vehicles_with_enough_points_and_applies_flips():
    boxes = np.array([[10, 0, -1, 4.5, 1.8, 1.5, 0.3], [30, 5, -1, 4.5, 1.8, 1.5, -1.0], [50, -5, -1, 4, 1.8, 1.5, 2]])
    counts = np.array([50, 9, 10])
    exact = DetectionModel(
        min_points=10,
        miss_prob=0,
        miss_prob_far=0,
        centre_sigma_m=0,
        centre_sigma_far_m=0,
        z_sigma_m=0,
        size_sigma_m=0,
        yaw_sigma_deg=0,
        flip_prob=0,
        false_positives=0,
    )
    det = detect(boxes, counts, None, np.random.default_rng(1), exact)
    np.testing.assert_array_equal(det.truth, [0, 2])
    np.testing.assert_allclose(det.boxes, boxes[[0, 2]])
    assert np.all((det.scores > 0) & (det.scores < 1))
    flipped = detect(boxes, counts, None, np.random.default_rng(1), exact.model_copy(update={"flip_prob": 1.0}))
    d_yaw = np.angle(np.exp(1j * (flipped.boxes[:, 6] - boxes[[0, 2], 6])))
    np.testing.assert_allclose(np.abs(d_yaw), np.pi, atol=1e-9)
    fp = detect(boxes, counts, None, np.random.default_rng(1), exact.model_copy(update={"false_positives": 5.0}))
    assert (fp.truth == -1).sum() >= 1 and np.all(np.hypot(*fp.boxes[fp.truth == -1, :2].T) < 100.5)
    with pytest.raises(ValueError, match="n_points"):
        detect(boxes, counts[:2], None, np.random.default_rng(1), exact)


def test_simulate_sequence_is_deterministic_and_cars_move():
    a = simulate_sequence(seed=7, n_frames=2, distance_m=25.0)
    b = simulate_sequence(seed=7, n_frames=2, distance_m=25.0)
    assert [f.stamp for f in a] == pytest.approx([0.0, 0.1])
    for fa, fb in zip(a, b):
        assert list(fa.agents) == ["0", "1"]
        for k in fa.agents:
            np.testing.assert_array_equal(fa.agents[k].points, fb.agents[k].points)
            np.testing.assert_array_equal(fa.agents[k].boxes, fb.agents[k].boxes)
            np.testing.assert_array_equal(fa.agents[k].T_world_sensor, fb.agents[k].T_world_sensor)
    f0 = a[0]
    ego, peer = f0.agents["0"], f0.agents["1"]
    assert ego.sensor != peer.sensor  # heterogeneous LiDARs
    assert ego.points.dtype == np.float32 and ego.points.shape[1] == 4 and len(ego.points) > 10_000
    assert ego.boxes.shape[1] == 7
    T_ego_peer = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
    assert np.hypot(*T_ego_peer[:2, 3]) == pytest.approx(25.0, abs=2.0)
    # ground returns sit about one mounting height below the sensor
    assert -2.3 < np.percentile(ego.points[:, 2], 5) < -1.4
    # consecutive frames: each car moved at most 16 m/s * 0.1 s, and the scans differ
    for k in ("0", "1"):
        step = np.linalg.norm(a[1].agents[k].T_world_sensor[:2, 3] - a[0].agents[k].T_world_sensor[:2, 3])
        assert step <= 1.7
    assert not np.array_equal(a[0].agents["0"].points, a[1].agents["0"].points)
    c = simulate_sequence(seed=8, n_frames=1, distance_m=25.0)
    assert not np.array_equal(c[0].agents["0"].points[:100], f0.agents["0"].points[:100])


def test_simulate_sequence_rejects_bad_arguments():
    with pytest.raises(ValueError, match="n_frames"):
        simulate_sequence(seed=1, n_frames=0)
    with pytest.raises(ValueError, match="distance_m"):
        simulate_sequence(seed=1, distance_m=-5.0)
    with pytest.raises(ValueError, match="dt"):
        simulate_sequence(seed=1, dt=0.0)


def test_simulated_scenario_round_trips_through_the_reader(tmp_path):
    cfg = SimConfig()
    name = write_scenario(tmp_path, seed=3, index=1, n_scenarios=4, config=cfg)
    frame = Scenario(scenario_seed(3, 1), 2, scenario_distance(3, 1, 4, cfg), cfg).frame(0)
    (g,) = list(iter_frames(tmp_path))
    assert g.scenario == name and list(g.agents) == ["0", "1"]
    for k, agent in g.agents.items():
        sim = frame.agents[k]
        np.testing.assert_allclose(agent.load_points(), sim.points)
        np.testing.assert_allclose(agent.T_world_sensor, sim.T_world_sensor, atol=1e-9)
        np.testing.assert_allclose(agent.detections, sim.boxes, atol=1e-9)
        np.testing.assert_allclose(agent.detection_scores, sim.scores, atol=1e-9)
        assert agent.extra["sensor"] == sim.sensor
        # the other agent is among this agent's vehicles, itself is not
        other = frame.agents["1" if k == "0" else "0"].vehicle_id
        assert str(other) in agent.vehicles and str(sim.vehicle_id) not in agent.vehicles


def test_porous_shape_stops_rays_through_its_depth():
    """A porous slab 2 m deep (porosity 0.5) in front of a wall: half the rays pass it (they meet the wall), and
    those that stop in it do so exponentially along the chord, mu * 2 m = ln 2: mean depth
    2 m * (1 / ln 2 - 0.5 / 0.5) = 0.885 m (a face-only model would put every return within its first metre)."""
    sh = Shapes()
    sh.prism(11.0, 0.0, 1.0, 30.0, 0.0, 0.0, 6.0, porosity=0.5)  # slab from x = 10 to 12 m
    sh.prism(20.5, 0.0, 0.5, 30.0, 0.0, 0.0, 6.0)  # wall behind, face at x = 20 m
    terrain = Terrain(np.array([-200.0, -200.0]), 2.0, np.zeros((201, 201)), np.zeros((201, 201)))
    car = Vehicle(0, 4.5, 1.8, 1.5, "car", path=straight((-100.0, 0.0), 0.0, 200.0), s0=100.0, speed=0.0)
    flat = SENSOR.model_copy(update={"elevations_deg": (0.0,), "columns": 3600})
    sweep = cast_sweep(World([], sh.arrays(), [car], terrain, []), 0, flat, Mount(height_m=2.0), 0.0,
                       np.random.default_rng(1))  # fmt: skip
    p = sweep.points
    az = np.arctan2(p[:, 1], p[:, 0])
    ahead = (p[:, 0] > 5) & (np.abs(az) < np.radians(8))  # near-perpendicular rays: chord 2-2.02 m
    x = np.hypot(p[ahead, 0], p[ahead, 1])  # range along the ray (the slab's face 10-10.1 m away)
    in_slab = x < 15
    assert ahead.sum() > 150
    assert abs(in_slab.mean() - 0.5) < 0.12
    depth = x[in_slab] - 10.0 / np.cos(az[ahead][in_slab])
    assert depth.min() >= -0.01 and depth.max() <= 2.05
    assert abs(depth.mean() - 2.0 * (1 / np.log(2) - 1.0)) < 0.15


@pytest.mark.parametrize("family", ["street", "turn"])
def test_scenario_families_place_the_cars_as_named(family):
    """street: the peer ahead of the ego in its lane, nearly the same heading; turn: the peer on a crossing street
    (65-115 deg, with the lane's own few degrees), at the drawn spacing (nearest feasible for turn)."""
    lo, hi = (60.0, 100.0) if family == "street" else (40.0, 70.0)
    for seed in (3, 4):
        sc = Scenario(seed, 2, None, SimConfig(family=family, min_distance_m=lo, max_distance_m=hi))
        T_world = {a: sc.world.vehicles[s.vehicle].pose(0.0) for a, s in zip("ep", sc.agents)}
        (xe, ye, he), (xp, yp, hp) = ([float(v) for v in T_world[a]] for a in "ep")
        d = np.hypot(xp - xe, yp - ye)
        dyaw = np.degrees(np.arctan2(np.sin(hp - he), np.cos(hp - he)))
        if family == "street":
            assert lo - 1 <= d <= hi + 1
            assert abs(dyaw) < 5.0
            assert (xp - xe) * np.cos(he) + (yp - ye) * np.sin(he) > 0.95 * d  # ahead, in line
        else:
            assert 20.0 <= d <= hi + 5
            assert 60.0 <= abs(dyaw) <= 120.0


def test_crossing_family_places_the_peer_on_the_crossing_street_50_to_100_m_away():
    """The crossing family (benchmarks/crossings.py): the ego on the main road within 30 m of the crossing, the peer
    on a lane of the crossing street 50-100 m away, turned 60-120 deg either way relative to the ego, on the turn
    family's world of the same seed."""
    cfg = SimConfig(family="crossing", min_distance_m=50.0, max_distance_m=100.0)
    signs = []
    for seed in (1, 6, 9):  # seed 1 turned left, 6 and 9 right
        sc = Scenario(seed, 2, None, cfg)
        ego, peer = (sc.world.vehicles[s.vehicle] for s in sc.agents)
        (xe, ye, he), (xp, yp, hp) = ([float(v) for v in car.pose(0.0)] for car in (ego, peer))
        d = np.hypot(xp - xe, yp - ye)
        dyaw = np.degrees(np.arctan2(np.sin(hp - he), np.cos(hp - he)))
        assert 50.0 - 1.5 <= d <= 100.0 + 1.5, (seed, d)
        assert 60.0 <= abs(dyaw) <= 120.0, (seed, dyaw)
        assert any(ego.path is ln for ln in sc.world.roads[0].lanes())
        cross = next(r for r in sc.world.roads[1:] if any(peer.path is ln for ln in r.lanes()))
        centre = np.array(cross.centre.pose_at(cross.centre.length / 2)[:2])
        assert sc.world.roads[0].centre.nearest_s(np.array([xe, ye]))[1] < 10.0  # on the main road
        assert np.hypot(xe - centre[0], ye - centre[1]) <= 31.0  # within 30 m of the crossing
        signs.append(np.sign(dyaw))
    assert set(signs) == {-1.0, 1.0}  # turned either way
    turn = generate_world(np.random.default_rng([9, 0]), family="turn")
    np.testing.assert_array_equal(turn.static.xy, sc.world.static.xy)  # the turn family's world


def test_reach_follows_the_datasheet_range_law():
    hdl = SENSOR_MODELS["hdl64"]
    # the two datasheet points, and the power law through them in between
    np.testing.assert_allclose(hdl.reach_m([0.8, 0.1]), [120.0, 50.0])
    k = np.log(120 / 50) / np.log(8)
    np.testing.assert_allclose(hdl.reach_m(0.4), 120 * 0.5**k)
    # without a datasheet 10 % range: the lidar equation's square-root law
    np.testing.assert_allclose(SENSOR.reach_m(0.1), 100 / np.sqrt(8))
    np.testing.assert_allclose(hdl.detect_probability([0.0, 50.0, 200.0], 0.1), [1.0, 0.0, 0.0])


@pytest.mark.parametrize("exponent", [0.0, 1.0])
def test_far_wall_returns_thin_out_as_the_range_law_says(exponent):
    """A wall of reflectivity 0.4 facing the car 60 m ahead: the share of rays that return, straight ahead and at
    35-45 deg off its normal, against 1 - (r / reach(0.4 cos^q(incidence)))^3 averaged over those rays."""
    sensor = SENSOR.model_copy(
        update={"elevations_deg": (0.0, 1.0), "far_falloff": 3.0, "max_range_m": 120, "range_10pct_m": 50.0}
    )
    sensor = sensor.model_copy(update={"incidence_exponent": exponent})
    sh = Shapes()
    sh.prism(60.5, 0.0, 0.5, 100.0, 0.0, 0.0, 20.0, reflect=0.4)
    terrain = Terrain(np.array([-200.0, -200.0]), 2.0, np.zeros((201, 201)), np.zeros((201, 201)))
    car = Vehicle(0, 4.5, 1.8, 1.5, "car", pose0=(0.0, 0.0, 0.0))
    world = World([], sh.arrays(), [car], terrain, [])
    sweep = cast_sweep(world, 0, sensor, Mount(height_m=2.0), 0.0, np.random.default_rng(3), distortion=False)
    az = np.degrees(np.arctan2(sweep.points[:, 1], sweep.points[:, 0]))
    cols = (np.arange(sensor.columns) + 0.5) / sensor.columns
    col_az = np.degrees(np.angle(np.exp(1j * (np.pi - 2 * np.pi * cols))))
    for lo, hi in ((-5.0, 5.0), (35.0, 45.0)):
        a = np.radians(col_az[(col_az > lo) & (col_az < hi)])
        expected = []
        for e in np.radians(sensor.elevations_deg):
            r = 60.0 / np.cos(a) / np.cos(e)
            expected.append(sensor.detect_probability(r, 0.4 * (np.cos(a) * np.cos(e)) ** exponent))
        expected = np.mean(expected)
        got = ((az > lo) & (az < hi)).sum() / (2 * len(a))
        assert abs(got - expected) < 3 * np.sqrt(expected * (1 - expected) / (2 * len(a))) + 0.01, (lo, got, expected)
    if exponent == 1.0:  # a Lambertian wall is fainter seen obliquely: fewer returns than straight ahead
        assert ((az > 35) & (az < 45)).sum() < 0.5 * ((az > -5) & (az < 5)).sum()


def test_street_family_has_a_junction_every_block():
    """A residential street meets a side street or a crossing every 80-200 m (real blocks' lengths), at 80-90 deg
    or diagonally at 30-60 deg: measured on the generated road polylines, where each side street touches the main
    road's centre line."""
    for seed in (5, 6):
        world = generate_world(np.random.default_rng([seed, 0]), family="street")
        main = world.roads[0].centre
        at, angles = [], []
        for road in world.roads[1:]:
            d = np.hypot(*(road.centre.xy[:, None, :] - main.xy[None, ::4, :]).transpose(2, 0, 1)).min(1)
            k = int(np.argmin(d))
            assert d[k] < 1.5  # it reaches the main road
            s, _ = main.nearest_s(road.centre.xy[k])
            dh = road.centre.heading[k] - float(main.pose_at(s)[2])
            ang = np.degrees(abs(np.arctan2(np.sin(dh), np.cos(dh))))
            at.append(s)
            angles.append(min(ang, 180.0 - ang))  # the angle between the two streets
        gaps = np.diff(np.sort(at))
        assert len(at) >= 3
        assert np.all((gaps > 79.0) & (gaps < 201.0)), gaps
        assert all(29.0 <= a <= 61.0 or 79.0 <= a <= 90.0 for a in angles), angles


@pytest.mark.parametrize(
    ("family", "n_shapes", "n_vehicles", "xy_sum", "zt_sum"),
    [
        ("mixed", 1142, 179, 24039.15641189408, 4941.471601648981),
        ("turn", 2342, 183, 496357.29604680056, 9665.231590196789),
    ],
)
def test_mixed_and_turn_worlds_stay_as_they_were(family, n_shapes, n_vehicles, xy_sum, zt_sum):
    """The fixed benchmark's (mixed) and the turn family's worlds do not move when the street family changes: the
    counts and sums of one world each, as the generator made them before the street family had junctions."""
    world = generate_world(np.random.default_rng([5, 0]), family=family)
    assert (len(world.static.a), len(world.vehicles)) == (n_shapes, n_vehicles)
    np.testing.assert_allclose([world.static.xy.sum(), world.static.zt.sum()], [xy_sum, zt_sum], rtol=1e-9)


def _side_wall_world() -> World:
    """A 20 m tall wall along the car's path, 10 m to its left, from 20 to 100 m ahead; the car stands at the origin."""
    sh = Shapes()
    sh.prism(60.0, 10.5, 40.0, 0.5, 0.0, 0.0, 20.0, reflect=0.8)  # seen to the sensor's 100 m
    terrain = Terrain(np.array([-200.0, -200.0]), 2.0, np.zeros((201, 201)), np.zeros((201, 201)))
    car = Vehicle(0, 4.5, 1.8, 1.5, "car", path=straight((-100.0, 0.0), 0.0, 200.0), s0=100.0, speed=0.0)
    return World([], sh.arrays(), [car], terrain, [])


@pytest.mark.parametrize("phases", [1, 8])
def test_lasers_at_their_own_azimuths_draw_a_grazing_wall_solid(phases):
    # 8 upward beams, 1000 columns (0.36 deg): at 70 m ahead the wall is seen 8.1 deg off grazing, so one laser's
    # hits on it are 70.7 m x 0.36 deg / sin(8.1 deg) = 3.1 m apart. All lasers at the column's azimuth leave one
    # 0.4 m bin in ~8 lit; 8 azimuth phases put a hit every 0.39 m.
    sensor = SENSOR.model_copy(
        update={"elevations_deg": tuple(np.arange(8) * 0.5), "columns": 1000, "azimuth_phases": phases}
    )
    p = cast_sweep(_side_wall_world(), 0, sensor, Mount(height_m=2.0), 0.0, np.random.default_rng(0)).points
    on = p[(p[:, 0] > 60) & (p[:, 0] < 80)]
    np.testing.assert_allclose(on[:, 1], 10.0, atol=1e-3)
    az = np.round(np.degrees(np.arctan2(on[:, 1], on[:, 0])), 6)
    assert len(np.unique(az)) == pytest.approx(len(on) / 8 * phases, rel=0.15)  # 8 beams share phases/8 azimuths
    lit = np.unique(np.floor(on[:, 0] / 0.4)).size / (20 / 0.4)
    assert (lit < 0.2) if phases == 1 else (lit > 0.9)


def test_real_lidar_lasers_fire_at_their_own_azimuths(shared_data):
    # what the azimuth phases model: in a real HDL-64E scan (KITTI 00) almost every return has an azimuth of its own,
    # where lasers sharing column azimuths would give 64 returns per azimuth
    from bb_align.io.clouds import load_cloud

    p = load_cloud(shared_data / "kitti00_run_far" / "000000.bin")
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    window = (az > 10) & (az < 11) & (np.hypot(p[:, 0], p[:, 1]) > 5)
    assert window.sum() > 100
    assert len(np.unique(np.round(az[window], 3))) > 0.8 * window.sum()


def test_sector_culled_footprint_hits_equal_the_dense_ones():
    # brute force as the truth: every footprint against every column, for a car moving through 300 random prisms
    # and cylinders (some moving, some around the sensor) over a distorted sweep
    from bb_align.lab.sim.raycast import _footprint_hits, _footprint_hits_dense

    rng = np.random.default_rng(5)
    sh = Shapes()
    for x, y in rng.uniform(-80, 80, (300, 2)):
        if rng.random() < 0.5:
            sh.prism(x, y, rng.uniform(0.2, 15), rng.uniform(0.1, 5), rng.uniform(-np.pi, np.pi), 0.0, 3.0)
        else:
            sh.cyl(x, y, rng.uniform(0.1, 4), 0.0, 3.0)
    sh.cyl(0.5, 0.2, 3.0, 0.0, 3.0)  # the sensor inside a footprint
    shapes = sh.arrays()
    n = 900
    dt = (np.arange(n) + 0.5) / n * 0.1 - 0.05
    phi = np.pi - 2 * np.pi * (np.arange(n) + 0.5) / n + 0.3 * dt
    ox, oy = 15.0 * dt, 2.0 * dt
    vel = rng.normal(0, 10, (len(shapes), 2))
    for v in (None, vel):
        culled = _footprint_hits(ox, oy, np.cos(phi), np.sin(phi), shapes, v, dt)
        dense = _footprint_hits_dense(ox, oy, np.cos(phi), np.sin(phi), shapes, v, dt)
        hit = np.isfinite(dense[0])
        assert hit.sum() > 1000
        np.testing.assert_array_equal(culled[0], dense[0])
        np.testing.assert_array_equal(culled[1][hit], dense[1][hit])
        np.testing.assert_array_equal(culled[2][hit], dense[2][hit])
