"""Helpers for the service tests: free loopback ports, a real uvicorn server in a thread, a moving pair of cars
in the synthetic street (tests/synthetic.py) with known poses."""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import uvicorn

from bb_align.engine.boxes import transform_boxes
from bb_align.engine.config import AlignConfig, BevConfig
from bb_align.engine.geometry import se2, se3_from_se2
from bb_align.lab.harness import free_port  # noqa: F401  (tests import it from here)
from bb_align.server import create_app
from bb_align.server.settings import Settings
from synthetic import synthetic_world, view_from

RANGE_M = 40.0  # small BV images keep the engine quick in tests


FLEET_KEY = "test-fleet-key-0123456789abcdef"  # tests only


def service_settings(zenoh: bool = True, zenoh_config: dict | None = None, **overrides) -> Settings:
    """Loopback-only settings with a small BV range; Zenoh on a free port with multicast scouting off.

    The embedded demo profile (no authentication) and no receiver-clock stamp window by default: the synthetic
    scenes are stamped from 0 s. Security tests pass ``secure_settings`` instead."""
    z = {
        "enabled": zenoh,
        "listen": [f"tcp/127.0.0.1:{free_port()}"],
        "multicast_scouting": False,
        **(zenoh_config or {}),
    }
    limits = {"check_stamp_clock": False, **overrides.pop("limits", {})}
    base = dict(
        profile="demo", port=free_port(), zenoh=z, align=AlignConfig(bev=BevConfig(range_m=RANGE_M)), limits=limits
    )
    return Settings(**{**base, **overrides})


def secure_settings(zenoh: bool = True, **overrides) -> Settings:
    """The vehicle profile: frames signed with FLEET_KEY, stamps checked against the clock (stamp frames with
    time.time())."""
    limits = {"check_stamp_clock": True, **overrides.pop("limits", {})}
    auth = {"fleet_key": FLEET_KEY, **overrides.pop("auth", {})}
    return service_settings(zenoh, profile="vehicle", auth=auth, limits=limits, **overrides)


@contextmanager
def running_service(settings: Settings):
    """(app, base_url) of a real uvicorn server on 127.0.0.1, always stopped (and its thread joined)."""
    app = create_app(settings)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=settings.port, log_level="warning"))
    thread = threading.Thread(target=server.run, name="uvicorn-test", daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            server.should_exit = True
            thread.join(10)
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield app, f"http://127.0.0.1:{settings.port}"
    finally:
        server.should_exit = True
        thread.join(30)
        assert not thread.is_alive(), "uvicorn did not stop"


@dataclass
class CarFrame:
    points: np.ndarray  # (N, 3) sensor frame
    boxes: np.ndarray  # (K, 7) sensor frame
    T_world_sensor: np.ndarray


def _frame(world, T_world_sensor: np.ndarray, seed: int, height: float) -> CarFrame:
    pts_w, boxes_w = world
    T2 = np.linalg.inv(T_world_sensor)[np.ix_([0, 1, 3], [0, 1, 3])]
    pts = view_from(pts_w, T_world_sensor, seed=seed, max_range=RANGE_M * 1.2, sensor_height=height)
    return CarFrame(pts, transform_boxes(T2, boxes_w), T_world_sensor)


def moving_pair(n_frames: int, dt: float = 0.1, seed: int = 0, times=None) -> list[tuple[float, CarFrame, CarFrame]]:
    """(stamp, ego, peer) per frame: two cars driving through the synthetic street (8 and 10 m/s), the peer ~18 m
    ahead and turned by ~17 deg. ``times``: the street's time of each frame (default k * dt; a replay forwards then
    backwards takes bb_align.lab.harness.to_and_fro_times). T_ego_peer truth: inv(ego.T_world_sensor) @
    peer.T_world_sensor."""
    world = synthetic_world(seed=seed)
    out = []
    for k in range(n_frames):
        t = k * dt if times is None else float(times[k])
        T_we = se3_from_se2(se2(0.2 * t, 8.0 * t, 0.3 * t))
        T_wp = se3_from_se2(se2(0.3 + 0.3 * t, 18.0 + 10.0 * t, 3.0 - 1.0 * t))
        out.append((k * dt, _frame(world, T_we, 2 * k, 1.8), _frame(world, T_wp, 2 * k + 1, 1.5)))
    return out


def true_T_ego_peer(ego: CarFrame, peer: CarFrame) -> np.ndarray:
    return np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor


def service_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(("bbalign-", "uvicorn-test"))]


def wait_for(cond, timeout: float = 20.0, what: str = "condition", step: float = 0.02) -> None:
    """Poll ``cond`` until true; fails the test after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(step)
