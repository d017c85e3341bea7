"""The anatomy of the engine's alias: which keypoints support the truth and which its best alias, on real far pairs
and simulated ones.

    .venv/bin/python benchmarks/alias_anatomy.py --data /work/shared/data --sim out/sim_street --pairs 6

Per pair (real: KITTI 00 at 73-80 m; simulated: a street-family run's pairs at least 73 m apart), the engine runs
once without a prior; its truth hypothesis (the best within 3 m / 3 deg of the reference, else the reference
itself), its best alias (the best by dense overlap more than 3 m or 3 deg away) and the image-only near-field
overlay (the peer slid along the baseline to within 25 m of the ego, either heading, best dense overlap:
``realism.along_street_alias`` kept near) are each scored on the same keypoints the acquisition votes with:

- geometric: peer keypoints with ANY ego keypoint within the inlier threshold (the acquisition's, 2 m) under the
  pose, descriptors ignored: how far the detector's keypoints coincide;
- top-k / top-1: peer keypoints with one of their acquire.top_k (or their nearest) descriptor candidates within
  the threshold: the keypoint matches the vote counts;
- where the top-k inliers sit: the peer keypoint's range from its own sensor (0-20 / 20-40 / 40+ m) and what the
  peer's points around it are (low: under 2.3 m above the local ground, i.e. cars, fences, bushes, kerbs; wall: a
  tall, straight line of points; tall: other tall things, i.e. crowns, poles, building corners).

Medians per set as markdown and JSON (docs/sim/alias_anatomy.*) and a plot.

``--baselines``: how the descriptors of the same place agree as the baseline grows: the share of geometrically
coincident peer keypoints (at the known pose) whose partner is among their top-k descriptor candidates, by class,
for real KITTI 00 frames 0.7 m, 4-7 m and 73-80 m apart (one car), the street family's two cars 7 / 20 / 40 / 77 m
apart, one simulated car's frames ~7 and ~77 m apart, and one simulated pose rendered twice (only the per-ray
randomness differs: foliage pass-through, facade relief, noise, dropout).

``--fov``: the same agreement on the real 73-80 m pairs with their returns clipped above 2.0 and 1.0 deg of
elevation, and on the street family's two cars 77 m apart with the HDL-64E model's top beam raised from 2.0 to
2.8 deg (a probe: the model is patched in this process only).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from bb_align import Aligner
from bb_align.engine.acquisition.model import SearchMemo
from bb_align.engine.geometry import ground_se2, pose_error, se2
from bb_align.engine.refine import overlap_fitness
from bb_align.lab.recording import RECORD_HELP, output_path

BANDS = (20.0, 40.0)  # peer keypoint range bands: 0-20, 20-40, 40+ m
CLASSES = ("low", "wall", "tall")
LOW_M = 2.3  # taller than any car or van above the local ground
NEAR_M = 25.0
RANGES = ((0.0, 20.0), (20.0, 40.0), (40.0, 60.0), (60.0, np.inf))  # peer keypoint range, the truth's breakdown
POSES = ("truth", "alias", "overlay")  # an alias placing the peer this close to the ego is a near-field overlay


def classify(pts: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Each keypoint's class from the cloud around it (sensor frame): low / wall / tall (module doc)."""
    tree = cKDTree(pts[:, :2])
    out = []
    for p in xy:
        near = pts[tree.query_ball_point(p, 3.0)]
        if len(near) < 5:
            out.append("low")
            continue
        ground = np.percentile(near[:, 2], 10)
        close = pts[tree.query_ball_point(p, 0.8)]
        top = (close[:, 2].max() if len(close) else ground) - ground
        if top < LOW_M:
            out.append("low")
            continue
        tall = near[near[:, 2] - ground > LOW_M][:, :2]
        ev = np.linalg.eigvalsh(np.cov(tall.T)) if len(tall) >= 5 else np.array([1.0, 1.0])
        out.append("wall" if ev[0] < 0.03 * ev[1] else "tall")
    return np.asarray(out)


def support(T: np.ndarray, kp_peer, kp_ego, cand, thr: float) -> dict:
    """Keypoint support for the pose T (ego <- peer, 3x3): geometric, top-1 and top-k counts and the top-k mask."""
    mapped = kp_peer @ T[:2, :2].T + T[:2, 2]
    d_geo, _ = cKDTree(kp_ego).query(mapped)
    d_cand = np.linalg.norm(kp_ego[cand] - mapped[:, None, :], axis=2)  # (Q, k)
    inl = (d_cand < thr).any(axis=1)
    return {
        "geo_mask": d_geo < thr,
        "geometric": int((d_geo < thr).sum()),
        "top1": int((d_cand[:, 0] < thr).sum()),
        "topk": int(inl.sum()),
        "mask": inl,
        "ego_range": np.linalg.norm(kp_ego[cand][np.arange(len(cand)), np.argmin(d_cand, axis=1)], axis=1),
    }


def where(mask: np.ndarray, kp_peer: np.ndarray, classes: np.ndarray, ego_range: np.ndarray) -> dict:
    """The top-k inliers by peer range band, by class, and how many sit within 20 m of the ego too."""
    r = np.linalg.norm(kp_peer[mask], axis=1)
    edges = [0.0, *BANDS, np.inf]
    return {
        "bands": [int(((r >= a) & (r < b)).sum()) for a, b in zip(edges[:-1], edges[1:], strict=True)],
        "classes": {c: int((classes[mask] == c).sum()) for c in CLASSES},
        "near_both": int(((r < BANDS[0]) & (ego_range[mask] < BANDS[0])).sum()),
    }


def near_overlay(ego_cloud, sample, G: np.ndarray, gate: float) -> np.ndarray:
    """The image-only near-field overlay: the pose with the best dense overlap among the peer slid along the
    baseline (every metre, +-1 m across, at the truth's yaw and turned by half a turn) to within NEAR_M of the ego
    (``realism.along_street_alias``'s search, kept near)."""
    yaw = np.arctan2(G[1, 0], G[0, 0])
    dist = np.linalg.norm(G[:2, 2])
    along = G[:2, 2] / dist
    across = np.array([-along[1], along[0]])
    best, best_T = -1.0, G
    for turn in (0.0, np.pi):
        for du in np.arange(-dist - NEAR_M, -dist + NEAR_M + 0.1, 1.0):
            for dv in (-1.0, 0.0, 1.0):
                t = G[:2, 2] + du * along + dv * across
                T = se2(yaw + turn, t[0], t[1])
                fit = overlap_fitness(ego_cloud, sample, T, gate)[0]
                if fit > best:
                    best, best_T = fit, T
    return best_T


def measure(aligner: Aligner, name: str, T_ref: np.ndarray, pts_ego, pts_peer) -> dict:
    cfg = aligner.config
    ego, peer = aligner.prepare(pts_ego), aligner.prepare(pts_peer)
    G = ground_se2(T_ref)
    result = aligner.align(ego, peer)
    hyps = [] if result.acquisition is None else result.acquisition.hypotheses
    near_truth = [h for h in hyps if max(pose_error(h.T, G)) <= 3]
    aliases = sorted((h for h in hyps if max(pose_error(h.T, G)) > 3), key=lambda h: -h.fitness)
    rows, cand = aligner.acquirer.candidates(ego, peer, SearchMemo())
    kp_peer, kp_ego = peer.keypoints_xy[rows], ego.keypoints_xy
    classes = classify(np.asarray(pts_peer)[:, :3], kp_peer)
    thr = cfg.ransac.inlier_threshold_m
    truth_T = max(near_truth, key=lambda h: h.fitness).T if near_truth else G
    ego_cloud, sample = ego.cloud(cfg.refine), aligner.refiner.sample(peer.bev)[0]
    row = {"pair": name, "keypoints_peer": len(kp_peer), "keypoints_ego": len(kp_ego), "truth_formed": bool(near_truth)}
    overlay = near_overlay(ego_cloud, sample, G, cfg.refine.gates_m[-1])
    for key, T in (("truth", truth_T), ("alias", aliases[0].T if aliases else None), ("overlay", overlay)):
        if T is None:
            row[key] = None
            continue
        s = support(T, kp_peer, kp_ego, cand, thr)
        yaw = float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))
        fit = overlap_fitness(ego_cloud, sample, T, cfg.refine.gates_m[-1])[0]
        row[key] = {
            "pose": [yaw, float(T[0, 2]), float(T[1, 2])],
            "fitness": float(fit),
            **{k: s[k] for k in ("geometric", "top1", "topk")},
            **where(s["mask"], kp_peer, classes, s["ego_range"]),
            "geometric_classes": {c: int((classes[s["geo_mask"]] == c).sum()) for c in CLASSES},
        }
        if key == "truth":  # per class and peer range: keypoints, how many coincide, how many the vote counts
            r = np.linalg.norm(kp_peer, axis=1)
            row["truth_by_range"] = {
                c: [
                    [int(m.sum()), int((m & s["geo_mask"]).sum()), int((m & s["mask"]).sum())]
                    for m in ((classes == c) & (r >= lo) & (r < hi) for lo, hi in RANGES)
                ]
                for c in CLASSES
            }
    row["near_field_alias"] = bool(row["alias"] and np.hypot(*row["alias"]["pose"][1:]) < NEAR_M)
    row["classes_all"] = {c: int((classes == c).sum()) for c in CLASSES}
    row["success"] = bool(result.success)
    return row


def real_pairs(data: Path, n: int):
    from bb_align.io.clouds import load_cloud
    from bb_align.lab.realpairs import kitti00_far

    far = kitti00_far(data)
    for p in far[:: max(1, len(far) // n)][:n]:
        yield p.name, p.T_ref, load_cloud(p.ego), load_cloud(p.peer)


def sim_pairs(root: Path, n: int, min_m: float = 73.0):
    from itertools import islice

    from bb_align.lab.realpairs import simulated_pairs

    for pair, pts_ego, pts_peer in islice(simulated_pairs(root, min_m), n):
        yield pair.name, pair.T_ref, pts_ego, pts_peer


def summary(rows: list[dict]) -> dict:
    """Medians of the counts for the truth and the alias, and the share of inliers by band and class."""
    out = {"pairs": len(rows), "near_field_alias": sum(r["near_field_alias"] for r in rows)}
    for key in POSES:
        rs = [r[key] for r in rows if r[key]]
        out[key] = {k: float(np.median([r[k] for r in rs])) for k in ("fitness", "geometric", "top1", "topk")}
        tot = max(1, sum(r["topk"] for r in rs))
        out[key]["bands"] = [round(sum(r["bands"][i] for r in rs) / tot, 3) for i in range(3)]
        out[key]["classes"] = {c: round(sum(r["classes"][c] for r in rs) / tot, 3) for c in CLASSES}
        out[key]["near_both"] = round(sum(r["near_both"] for r in rs) / tot, 3)
    out["alias_topk_above_truth"] = sum(bool(r["alias"] and r["alias"]["topk"] > r["truth"]["topk"]) for r in rows)
    out["overlay_topk_above_truth"] = sum(r["overlay"]["topk"] > r["truth"]["topk"] for r in rows)
    out["alias_geometric_above_truth"] = sum(
        bool(r["alias"] and r["alias"]["geometric"] > r["truth"]["geometric"]) for r in rows
    )
    out["truth_by_range"] = {
        c: [[sum(r["truth_by_range"][c][k][j] for r in rows) for j in range(3)] for k in range(len(RANGES))]
        for c in CLASSES
    }
    n_all = {c: sum(r["classes_all"][c] for r in rows) for c in CLASSES}
    out["classes_all"] = {c: round(v / max(1, sum(n_all.values())), 3) for c, v in n_all.items()}
    return out


def shares(by_class: dict) -> str:
    return " / ".join(f"{by_class[c]:.2f}" for c in CLASSES)


def table(sets: dict[str, dict], command: str) -> str:
    lines = [
        "# The engine's alias beside the truth: keypoint support",
        "",
        f"Made by `{command}`. Medians per set (no prior). Geometric: peer keypoints with any ego keypoint within",
        "2 m under the pose; top-1 / top-k: with their nearest / one of their 12 nearest descriptor candidates",
        "within 2 m (what the vote counts). Shares: of all top-k inliers, by the peer keypoint's range and class",
        "(low < 2.3 m: cars, fences, bushes; wall: a straight tall line; tall: crowns, poles, corners); near both:",
        "within 20 m of both sensors.",
        "",
        "| set | pose | overlap | geometric | top-1 | top-k | 0-20 / 20-40 / 40+ m | low / wall / tall | near both |",
        "| --- | --- | ---: | ---: | ---: | ---: | --- | --- | ---: |",
    ]
    for name, s in sets.items():
        for key in POSES:
            m = s[key]
            lines.append(
                f"| {name} | {key} | {m['fitness']:.3f} | {m['geometric']:.0f} | {m['top1']:.0f} | {m['topk']:.0f} | "
                f"{' / '.join(f'{b:.2f}' for b in m['bands'])} | "
                f"{shares(m['classes'])} | {m['near_both']:.2f} |"
            )
    lines += [
        "",
        "| set | pairs | near-field alias | alias top-k > truth's | alias geometric > truth's | "
        "overlay top-k > truth's | keypoints low / wall / tall |",
        "| --- | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for name, s in sets.items():
        lines.append(
            f"| {name} | {s['pairs']} | {s['near_field_alias']} | {s['alias_topk_above_truth']} | "
            f"{s['alias_geometric_above_truth']} | {s['overlay_topk_above_truth']} | {shares(s['classes_all'])} |"
        )
    lines += [
        "",
        "The truth's keypoints by the peer keypoint's range and class, summed over the pairs: peer keypoints / with an",
        "ego keypoint within 2 m at the truth / of those, found by their descriptor candidates (top-k).",
        "",
        "| set | class | "
        + " | ".join(f"{lo:.0f}-{hi:.0f} m" if np.isfinite(hi) else f"{lo:.0f}+ m" for lo, hi in RANGES)
        + " |",
        "| --- | --- |" + " --- |" * len(RANGES),
    ]
    for name, s in sets.items():
        for c in CLASSES:
            cells = " | ".join(" / ".join(map(str, v)) for v in s["truth_by_range"][c])
            lines.append(f"| {name} | {c} | {cells} |")
    return "\n".join(lines) + "\n"


def plot(sets_rows: dict[str, list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key in zip(axes, ("geometric", "topk"), strict=True):
        for (name, rows), marker in zip(sets_rows.items(), "os^", strict=False):
            pts = [(r["truth"][key], r["alias"][key]) for r in rows if r["alias"]]
            if pts:
                ax.scatter(*np.array(pts).T, marker=marker, label=name)
        lim = ax.get_xlim()[1]
        ax.plot([0, lim], [0, lim], "k:", lw=1)
        ax.set_xlabel(f"{key} support of the truth")
        ax.set_ylabel(f"{key} support of the best alias")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def agreement(pairs) -> dict:
    """Top-k and top-1 inliers over geometric coincidences at the known pose, overall and by class (summed)."""
    aligner = Aligner()
    thr = aligner.config.ransac.inlier_threshold_m
    geo, top1, topk = 0, 0, 0
    by = {c: [0, 0] for c in CLASSES}
    for pts_a, pts_b, T_a_b in pairs:
        a, b = aligner.prepare(pts_a), aligner.prepare(pts_b)
        rows, cand = aligner.acquirer.candidates(a, b, SearchMemo())
        kp_b = b.keypoints_xy[rows]
        cls = classify(np.asarray(pts_b)[:, :3], kp_b)
        s = support(ground_se2(T_a_b), kp_b, a.keypoints_xy, cand, thr)
        geo, top1, topk = geo + s["geometric"], top1 + s["top1"], topk + s["topk"]
        for c in CLASSES:
            by[c][0] += int((s["geo_mask"] & (cls == c)).sum())
            by[c][1] += int((s["mask"] & (cls == c)).sum())
    return {
        "geometric": geo,
        "topk_share": topk / max(1, geo),
        "top1_share": top1 / max(1, geo),
        "by_class": {c: round(k / max(1, g), 3) for c, (g, k) in by.items()},
    }


def baseline_sets(data: Path, n: int = 4) -> dict:
    """name -> (pts_a, pts_b, T_a_b) generator for each ``--baselines`` row (module doc)."""
    from bb_align.io.clouds import load_cloud
    from bb_align.lab.sim.raycast import cast_sweep
    from bb_align.lab.sim.scenario import Scenario, SimConfig

    far = data / "kitti00_run_far"
    cfg = SimConfig(family="street", fleet=("hdl64",), distortion=False)

    def real(pairs):
        for i, j in pairs:
            yield load_cloud(far / f"{i:06d}.bin"), load_cloud(far / f"{j:06d}.bin"), np.loadtxt(far / f"T_{i}_{j}.txt")

    def two_cars(d):
        for i in range(n):
            e, p = Scenario(7 * 100003 + i, 2, d, cfg).frame(0).agents.values()
            yield e.points, p.points, np.linalg.inv(e.T_world_sensor) @ p.T_world_sensor

    def one_car(d):
        moving = cfg.model_copy(update={"stopped_prob": 0.0})
        for i in range(n):
            sc = Scenario(7 * 100003 + i, 2, 77.0, moving)
            k = max(1, round(d / (0.1 * sc.world.vehicles[sc.agents[1].vehicle].speed)))
            a, b = sc.frame(0).agents["1"], sc.frame(k).agents["1"]
            yield a.points, b.points, np.linalg.inv(a.T_world_sensor) @ b.T_world_sensor

    def rerendered():
        for i in range(n):
            sc = Scenario(7 * 100003 + i, 2, 77.0, cfg)
            a, spec = sc.frame(0).agents["1"], sc.agents[1]
            rng = np.random.default_rng([99, i])
            again = cast_sweep(sc.world, spec.vehicle, spec.sensor, spec.mount, spec.phase_s, rng, spec.beam_error_deg,
                               distortion=False)  # fmt: skip
            yield a.points, again.points, np.eye(4)

    return {
        "real, one car, 0.7 m": real([(i, i + 1) for i in range(0, 2 * n, 2)]),
        "real, one car, 4-7 m": real([(0, j) for j in range(10 - n, 10)]),
        "real, one car, 73-80 m": real([(i, 94) for i in range(n)]),
        "sim, one pose rendered twice": rerendered(),
        "sim, one car, ~7 m": one_car(7.0),
        "sim, two cars, 7 m": two_cars(7.0),
        "sim, two cars, 20 m": two_cars(20.0),
        "sim, two cars, 40 m": two_cars(40.0),
        "sim, one car, ~77 m": one_car(77.0),
        "sim, two cars, 77 m": two_cars(77.0),
    }


def baselines(data: Path, out: Path) -> None:
    rows = {name: agreement(tqdm(gen, desc=name, total=4)) for name, gen in baseline_sets(data).items()}
    lines = [
        "# Descriptor agreement against the baseline",
        "",
        "Made by `python benchmarks/alias_anatomy.py --baselines`. Of the peer keypoints with an ego keypoint",
        "within 2 m at the known pose (geometric), the share with that partner among their 12 nearest descriptor",
        "candidates (top-k) or as the nearest (top-1), by the peer keypoint's class; 4 pairs per row, summed.",
        "",
        "| pairs | geometric | top-k share | top-1 share | low / wall / tall top-k share |",
        "| --- | ---: | ---: | ---: | --- |",
    ]
    for name, r in rows.items():
        lines.append(
            f"| {name} | {r['geometric']} | {r['topk_share']:.2f} | {r['top1_share']:.2f} | {shares(r['by_class'])} |"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def clipped(pts: np.ndarray, max_deg: float) -> np.ndarray:
    """The returns at most max_deg above the sensor's horizon."""
    return pts[np.degrees(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1]))) <= max_deg]


def fov(data: Path, out: Path, n: int = 4) -> None:
    from bb_align.io.clouds import load_cloud
    from bb_align.lab.sim import sensors
    from bb_align.lab.sim.scenario import Scenario, SimConfig

    far = data / "kitti00_run_far"
    rows = {}
    for max_deg in (90.0, 2.0, 1.0):
        pairs = [
            (clipped(load_cloud(far / f"{i:06d}.bin"), max_deg), clipped(load_cloud(far / "000094.bin"), max_deg),
             np.loadtxt(far / f"T_{i}_94.txt"))
            for i in range(n)
        ]  # fmt: skip
        rows[f"real, one car, 73-80 m, returns <= {max_deg:g} deg"] = agreement(pairs)
    model = sensors.SENSOR_MODELS["hdl64"]
    upper = np.linspace(2.8, -8.33, 32)
    lower = np.asarray(model.elevations_deg)[32:]
    sensors.SENSOR_MODELS["hdl64"] = model.model_copy(
        update={"elevations_deg": tuple(np.round(np.r_[upper, lower], 3))}
    )
    try:
        cfg = SimConfig(family="street", fleet=("hdl64",), distortion=False)
        frames = [Scenario(7 * 100003 + i, 2, 77.0, cfg).frame(0).agents.values() for i in range(n)]
        rows["sim, two cars, 77 m, top beam 2.8 deg"] = agreement(
            (e.points, p.points, np.linalg.inv(e.T_world_sensor) @ p.T_world_sensor) for e, p in frames
        )
    finally:
        sensors.SENSOR_MODELS["hdl64"] = model
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    for name, r in rows.items():
        print(
            f"| {name} | {r['geometric']} | {r['topk_share']:.2f} | {r['top1_share']:.2f} | {shares(r['by_class'])} |"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="the shared data folder (holds kitti00_run_far)")
    ap.add_argument("--sim", action="append", default=[], help="NAME=FOLDER of a simulated run (repeatable)")
    ap.add_argument("--pairs", type=int, default=6, help="pairs per set")
    ap.add_argument(
        "--out", type=Path, default=None, help="default: out/sim/alias_anatomy (docs/sim/alias_anatomy with --record)"
    )
    ap.add_argument("--record", action="store_true", help=RECORD_HELP)
    ap.add_argument("--baselines", action="store_true", help="descriptor agreement against the baseline instead")
    ap.add_argument("--fov", action="store_true", help="the upper field of view's part in the agreement instead")
    args = ap.parse_args()
    args.out = args.out or output_path("docs/sim/alias_anatomy", args.record)
    if args.fov:
        fov(args.data, args.out.with_name("descriptor_fov"))
        return
    if args.baselines:
        baselines(args.data, args.out.with_name("descriptor_baselines"))
        return
    aligner = Aligner()
    sources = {"real: KITTI 00": real_pairs(args.data, args.pairs)}
    for spec in args.sim:
        name, folder = spec.split("=", 1)
        sources[name] = sim_pairs(Path(folder), args.pairs)
    rows = {
        name: [measure(aligner, *p) for p in tqdm(src, desc=name, total=args.pairs)] for name, src in sources.items()
    }
    sets = {name: summary(rs) for name, rs in rows.items()}
    command = "python benchmarks/alias_anatomy.py " + " ".join(
        [f"--pairs {args.pairs}", *(f'--sim "{s}"' for s in args.sim)]
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"sets": sets, "rows": rows}, indent=1, default=float))
    args.out.with_suffix(".md").write_text(table(sets, command))
    plot(rows, args.out.with_suffix(".png"))
    print(table(sets, command))


if __name__ == "__main__":
    main()
