"""Sender-side de-skewing (bb_align_client.deskew): against the exact kinematics of a car on a circle, against the
simulator's own distorted sweep, and its errors on bad input."""

from __future__ import annotations

import numpy as np
import pytest

from bb_align.lab.sim.raycast import Mount, cast_sweep
from bb_align_client.deskew import deskew_sweep, firing_times
from sim_support import SENSOR, walls_world


def test_a_point_seen_from_a_turning_car_returns_to_where_it_was_at_mid_sweep():
    """A car on a circle (10 m/s, 1 rad/s): at time t from mid-sweep its sensor has turned by t rad and moved to
    10 (sin t, 1 - cos t) in the mid-sweep frame (the arc, worked by hand); a world point seen then is reported in
    that frame. De-skewing with the twist must give back the point in the mid-sweep frame."""
    rng = np.random.default_rng(0)
    world = rng.uniform(-40, 40, (200, 2))
    times = rng.uniform(-0.05, 0.05, 200)
    pos = 10.0 * np.stack([np.sin(times), 1.0 - np.cos(times)], axis=1)
    c, s = np.cos(times), np.sin(times)
    d = world - pos
    seen = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], rng.normal(0, 1, 200)], axis=1)
    back = deskew_sweep(seen, (10.0, 0.0), 1.0, times_s=times)
    np.testing.assert_allclose(back[:, :2], world, atol=1e-9)
    np.testing.assert_array_equal(back[:, 2], seen[:, 2])  # z untouched
    # straight ahead the same, with the small-angle branch
    straight_back = deskew_sweep(seen, (10.0, 0.0), 0.0, times_s=times)
    shift = np.stack([10.0 * times, np.zeros_like(times)], axis=1)
    np.testing.assert_allclose(straight_back[:, :2], seen[:, :2] + shift, atol=1e-12)


def test_firing_time_follows_a_clockwise_sweep_with_its_seam_behind():
    pts = np.array([[10.0, 0.0, 0], [0.0, 10.0, 0], [0.0, -10.0, 0], [-10.0, 1e-6, 0], [-10.0, -1e-6, 0]])
    np.testing.assert_allclose(firing_times(pts, 0.1), [0.0, -0.025, 0.025, -0.05, 0.05], atol=1e-8)
    np.testing.assert_allclose(firing_times(pts, 0.1, clockwise=False), [0.0, 0.025, -0.025, 0.05, -0.05], atol=1e-8)


def test_the_simulators_torn_sweep_is_mended_with_the_cars_velocity():
    """The simulator's sweep at 15 m/s (not de-skewed: the wall behind the car torn by 1.5 m) de-skewed with the
    car's velocity and the azimuth's firing time lies where the undistorted sweep puts the walls."""
    world = walls_world(15.0)
    torn = cast_sweep(world, 0, SENSOR, Mount(height_m=2.0), 0.0, np.random.default_rng(0), distortion=True).points
    rear = (torn[:, 0] < -5) & (np.abs(torn[:, 1]) < 3)
    front = (torn[:, 0] > 5) & (np.abs(torn[:, 1]) < 3)
    assert np.ptp(torn[rear, 0]) > 1.4  # the tear: 9.25 m at the seam's start, 10.75 m at its end
    mended = deskew_sweep(torn, (15.0, 0.0), 0.0, period_s=1.0 / SENSOR.spin_hz)
    np.testing.assert_allclose(mended[rear, 0], -10.0, atol=0.02)
    np.testing.assert_allclose(mended[front, 0], 10.0, atol=0.02)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"velocity": (1.0, 2.0, 3.0)}, "velocity"),
        ({"velocity": (np.nan, 0.0)}, "velocity"),
        ({"velocity": (1.0, 0.0), "yaw_rate": np.inf}, "yaw_rate"),
        ({"velocity": (1.0, 0.0), "period_s": 0.0}, "period_s"),
        ({"velocity": (1.0, 0.0), "times_s": np.zeros(3)}, "times_s"),
    ],
)
def test_bad_input_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        deskew_sweep(np.zeros((5, 4)), **kwargs)
    with pytest.raises(ValueError, match="points"):
        deskew_sweep(np.zeros((5, 2)), (1.0, 0.0))


def test_a_frame_encoded_with_the_cars_motion_carries_the_de_skewed_image():
    from bb_align.engine.bev import make_bev
    from bb_align.engine.config import BevConfig
    from bb_align_client import encode_frame
    from bb_align_client.encode import make_frame

    torn = cast_sweep(walls_world(15.0), 0, SENSOR, Mount(height_m=2.0), 0.0, np.random.default_rng(0)).points
    frame = make_frame(torn, vehicle_id="car1", stamp=1.0, velocity=(15.0, 0.0))
    assert frame.png == make_bev(deskew_sweep(torn, (15.0, 0.0)), BevConfig()).to_png(6)
    assert frame.png != make_frame(torn, vehicle_id="car1", stamp=1.0).png
    assert encode_frame(torn, vehicle_id="car1", stamp=1.0, velocity=(15.0, 0.0)) != encode_frame(
        torn, vehicle_id="car1", stamp=1.0
    )
    with pytest.raises(ValueError, match="velocity"):
        make_frame(make_bev(torn, BevConfig()), vehicle_id="car1", stamp=1.0, velocity=(15.0, 0.0))
