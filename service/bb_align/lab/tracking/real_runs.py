"""Tracking on real sweeps: the follower run through time on the real 10 Hz KITTI runs in ``../shared/data``.

The runs hold one car's consecutive sweeps (and, in ``kitti00_run_far``, the same car about 75 m further on), so
two cars are made from them: the ego drives the run's frames forward, back and forward again (each step 0.1 s;
its odometry the run's poses), and the peer is another frame of the same run at each step (its odometry the
same poses). Every answer is scored against the run's reference poses:

- ``kitti08_run`` (residential) and ``kitti01_run`` (highway entry, fast, turning: strong self-motion
  distortion): the peer is frame ``9 - k`` while the ego is at frame ``k``, 0-9 m apart;
- ``kitti00_run_far``: the peer alternates between frames 94 and 95 (the car 73-80 m ahead), its odometry
  jumping back and forth by one sweep's travel, as the poses say;
- ``kitti00_run_far_behind``: the same two cars with their roles swapped: the ego is the car ahead (frames 94 /
  95), the peer the car 73-80 m behind it;
- ``no_overlap``: the ego drives ``kitti08_run``'s frames, the peer ``kitti00_run_far``'s, in two cities: no pose
  is right, so every success is wrong; its GNSS-grade pose claims the far run's geometry (the peer 73-80 m ahead).

With ``gnss``, each frame also carries a GNSS-grade reported pose: the reference ``T_ego_peer`` moved by a smooth
random walk (a first-order Gauss-Markov process, 2 m / 2 deg 1-sigma, 3 s correlation time, seeded), as two cars'
GNSS errors drift together.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bb_align.engine.config import AlignConfig
from bb_align.engine.follow import Follower
from bb_align.engine.geometry import pose_error, se2, se3_from_se2
from bb_align.engine.pipeline import Aligner
from bb_align.io.clouds import load_cloud
from bb_align.lab.tracking.replay import error_components, stream_sample

RUNS = ("kitti08_run", "kitti01_run", "kitti00_run_far", "kitti00_run_far_behind", "no_overlap")
# (ego's folder, peer's folder) of the runs not named after one folder
_FOLDERS = {
    "kitti00_run_far_behind": ("kitti00_run_far", "kitti00_run_far"),
    "no_overlap": ("kitti08_run", "kitti00_run_far"),
}
FAR_PEER_FRAMES = (94, 95)
STEP_S = 0.1
GNSS_SIGMA_M, GNSS_SIGMA_DEG, GNSS_TAU_S = 2.0, 2.0, 3.0


def gnss_errors(steps: int, seed: int = 0) -> list[np.ndarray]:
    """Per step, the reported pose's error (yaw rad, x m, y m): a stationary first-order Gauss-Markov process."""
    rng = np.random.default_rng(seed)
    sigma = np.array([np.radians(GNSS_SIGMA_DEG), GNSS_SIGMA_M, GNSS_SIGMA_M])
    keep = np.exp(-STEP_S / GNSS_TAU_S)
    e, out = rng.normal(size=3) * sigma, []
    for _ in range(steps):
        out.append(e.copy())
        e = keep * e + np.sqrt(1.0 - keep**2) * rng.normal(size=3) * sigma
    return out


@dataclass
class Step:
    run: str
    step: int
    ego_frame: int
    peer_frame: int
    distance_m: float
    source: str | None
    state: str | None
    success: bool
    reason: str | None
    t_err_m: float
    r_err_deg: float
    stamp: float = 0.0
    event: str | None = None
    # This frame's own evidence as the track's stream holds it (replay.stream_sample): error and covariance.
    evidence_err: list[float] | None = None
    evidence_cov: list[list[float]] | None = None
    err: list[float] | None = None  # the answer's (yaw rad, tx m, ty m) minus the reference's
    covariance: list[list[float]] | None = None  # the answer's, of those parameters

    truth: bool = True  # False: no pose is right (the two cars' scans do not overlap)

    @property
    def wrong(self) -> bool:
        return self.success and not (self.truth and self.t_err_m < 1.0 and self.r_err_deg < 1.0)


def run_poses(folder: Path) -> dict[int, np.ndarray]:
    """Frame -> 4x4 T_velo0_veloK: the run's pose list, plus ``T_0_K.txt`` for frames outside it (94, 95)."""
    poses: dict[int, np.ndarray] = {}
    for line in next(folder.glob("velo_poses_*.txt")).read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            v = [float(x) for x in line.split()]
            T = np.eye(4)
            T[:3] = np.array(v[1:13]).reshape(3, 4)
            poses[int(v[0])] = T
    for k in FAR_PEER_FRAMES:
        if (path := folder / f"T_0_{k}.txt").exists():
            poses[k] = np.loadtxt(path)
    return poses


def folders(data: Path, run: str) -> tuple[Path, Path]:
    """(the ego's folder, the peer's folder) of a run."""
    ego, peer = _FOLDERS.get(run, (run, run))
    return data / ego, data / peer


def schedule(run: str, laps: int = 3) -> list[tuple[int, int]]:
    """(ego frame, peer frame) per step: the ego forward, back and forward over frames 0-9 (``laps`` passes)."""
    ego = [k if lap % 2 == 0 else 9 - k for lap in range(laps) for k in range(10)]
    if run in ("kitti00_run_far", "no_overlap"):
        return [(e, FAR_PEER_FRAMES[i % 2]) if run == "kitti00_run_far" else (e, e) for i, e in enumerate(ego)]
    if run == "kitti00_run_far_behind":
        return [(p, e) for e, p in schedule("kitti00_run_far", laps)]
    return [(e, 9 - e) for e in ego]


def track_run(
    data: Path,
    run: str,
    laps: int = 3,
    odometry: bool = True,
    config: AlignConfig | None = None,
    gnss: bool = False,
    seed: int = 0,
):
    """Every step of one run through a fresh follower; a Step per peer frame. ``gnss``: each frame carries a
    GNSS-grade reported pose (module doc; ``seed`` seeds its errors), the acquisitions' prior."""
    ego_dir, peer_dir = folders(data, run)
    config = config or AlignConfig()
    # These replays turn the cars round in one step (and the far peer steps back and forth a sweep's travel):
    # not a motion, and the odometry's acceleration check would take every turn for a relocalisation. It is off here;
    # tests/test_odometry.py checks it on real drives.
    track = config.track.model_copy(update={"max_odometry_accel_m_s2": None})
    aligner = Aligner(config.model_copy(update={"track": track}))
    ego_poses, peer_poses = run_poses(ego_dir), run_poses(peer_dir)
    truth = ego_dir == peer_dir  # two cities: no pose is right
    far_poses = run_poses(data / "kitti00_run_far") if not truth else None
    follower = Follower(aligner)
    frames: dict[tuple[int, bool], object] = {}

    def frame(k: int, peer: bool):
        if (k, peer) not in frames:  # the ego frame needs no features: the follower measures against it
            folder = peer_dir if peer else ego_dir
            frames[(k, peer)] = aligner.prepare(load_cloud(folder / f"{k:06d}.bin"), features=peer)
        return frames[(k, peer)]

    steps, plan = [], schedule(run, laps)
    errors = gnss_errors(len(plan), seed)
    for i, (e, p) in enumerate(plan):
        if truth:
            T_true = np.linalg.inv(ego_poses[e]) @ peer_poses[p]
        else:  # what the reports claim: the far run's geometry (the peer 73-80 m ahead)
            T_true = np.linalg.inv(far_poses[e]) @ far_poses[FAR_PEER_FRAMES[i % 2]]
        O = {"O_ego": ego_poses[e], "O_peer": peer_poses[p]} if odometry else {}
        if gnss:
            O["T_prior"] = se3_from_se2(se2(*errors[i])) @ T_true
        r = follower.step(frame(e, False), frame(p, True), STEP_S * i, **O)
        t_err, r_err = pose_error(r.T_ego_peer, T_true) if truth else (float("nan"), float("nan"))
        dist = float(np.hypot(T_true[0, 3], T_true[1, 3]))
        ev = stream_sample(follower, STEP_S * i, O.get("O_ego"), O.get("O_peer"), T_true if truth else None)
        steps.append(
            Step(
                run, i, e, p, dist, r.source, r.track_state, bool(r.success), r.reason, t_err, r_err,
                stamp=STEP_S * i,
                event=r.track_event,
                evidence_err=ev["evidence_err"],
                evidence_cov=ev["evidence_cov"],
                err=error_components(r.T_ego_peer, T_true) if truth else None,
                covariance=None if r.covariance is None or not truth else np.asarray(r.covariance).tolist(),
                truth=truth,
            )
        )  # fmt: skip
    return steps


def summary(steps: list[Step]) -> dict:
    """Per run: steps, successful, wrong successes, the worst successful error, refusal reasons."""
    out: dict = {}
    for s in steps:
        o = out.setdefault(s.run, {"steps": 0, "successful": 0, "wrong": 0, "worst_m": 0.0, "worst_deg": 0.0})
        o["steps"] += 1
        o["successful"] += s.success
        o["wrong"] += s.wrong
        if s.success and s.truth:
            o["worst_m"], o["worst_deg"] = max(o["worst_m"], s.t_err_m), max(o["worst_deg"], s.r_err_deg)
        else:
            reasons = o.setdefault("refused", {})
            reasons[s.reason] = reasons.get(s.reason, 0) + 1
    return out


def records(steps: list[Step]) -> list[dict]:
    return [asdict(s) for s in steps]
