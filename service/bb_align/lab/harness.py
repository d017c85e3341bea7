"""What the lab's drivers (bench, soak, demo) and the tests share: free loopback ports, a ``bb-align`` service in
a child process (started, waited for, measured, stopped), and simulated cars' frames."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# The child process runs what `bb-align serve` runs (SIGTERM drains, exit 0); settings as JSON in argv (auth: only
# the paths of the authority and the ego's credential, which are not secrets), the fleet key (if any) on stdin, never
# in argv or the environment.
_CHILD = """
import json, sys
from bb_align.server.commands import run_server
from bb_align.server.settings import Settings
values = json.loads(sys.argv[1])
key = sys.stdin.readline().strip()
if key:
    values.setdefault("auth", {}).update(mode="signed", fleet_key=key)
run_server(Settings.model_validate(values), sys.argv[2])
"""
_SECRETS = {"fleet_key", "peer_keys", "rest_token"}  # never in the child's argv


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def process_memory_mb(pid: int | None) -> dict[str, float | None]:
    """Current and peak resident memory of a process (Linux /proc VmRSS, VmHWM), MB; None where unknown."""
    out: dict[str, float | None] = {"rss_mb": None, "rss_peak_mb": None}
    if pid is None:
        return out
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key = {"VmRSS:": "rss_mb", "VmHWM:": "rss_peak_mb"}.get(line.split(maxsplit=1)[0] if line else "")
            if key:
                out[key] = int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return out


def process_cpu_seconds(pid: int | None) -> float | None:
    """utime + stime of a process (Linux /proc), seconds."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, TypeError):
        return None


def log_tail(path: Path, n: int = 800) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return "(no log)"


def wait_until_ready(
    proc: subprocess.Popen, rest_url: str, timeout_s: float, log_path: Path, stop: Callable[[], object]
) -> None:
    """Poll ``rest_url``/readyz until it answers 200. RuntimeError (with the log's tail) when the process exits
    first, or, after calling ``stop``, when ``timeout_s`` passes."""
    import httpx

    deadline = time.monotonic() + timeout_s
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"the service exited with code {proc.returncode}: {log_tail(log_path)}")
        try:
            if httpx.get(rest_url + "/readyz", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        if time.monotonic() > deadline:
            stop()
            raise RuntimeError(f"the service was not ready within {timeout_s} s: {log_tail(log_path)}")
        time.sleep(0.2)


@dataclass
class ServiceProcess:
    """A service to drive: one this harness started (``proc``), or one already running (``pid`` only, or nothing)."""

    rest: str
    zenoh_endpoint: str
    key: str | None  # the fleet key frames are signed with (None: the service does not authenticate)
    proc: subprocess.Popen | None = None
    pid: int | None = None
    log_path: Path | None = None

    def cpu_seconds(self) -> float | None:
        return process_cpu_seconds(self.pid)

    def memory_mb(self) -> dict[str, float | None]:
        return process_memory_mb(self.pid)

    def get(self, path: str) -> dict:
        import httpx

        return httpx.get(self.rest + path, timeout=10).json()

    def stop(self, timeout_s: float = 60.0) -> int | None:
        """SIGTERM (the service drains) and wait; the exit code, None if it had to be killed or was not ours."""
        proc = self.proc
        if proc is None:
            return None
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
                return None
        return proc.returncode


def start_service(
    settings, key: str | None, log_dir: Path, timeout_s: float = 90.0, log_level: str = "warning"
) -> ServiceProcess:
    """Run ``settings`` (a server Settings; REST port, Zenoh listen endpoint set) in a child process, signed
    frames required when ``key`` is given; returns once /readyz answers."""
    endpoint = settings.zenoh.listen[0] if settings.zenoh.enabled and settings.zenoh.listen else ""
    log_path = Path(log_dir) / f"service-{settings.port}.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD, _child_settings(settings), log_level],
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.PIPE,
        )
    try:
        proc.stdin.write(((key or "") + "\n").encode())
        proc.stdin.close()
    except OSError:
        pass  # the child died early; reported below with its log
    svc = ServiceProcess(f"http://127.0.0.1:{settings.port}", endpoint, key, proc, proc.pid, log_path)
    wait_until_ready(proc, svc.rest, timeout_s, log_path, svc.stop)
    return svc


def _child_settings(settings) -> str:
    """The settings as JSON for the child's argv: every secret left out (the fleet key goes on stdin)."""
    values = json.loads(settings.model_dump_json(exclude={"auth": _SECRETS}))
    values["auth"] = {k: v for k, v in values["auth"].items() if v is not None}
    return json.dumps(values)


def make_credentials(directory: Path, vehicle_ids: Iterable[str]) -> dict:
    """A fleet authority in ``directory`` and one Ed25519 credential per vehicle, made by the ``bb-align keys``
    command itself (init, then issue per vehicle); returns vehicle id -> its loaded Credential."""
    from typer.testing import CliRunner

    from bb_align.protocol import Credential
    from bb_align.server.keys_cli import keys_app

    runner = CliRunner()
    for args in (["init", str(directory)], *(["issue", str(directory), vid] for vid in vehicle_ids)):
        out = runner.invoke(keys_app, args)
        if out.exit_code != 0:
            raise RuntimeError(f"bb-align keys {' '.join(args)} failed: {out.output}")
    return {vid: Credential.load(Path(directory) / f"{vid}.cred") for vid in vehicle_ids}


def fleet_credentials(directory: Path, vehicle_ids: Iterable[str]) -> dict:
    """vehicle id -> its Credential from a fleet directory (``bb-align keys``): ``DIR/<id>.cred`` where it exists,
    else issued now by the authority in ``DIR/ca.key`` (kept in memory, nothing written). ValueError naming the
    command to run when neither exists."""
    from bb_align.protocol import Credential, FleetAuthority

    directory = Path(directory)
    out, authority = {}, None
    for vid in vehicle_ids:
        path = directory / f"{vid}.cred"
        if path.exists():
            out[vid] = Credential.load(path)
            continue
        if authority is None:
            if not (directory / "ca.key").exists():
                raise ValueError(f"no credential for {vid!r} in {directory}: bb-align keys issue {directory} {vid}")
            authority = FleetAuthority.load(directory)
        out[vid] = authority.issue(vid)
    return out


@dataclass
class CarStream:
    """One simulated car's frames (wire Frames; stamps and seqs set at publish time) and its true poses."""

    vehicle_id: str
    frames: list
    T_world_sensor: list[np.ndarray]
    cloud: tuple[np.ndarray, np.ndarray] | None = None  # (points, boxes) of the first frame, to re-encode it


REPLAY_ACCEL_M_S2 = 6.0  # the replays' cars brake and start like a car in traffic, well inside engine.odometry's 1 g


def to_and_fro_times(n: int, dt: float, speed_m_s: float, accel_m_s2: float = REPLAY_ACCEL_M_S2) -> np.ndarray:
    """Simulation times of ``n`` frames shown ``dt`` apart, for a replay forwards then backwards (0 1 .. n-1 n-2 ..):
    the world's clock runs at rate f (1 - cos) / 2 over the n frames, so every car stops at both ends and turns
    round as a car can (a replay at the simulation's pace would reverse a 10 m/s car in one frame: a jump to the
    service's odometry check). f keeps a car of ``speed_m_s`` within ``accel_m_s2``."""
    if n <= 1:
        return np.zeros(max(n, 0))
    span = (n - 1) * dt
    f = min(1.0, accel_m_s2 * span / (np.pi * max(speed_m_s, 1e-6)))
    t = np.arange(n) * dt
    return f / 2.0 * (t - span / (2.0 * np.pi) * np.sin(2.0 * np.pi * t / span))


def simulated_cars(
    n_peers: int,
    n_frames: int,
    seed: int,
    *,
    ego_id: str = "ego",
    dt: float = 0.1,
    sim_config=None,
    bev_options: dict | None = None,
    reported_pose: Callable[[np.ndarray, int, int], np.ndarray | None] | None = None,
    progress: Callable[[Iterable, str], Iterable] | None = None,
) -> list[CarStream]:
    """The ego first (``ego_id``), then peers ``car1``..``carN``: ``n_frames`` simulated frames each, made to be
    replayed forwards then backwards at ``dt`` (``to_and_fro_times``). ``reported_pose(T_world_sensor, car, frame)``
    gives the pose a frame carries (default: the true pose)."""
    from bb_align_client.encode import make_frame

    from .sim import Scenario

    scenario = Scenario(seed, 1 + n_peers, None, sim_config)
    fastest = max(scenario.world.vehicles[a.vehicle].speed for a in scenario.agents)
    times = to_and_fro_times(n_frames, dt, fastest)
    seq = [scenario.frame(k, dt, stamp=t) for k, t in enumerate(times)]
    ids = [ego_id] + [f"car{i}" for i in range(1, n_peers + 1)]
    items = list(enumerate(ids))
    cars = []
    for a, vid in progress(items, "simulated cars") if progress else items:
        agents = [f.agents[str(a)] for f in seq]
        frames = [
            make_frame(
                ag.points,
                ag.boxes,
                vehicle_id=vid,
                stamp=0.0,
                seq=0,
                pose=ag.T_world_sensor if reported_pose is None else reported_pose(ag.T_world_sensor, a, k),
                **(bev_options or {}),
            )
            for k, ag in enumerate(agents)
        ]
        cars.append(CarStream(vid, frames, [ag.T_world_sensor for ag in agents], (agents[0].points, agents[0].boxes)))
    return cars
