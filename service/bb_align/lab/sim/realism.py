"""How simulated BV images compare with real ones: statistics and a side-by-side figure.

    python -m bb_align.lab.sim.realism docs/sim [--data ../shared/data] [--street 12] [--landscape N] [--shared N]

Statistics per cloud (engine's default BevConfig): points, lit BV pixels, lit pixels per 100 m^2 in range
rings (sparsity with range), the share of lit pixels that are low clutter (0.3-1.5 m above the local ground:
kerbs, bushes, terrain) versus tall structure (over 3 m: walls, trees), and FAST keypoints (what stage 1 can
match). Real clouds: whatever of KITTI (HDL-64E), Argoverse 2 (2 x VLP-32C) and nuScenes (32 beams) is in the
data folder.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bb_align.engine.bev import make_bev
from bb_align.engine.config import BevConfig
from bb_align.engine.keypoints import detect_keypoints

RINGS = ((0, 20), (20, 40), (40, 60), (60, 80))
BANDS = ((0, 20), (20, 40), (40, 70), (70, 100))  # the far-pair bands of benchmarks/sim_vs_real.py
CARRIAGEWAY_M = 7.0  # half the kerb-to-kerb width of a street with parking both sides, m
TALL_M = 2.0  # taller than a car: what lines a street (facades, hedges, crowns, poles), m above the local ground
TUNED = {"KITTI 00 street (tuned on)": "kitti00_run_far"}
HELD_OUT = {
    "KITTI 08 street (held out)": "kitti08_run",
    "KITTI 08 loop (held out)": "kitti08_loop",
    "KITTI 01 highway (held out)": "kitti01_run",
}


def lit_by_band(bev, within_y_m: float = np.inf) -> list[int]:
    """Lit pixels of a BV image by range from its sensor, in BANDS (only those within ``within_y_m`` of its x axis)."""
    rc = np.argwhere(bev.image > 0)
    xy = bev.pixel_to_metre(rc)
    r = np.hypot(*xy.T)
    near_axis = np.abs(xy[:, 1]) < within_y_m
    return [int(((r >= lo) & (r < hi) & near_axis).sum()) for lo, hi in BANDS]


def nearest_tall_m(bev, reach_m: float = 40.0, slice_m: float = 4.0, max_lateral_m: float = 25.0):
    """The street's cross-section as a scan shows it: in each ``slice_m`` slice along the sensor's x axis within
    ``reach_m``, the lateral distance to the nearest pixel over TALL_M above the local ground (facades, hedges, crowns,
    poles: taller than a car), on the left and on the right; slices with none are left out."""
    xy = bev.pixel_to_metre(np.argwhere(bev.heights_m() > TALL_M))
    left, right = [], []
    for x0 in np.arange(-reach_m, reach_m, slice_m):
        y = xy[(xy[:, 0] >= x0) & (xy[:, 0] < x0 + slice_m), 1]
        y = y[np.abs(y) < max_lateral_m]
        if (y > 0.5).any():
            left.append(float(y[y > 0.5].min()))
        if (y < -0.5).any():
            right.append(float(-y[y < -0.5].max()))
    return left, right


def band_profile(clouds) -> dict:
    """Median and quartiles of lit pixels by band over HDL-64E scans, through the engine's own preparation, and the
    median of those within CARRIAGEWAY_M of the sensor's x axis (on a street the car drives along: its carriageway,
    parked cars and what stands over it)."""
    from bb_align import AlignConfig, Aligner

    aligner = Aligner(AlignConfig())
    bevs = [aligner.prepare(p).bev for p in clouds]
    rows = np.array([lit_by_band(b) for b in bevs])
    lane = np.array([lit_by_band(b, CARRIAGEWAY_M) for b in bevs])
    sides = [nearest_tall_m(b) for b in bevs]
    return {
        "scans": len(rows),
        "median": np.median(rows, 0).astype(int).tolist(),
        "q25": np.percentile(rows, 25, 0).astype(int).tolist(),
        "q75": np.percentile(rows, 75, 0).astype(int).tolist(),
        "carriageway_median": np.median(lane, 0).astype(int).tolist(),
        "nearest_tall_median_m": [round(float(np.median(sum((sd[k] for sd in sides), []))), 1) for k in (0, 1)],
    }


def along_street_alias(pts_ego, pts_peer, T_ego_peer, reach_m: float = 90.0) -> tuple[float, float]:
    """(overlap at the truth, best overlap elsewhere) of the peer's BV samples on the ego's: the peer slid along the
    baseline every metre over +-reach_m and +-1 m across, at the truth's yaw and turned by half a turn, skipping
    the truth's +-3 m. Images only (no engine decision): how much a place looks like another one along a street."""
    from bb_align import AlignConfig, Aligner
    from bb_align.engine.geometry import ground_se2, se2
    from bb_align.engine.refine import overlap_fitness

    aligner = Aligner(AlignConfig())
    cfg = aligner.config
    ego, peer = aligner.prepare(pts_ego), aligner.prepare(pts_peer)
    G = ground_se2(T_ego_peer)
    cloud, sample = ego.cloud(cfg.refine), aligner.refiner.sample(peer.bev)[0]
    gate = cfg.refine.gates_m[-1]
    truth = overlap_fitness(cloud, sample, G, gate)[0]
    yaw = np.arctan2(G[1, 0], G[0, 0])
    along = G[:2, 2] / np.linalg.norm(G[:2, 2])
    across = np.array([-along[1], along[0]])
    best = 0.0
    for turn in (0.0, np.pi):
        for du in np.arange(-reach_m, reach_m + 0.1, 1.0):
            if turn == 0.0 and abs(du) < 3:
                continue
            for dv in (-1.0, 0.0, 1.0):
                t = G[:2, 2] + du * along + dv * across
                best = max(best, overlap_fitness(cloud, sample, se2(yaw + turn, t[0], t[1]), gate)[0])
    return float(truth), float(best)


LATERAL_BANDS = ((0, 4), (4, 7), (7, 10), (10, 14), (14, 20), (20, 40))  # metres from the baseline


def shared_by_lateral(
    pts_ego, pts_peer, T_ego_peer, zone_m: tuple[float, float] = (20.0, 60.0), tol_m: float = 0.4
) -> list[dict]:
    """What the two cars share between them, by distance from the line joining them. The peer's lit BV pixels
    ``zone_m`` from it towards the ego (on a straight street: the stretch both see at similar ranges), per band of
    lateral distance from the baseline (LATERAL_BANDS): how many (``peer_px``), the share within ``tol_m`` of an ego
    lit pixel under the true pose (``shared``), and the ego's lit pixels in the same place (``ego_px``)."""
    from scipy.spatial import cKDTree

    from bb_align.engine.geometry import ground_se2

    G = ground_se2(T_ego_peer)
    ego, peer = make_bev(pts_ego), make_bev(pts_peer)
    a = ego.pixel_to_metre(np.argwhere(ego.image > 0))
    b = peer.pixel_to_metre(np.argwhere(peer.image > 0))
    G_inv = np.linalg.inv(G)
    toward = G_inv[:2, 2] / np.linalg.norm(G_inv[:2, 2])  # from the peer towards the ego, peer frame
    a_in_peer = a @ G_inv[:2, :2].T + G_inv[:2, 2]
    shared = cKDTree(a).query(b @ G[:2, :2].T + G[:2, 2])[0] <= tol_m

    def place(xy):  # (distance towards the ego, lateral distance from the baseline)
        return xy @ toward, np.abs(xy[:, 0] * toward[1] - xy[:, 1] * toward[0])

    (sb, lb), (sa, la) = place(b), place(a_in_peer)
    in_b, in_a = (sb >= zone_m[0]) & (sb < zone_m[1]), (sa >= zone_m[0]) & (sa < zone_m[1])
    rows = []
    for lo, hi in LATERAL_BANDS:
        mb, ma = in_b & (lb >= lo) & (lb < hi), in_a & (la >= lo) & (la < hi)
        rows.append(
            {
                "band_m": [lo, hi],
                "peer_px": int(mb.sum()),
                "shared": float(shared[mb].mean()) if mb.any() else 0.0,
                "ego_px": int(ma.sum()),
            }
        )
    return rows


def landscape_at_truth(pts_ego, pts_peer, T_ego_peer) -> tuple[bool, float]:
    """(bounded, 1-sigma along the baseline) of the engine's pose landscape (engine/landscape.py) laid around the
    true pose: whether the images pin the pose along a street at all. Unbounded (a corridor: the landscape's mass
    reaches its window's edge) gives inf. Images only: the score the engine would weigh, not its decision."""
    from bb_align import AlignConfig, Aligner
    from bb_align.engine.geometry import ground_se2
    from bb_align.engine.landscape import Fields, landscape

    aligner = Aligner(AlignConfig())
    cfg = aligner.config
    ego, peer = aligner.prepare(pts_ego), aligner.prepare(pts_peer)
    G = ground_se2(T_ego_peer)
    cloud = ego.cloud(cfg.refine)
    pts = aligner.refiner.sample(peer.bev)[0][: cfg.landscape.max_points]
    land = landscape(cloud, Fields.of(cloud, cfg.landscape), pts, G, cfg.landscape)
    if land.at_edge:
        return False, float("inf")
    along = G[:2, 2] / np.linalg.norm(G[:2, 2])
    return True, float(np.sqrt(along @ land.covariance[1:, 1:] @ along))


def real_hdl64_scans(data: Path, folder: str) -> list[np.ndarray]:
    from bb_align.io.clouds import load_cloud

    return [load_cloud(f) for f in sorted((data / folder).glob("*.bin"))]


def street_scans(n: int, seed: int = 7) -> list[np.ndarray]:
    """Both cars' scans of n street-family scenarios, HDL-64E, 73-81 m apart (make bench-sim-real's set)."""
    return [pts for pts_ego, pts_peer, _ in street_pairs(n, seed) for pts in (pts_ego, pts_peer)]


def bev_stats(points: np.ndarray, config: BevConfig | None = None) -> dict:
    cfg = config or BevConfig()
    bev = make_bev(points, cfg)
    img = bev.image
    n = img.shape[0]
    rc = np.indices(img.shape).reshape(2, -1).T
    xy = bev.pixel_to_metre(rc)
    r = np.hypot(xy[:, 0], xy[:, 1]).reshape(n, n)
    lit = img > 0
    h = bev.heights_m()
    out = {"points": int(len(points)), "lit_pixels": int(lit.sum()), "keypoints": int(len(detect_keypoints(img)))}
    px_area = cfg.resolution_m**2
    for lo, hi in RINGS:
        ring = (r >= lo) & (r < hi)
        out[f"lit_per_100m2_{lo}-{hi}m"] = float(lit[ring].sum() * 100.0 / max(ring.sum() * px_area, 1e-9))
    out["low_clutter_share"] = float(((h > 0) & (h < 1.5)).sum() / max(lit.sum(), 1))
    out["tall_share"] = float((h > 3.0).sum() / max(lit.sum(), 1))
    return out


def real_clouds(data: Path) -> dict[str, np.ndarray]:
    """Named real clouds found under the shared data folder (missing ones skipped)."""
    found = {}
    k = data / "kitti_seq08_pair" / "000000.bin"
    if k.exists():
        found["KITTI HDL-64E"] = np.fromfile(k, np.float32).reshape(-1, 4)
    for d in sorted(data.glob("av2_sensor_*")):
        f = sorted(d.glob("lidar_*.bin"))
        if f:
            found[f"AV2 2xVLP-32C ({d.name[-8:]})"] = np.fromfile(f[0], np.float32).reshape(-1, 5)
    n = data / "mmdet3d_single_scans" / "nuscenes_LIDAR_TOP_1532402927647951.pcd.bin"
    if n.exists():
        found["nuScenes 32-beam"] = np.fromfile(n, np.float32).reshape(-1, 5)
    return found


def simulated_clouds(seeds=(11, 12, 13, 14)) -> dict[str, np.ndarray]:
    from .scenario import Scenario

    out = {}
    for seed in seeds:
        sc = Scenario(seed, n_agents=2, distance_m=30.0)
        frame = sc.frame(0)
        for aid, a in frame.agents.items():
            out[f"sim seed {seed} agent {aid} {a.sensor}"] = a.points
    return out


def figure(clouds: dict[str, np.ndarray], path: Path, cols: int = 4) -> None:
    from bb_align.io.plot import pyplot

    plt = pyplot()

    rows = int(np.ceil(len(clouds) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 4.2 * rows))
    for ax in np.atleast_1d(axes).ravel():
        ax.axis("off")
    for ax, (name, pts) in zip(np.atleast_1d(axes).ravel(), clouds.items()):
        img = make_bev(pts).image
        ax.imshow(img > 0, cmap="gray", interpolation="nearest")
        ax.set_title(f"{name}\n{int((img > 0).sum())} lit px", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def pair_overlay(seed: int, distance_m: float, path: Path) -> None:
    """Ego BV (red) and peer BV moved into the ego frame with the true pose (green): the common view."""
    from bb_align.io.plot import pyplot

    plt = pyplot()

    from .scenario import Scenario

    frame = Scenario(seed, n_agents=2, distance_m=distance_m).frame(0)
    ego, peer = frame.agents["0"], frame.agents["1"]
    T = np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor
    pts = peer.points[:, :3] @ T[:3, :3].T + T[:3, 3]
    a, b = make_bev(ego.points).image > 0, make_bev(pts).image > 0
    rgb = np.zeros(a.shape + (3,))
    rgb[..., 0], rgb[..., 1] = a, b
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.imshow(rgb, interpolation="nearest")
    ax.set_title(
        f"sim seed {seed}: ego {ego.sensor} (red), peer {peer.sensor} (green) at the true pose,\n"
        f"{np.hypot(*T[:2, 3]):.0f} m apart; yellow = both see it",
        fontsize=8,
    )
    ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[4] / "shared" / "data")
    ap.add_argument("--street", type=int, default=12, help="street-family scenarios for the band profile")
    ap.add_argument("--alias", type=int, default=0, help="pairs for the along-street alias (real KITTI 00 and street)")
    ap.add_argument(
        "--landscape", type=int, default=0, help="street pairs for the landscape at the truth (and all real far pairs)"
    )
    ap.add_argument(
        "--shared", type=int, default=0, help="street pairs (de-skewed) for what two cars share, by lateral band"
    )
    args = ap.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    street_profiles(args)
    if args.alias:
        alias_table(args)
    if args.landscape:
        landscape_table(args)
    if args.shared:
        shared_table(args)
    real = real_clouds(args.data) if args.data.is_dir() else {}
    sim = simulated_clouds()
    stats = {"real": {k: bev_stats(v) for k, v in real.items()}, "sim": {k: bev_stats(v) for k, v in sim.items()}}
    (args.out_dir / "bev_stats.json").write_text(json.dumps(stats, indent=2))
    figure({**real, **dict(list(sim.items())[:4])}, args.out_dir / "bev_real_vs_sim.png")
    figure(dict(list(sim.items())[4:]), args.out_dir / "bev_sim_more.png")
    pair_overlay(21, 25.0, args.out_dir / "pair_overlay_25m.png")
    pair_overlay(22, 55.0, args.out_dir / "pair_overlay_55m.png")
    for group, d in stats.items():
        for name, s in d.items():
            print(
                f"{group:4s} {name:40s} "
                + " ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in s.items())
            )


def street_profiles(args) -> None:
    """Lit pixels by band: the street family against the KITTI 00 scans it was tuned on and held-out HDL-64E scans."""
    from tqdm import tqdm

    sets = {}
    for name, folder in tqdm({**TUNED, **HELD_OUT}.items(), desc="real"):
        if (args.data / folder).is_dir():
            sets[name] = band_profile(real_hdl64_scans(args.data, folder))
    street = street_scans(args.street)
    sets["sim street family, 73-81 m"] = band_profile(street)
    real = {}
    for folder, frame in (("kitti00_run_far", "000094"), ("kitti00_run_far", "000000"), ("kitti08_run", "000000")):
        if (args.data / folder / f"{frame}.bin").exists():
            real[f"{folder} {frame} (real)"] = real_hdl64_scans(args.data, folder)[0 if frame == "000000" else -2]
    figure(
        {**real, **{f"sim street {i // 2} car {i % 2}": street[i] for i in range(0, 6, 2)}},
        args.out_dir / "street_real_vs_sim.png",
        cols=3,
    )
    (args.out_dir / "street_profile.json").write_text(json.dumps(sets, indent=2))
    print(
        "| scans | n | lit 0-20 / 20-40 / 40-70 / 70-100 m, median | 25th-75th percentile | within 7 m of the axis |"
        " nearest tall thing left / right, m |"
    )
    print("| --- | ---: | --- | --- | --- | --- |")
    for name, p in sets.items():
        quart = " / ".join(f"{a}-{b}" for a, b in zip(p["q25"], p["q75"]))
        lane = " / ".join(map(str, p["carriageway_median"]))
        side = " / ".join(map(str, p["nearest_tall_median_m"]))
        print(f"| {name} | {p['scans']} | {' / '.join(map(str, p['median']))} | {quart} | {lane} | {side} |")


def kitti00_far_pairs(data: Path):
    """(ego points, peer points, T_ego_peer) of the real KITTI 00 pairs 73-80 m apart (lab.realpairs.kitti00_far)."""
    from bb_align.io.clouds import load_cloud
    from bb_align.lab.realpairs import kitti00_far

    for pair in kitti00_far(data):
        yield load_cloud(pair.ego), load_cloud(pair.peer), pair.T_ref


def street_pairs(n: int, seed: int = 7, lo: float = 73.0, hi: float = 81.0, distortion: bool = True):
    """(ego points, peer points, T_ego_peer) of n street-family pairs, HDL-64E, spaced evenly over [lo, hi] m."""
    from .scenario import Scenario, SimConfig

    cfg = SimConfig(family="street", fleet=("hdl64",), distortion=distortion)
    for i in range(n):
        d = lo + (hi - lo) * (i + 0.5) / n
        frame = Scenario(seed * 100003 + i, 2, d, cfg).frame(0)
        e, p = frame.agents["0"], frame.agents["1"]
        yield e.points, p.points, np.linalg.inv(e.T_world_sensor) @ p.T_world_sensor


def landscape_table(args) -> None:
    """landscape_at_truth on every KITTI 00 far pair, the KITTI 08 16 m pair (held out) and street-family pairs at
    73-81 m and at 16 m: how many are a corridor, and the median 1-sigma along the street of the bounded ones."""
    from tqdm import tqdm

    from bb_align.io.clouds import load_cloud as load

    k08 = args.data / "kitti_seq08_pair"
    sets = {
        "KITTI 00, 73-80 m (tuned on)": kitti00_far_pairs(args.data),
        "KITTI 08, 16 m (held out)": [
            (load(k08 / "000000.bin"), load(k08 / "000049.bin"), np.loadtxt(k08 / "T_velo0_velo49_icp_refined.txt"))
        ],
    }
    sets["sim street family, 73-81 m"] = street_pairs(args.landscape)
    sets["sim street family, 16 m"] = street_pairs(max(1, args.landscape // 4), lo=15.5, hi=16.5)
    out = {}
    for name, pairs in sets.items():
        rows = [landscape_at_truth(*p) for p in tqdm(pairs, desc=name)]
        bounded = [s for ok, s in rows if ok]
        out[name] = {
            "pairs": len(rows),
            "corridor": len(rows) - len(bounded),
            "sigma_along_median_m": float(np.median(bounded)) if bounded else None,
        }
    (args.out_dir / "street_landscape.json").write_text(json.dumps(out, indent=2))
    print("| pairs | n | landscape at the truth a corridor | 1-sigma along the street, median of the bounded |")
    print("| --- | ---: | ---: | ---: |")
    for k, v in out.items():
        sig = "-" if v["sigma_along_median_m"] is None else f"{v['sigma_along_median_m']:.2f} m"
        print(f"| {k} | {v['pairs']} | {v['corridor']} / {v['pairs']} | {sig} |")


def alias_table(args) -> None:
    """along_street_alias on KITTI 00 pairs (frames 0, 3, 6, 9 against 94, 95) and as many street-family pairs."""
    far = args.data / "kitti00_run_far"
    rows = {"KITTI 00, 73-80 m": [], "sim street family, 73-81 m": []}
    scans = real_hdl64_scans(args.data, "kitti00_run_far")
    for a in (0, 3, 6, 9)[: max(1, args.alias // 2)]:
        for j, b in enumerate((94, 95)):
            T = np.loadtxt(far / f"T_{a}_{b}.txt")
            rows["KITTI 00, 73-80 m"].append(along_street_alias(scans[a], scans[10 + j], T))
    for pts_ego, pts_peer, T in street_pairs(args.alias):
        rows["sim street family, 73-81 m"].append(along_street_alias(pts_ego, pts_peer, T))
    out = {
        k: np.median(np.array(v), axis=0).tolist() + [int(sum(b > t for t, b in v)), len(v)] for k, v in rows.items()
    }
    (args.out_dir / "street_alias.json").write_text(json.dumps(out, indent=2))
    for k, (t, b, above, n) in out.items():
        print(f"| {k} | {t:.3f} | {b:.3f} | {above} / {n} |")


def shared_table(args) -> None:
    """shared_by_lateral summed over the real KITTI 00 far pairs and over street-family pairs (de-skewed, as the
    real scans are): per lateral band the peer's pixels per pair, their shared share and the ego's pixels per pair."""
    from tqdm import tqdm

    sets = {
        "real: KITTI 00, 73-80 m": [shared_by_lateral(*p) for p in tqdm(kitti00_far_pairs(args.data), desc="real")],
        "sim street family, 73-81 m": [
            shared_by_lateral(*p)
            for p in tqdm(street_pairs(args.shared, distortion=False), total=args.shared, desc="street")
        ],
    }
    (args.out_dir / "shared_by_lateral.json").write_text(json.dumps(sets, indent=1))
    print("| set | pairs | " + " | ".join(f"{lo}-{hi} m" for lo, hi in LATERAL_BANDS) + " |")
    print("| --- | ---: |" + " --- |" * len(LATERAL_BANDS))
    for name, rows in sets.items():
        cells = []
        for k in range(len(LATERAL_BANDS)):
            peer = sum(r[k]["peer_px"] for r in rows)
            hit = sum(r[k]["peer_px"] * r[k]["shared"] for r in rows)
            ego = sum(r[k]["ego_px"] for r in rows)
            cells.append(f"{peer / len(rows):.0f} ({hit / max(peer, 1):.2f}) / {ego / len(rows):.0f}")
        print(f"| {name} | {len(rows)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
