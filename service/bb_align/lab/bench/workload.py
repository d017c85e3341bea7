"""The benchmark's inputs: a fixed, seeded set of ego/peer frame pairs as the service receives them (PNG BV images
at the configured range and resolution, boxes) with their true relative pose.

The default workload comes from the project's simulator (``bb_align.lab.sim``): two cars with different LiDARs on a
procedural street, self-motion distortion and detector noise on, at spacings from 10 to 60 m. It needs nothing
outside the repository and is the same on every machine for the same parameters. ``data_workload`` reads real
scans in the OPV2V / V2V4Real folder layout instead (``bb_align.io.dataset``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bb_align.engine.bev import BevImage, make_bev
from bb_align.engine.boxes import as_boxes
from bb_align.engine.config import AlignConfig

# Full workload: 6 spacings x 2 streets = 12 pairs. Quick: 2 pairs.
SIM_DISTANCES_M = (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)
SIM_SEEDS = (101, 202)
QUICK_DISTANCES_M = (20.0, 40.0)
QUICK_SEEDS = (101,)
SIM_SPACING_TOLERANCE_M = 3.0  # a simulated pair must be this close to its requested spacing
SIM_RETRIES = 20
SIM_RETRY_STRIDE = 1000


@dataclass(frozen=True)
class BenchPair:
    """One ego/peer pair as bytes on the wire, plus the truth to score the result against."""

    name: str
    ego_png: bytes
    peer_png: bytes
    bev_meta: dict  # BevImage.meta() of both images (same configuration)
    boxes_ego: np.ndarray  # (K, 7) ego sensor frame
    boxes_peer: np.ndarray  # (M, 7) peer sensor frame
    T_ego_peer: np.ndarray | None  # 4x4 truth, None when unknown
    distance_m: float
    num_points: tuple[int, int]  # raw cloud sizes (ego, peer)

    def ego_bev(self) -> BevImage:
        return BevImage.from_png(self.ego_png, **self.bev_meta)

    def peer_bev(self) -> BevImage:
        return BevImage.from_png(self.peer_png, **self.bev_meta)


@dataclass
class Workload:
    pairs: list[BenchPair]
    source: str  # "sim" or "data:<folder>"
    params: dict = field(default_factory=dict)

    def describe(self) -> dict:
        return {
            "source": self.source,
            **self.params,
            "pairs": len(self.pairs),
            "image_px": list(self.pairs[0].ego_bev().shape) if self.pairs else None,
            "png_bytes_mean": float(np.mean([len(p.peer_png) for p in self.pairs])) if self.pairs else 0.0,
            "boxes_mean": float(np.mean([len(p.boxes_peer) for p in self.pairs])) if self.pairs else 0.0,
            "distances_m": [p.distance_m for p in self.pairs],
        }


def make_pair(
    name: str,
    pts_ego: np.ndarray,
    pts_peer: np.ndarray,
    boxes_ego,
    boxes_peer,
    T_ego_peer: np.ndarray | None,
    config: AlignConfig,
) -> BenchPair:
    """Two clouds (each in its own sensor frame) -> the PNG BV images a car would send, at config.bev."""
    bev_ego, bev_peer = make_bev(pts_ego, config.bev), make_bev(pts_peer, config.bev)
    T = None if T_ego_peer is None else np.asarray(T_ego_peer, dtype=float)
    return BenchPair(
        name=name,
        ego_png=bev_ego.to_png(),
        peer_png=bev_peer.to_png(),
        bev_meta=bev_ego.meta(),
        boxes_ego=as_boxes(boxes_ego),
        boxes_peer=as_boxes(boxes_peer),
        T_ego_peer=T,
        distance_m=float(np.hypot(*T[:2, 3])) if T is not None else float("nan"),
        num_points=(int(len(pts_ego)), int(len(pts_peer))),
    )


def sim_workload(
    config: AlignConfig | None = None,
    *,
    quick: bool = False,
    seeds: Iterable[int] | None = None,
    distances_m: Iterable[float] | None = None,
    progress: Callable[[Iterable], Iterable] | None = None,
) -> Workload:
    """Simulated pairs: for each seed (a street) and spacing, frame 0 of a two-car sequence; agent "0" is the ego.
    ``progress`` wraps the iteration (e.g. tqdm)."""
    from ..sim import simulate_sequence

    config = config or AlignConfig()
    seeds = tuple(seeds if seeds is not None else (QUICK_SEEDS if quick else SIM_SEEDS))
    distances = tuple(distances_m if distances_m is not None else (QUICK_DISTANCES_M if quick else SIM_DISTANCES_M))
    jobs = [(s, d) for s in seeds for d in distances]
    pairs = []
    for seed, dist in progress(jobs) if progress else jobs:
        # A street may not offer the wanted spacing (the simulator then places the peer elsewhere): take the
        # next seed of a fixed sequence, so the workload stays deterministic and every spacing is present.
        for attempt in range(SIM_RETRIES):
            s = seed + SIM_RETRY_STRIDE * attempt
            frame = simulate_sequence(seed=s, n_frames=1, n_agents=2, distance_m=dist)[0]
            ego, peer = frame.agents["0"], frame.agents["1"]
            T_true = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
            if abs(np.hypot(*T_true[:2, 3]) - dist) <= SIM_SPACING_TOLERANCE_M:
                break
        else:
            raise RuntimeError(
                f"the simulator did not place two cars {dist:g} m apart for seeds {seed} + "
                f"{SIM_RETRY_STRIDE} k, k < {SIM_RETRIES}"
            )
        pairs.append(make_pair(f"sim-s{s}-d{dist:g}", ego.points, peer.points, ego.boxes, peer.boxes, T_true, config))
    return Workload(
        pairs,
        "sim",
        {
            "seeds": list(seeds),
            "spacings_m": list(distances),
            "range_m": config.bev.range_m,
            "resolution_m": config.bev.resolution_m,
        },
    )


def _sensor_boxes(agent, config: AlignConfig) -> np.ndarray:
    """An agent's detections, else the ground-truth vehicles moved into its sensor frame (its own car and boxes
    outside the BV image left out)."""
    if agent.detections is not None:
        return agent.detections
    if not agent.vehicles:
        return np.zeros((0, 7))
    world = np.array(list(agent.vehicles.values()), dtype=float)
    T_sw = np.linalg.inv(agent.T_world_sensor)
    out = world.copy()
    out[:, :3] = world[:, :3] @ T_sw[:3, :3].T + T_sw[:3, 3]
    out[:, 6] = world[:, 6] + np.arctan2(T_sw[1, 0], T_sw[0, 0])
    r = config.bev.range_m
    keep = (np.hypot(out[:, 0], out[:, 1]) > 2.5) & (np.abs(out[:, 0]) < r) & (np.abs(out[:, 1]) < r)
    return out[keep]


def data_workload(
    root: str | Path,
    config: AlignConfig | None = None,
    *,
    max_pairs: int = 12,
    progress: Callable[[Iterable], Iterable] | None = None,
) -> Workload:
    """Real scans in the OPV2V / V2V4Real layout (ROOT/<scenario>/<agent>/<timestamp>.pcd + .yaml): the ego
    against each peer of the first frame groups, up to ``max_pairs`` pairs."""
    from bb_align.io.dataset import iter_frames

    config = config or AlignConfig()
    groups = []
    for group in iter_frames(root):
        groups += [(group, peer) for peer in group.peers]
        if len(groups) >= max_pairs:
            break
    if not groups:
        raise ValueError(f"--data {root}: no scenario with two agents at one timestamp (OPV2V/V2V4Real layout)")
    pairs = []
    for group, peer in progress(groups[:max_pairs]) if progress else groups[:max_pairs]:
        ego = group.ego
        T_true = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
        pairs.append(
            make_pair(
                f"{group.scenario}/{group.timestamp}/{ego.agent}-{peer.agent}",
                ego.load_points(),
                peer.load_points(),
                _sensor_boxes(ego, config),
                _sensor_boxes(peer, config),
                T_true,
                config,
            )
        )
    return Workload(pairs, f"data:{root}", {"range_m": config.bev.range_m, "resolution_m": config.bev.resolution_m})
