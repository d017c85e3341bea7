"""Point-to-plane ICP on the full clouds, started from the same prior as bb-align, beside bb-align's answer: the
yardstick of issue 44 ("accuracy at range at least that of a point-to-plane ICP started from the same prior").

    make bench-icp            (or, by hand:)
    .venv/bin/python benchmarks/icp_from_prior.py --data ../shared/data            # -> out/icp_from_prior/
    .venv/bin/python benchmarks/icp_from_prior.py --data ../shared/data --record   # -> docs/real_pairs/icp_from_prior.*
    .venv/bin/python benchmarks/icp_from_prior.py --data ../shared/data --bb-records docs/real_pairs/records.jsonl
        (bb-align's side read from a `bb-align real-pairs` run instead of aligned again)

Every pair `bb-align real-pairs` finds (bb_align.lab.realpairs.discover) gets its seeded 2 m / 2 deg prior
(``seeded_prior``: the same on every run, the one `bb-align real-pairs` gives the engine). ICP (small_gicp's
PLANE_ICP, the `bench` extra; never used by the engine) starts from that prior lifted to 3-D as the engine receives
it (z = 0, level: a ground-plane prior) on the full clouds (x, y, z of every point, voxel-downsampled to
``IcpSettings.voxel_m``, normals from ``neighbours`` nearest points) and runs a schedule of maximum correspondence
distances, each stage started where the last stopped. The first stage's 5 m covers the prior's worst displacement
of a point at the far end of the overlap (2 m + 2 deg x 80 m = 4.8 m); the last is twice the voxel. The schedule
was set from that reasoning before any pair was run, not tuned on the pairs.

Per pair: ICP's ground-plane error against the reference (m, deg, and along / across the baseline as
`bb-align real-pairs` splits it), its own claims (the last stage's ``converged``; fitness = inliers of the last
stage / downsampled peer points), its time (preprocessing both clouds, registration); beside bb-align's answer with
the same prior (right / wrong / refused, error). ICP has no refusal: its every answer counts, right when within
1 m and 1 deg. On a pair without overlap (no reference) the table gives what ICP claims there and how far its
answer lies from the dataset's own poses.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bb_align.engine.geometry import ground_se2, pose_error, se3_from_se2
from bb_align.lab.realpairs import RIGHT_DEG, RIGHT_M, RealPair, discover, seeded_prior

DEFAULT_OUT = Path("out/icp_from_prior")
RECORD_DIR = Path("docs/real_pairs")  # --record: icp_from_prior.{jsonl,json,md} here


@dataclass(frozen=True)
class IcpSettings:
    voxel_m: float = 0.25  # downsampling of both full clouds
    neighbours: int = 20  # points per normal estimate
    schedule_m: tuple[float, ...] = (5.0, 2.0, 1.0, 0.5)  # max correspondence distance per stage (module doc)
    iterations: int = 30  # per stage
    threads: int = 1
    method: str = "PLANE_ICP"  # small_gicp's registration type: PLANE_ICP (the yardstick) or GICP


@dataclass
class IcpAnswer:
    T: np.ndarray  # 4x4 T_ego_peer (p_ego = T @ p_peer)
    converged: bool  # the last stage's own claim
    fitness: float  # inliers of the last stage / downsampled peer points
    inliers: int
    iterations: int  # over all stages
    prepare_ms: float
    register_ms: float


def icp(ego_points: np.ndarray, peer_points: np.ndarray, T_init: np.ndarray, settings: IcpSettings) -> IcpAnswer:
    """Point-to-plane ICP of the peer cloud onto the ego cloud from ``T_init`` (4x4, or a 3x3 ground-plane pose
    lifted level at z = 0): T_ego_peer, mapping the peer's points into the ego's frame."""
    import small_gicp  # the `bench` extra; imported here so the suite imports this script without it

    T = np.asarray(T_init, dtype=np.float64)
    if T.shape == (3, 3):
        T = se3_from_se2(T)
    if T.shape != (4, 4):
        raise ValueError(f"T_init: a 3x3 or 4x4 transform, got shape {T.shape}")
    t0 = time.perf_counter()
    clouds = [
        small_gicp.preprocess_points(
            np.ascontiguousarray(p[:, :3], dtype=np.float64),
            downsampling_resolution=settings.voxel_m,
            num_neighbors=settings.neighbours,
            num_threads=settings.threads,
        )
        for p in (ego_points, peer_points)
    ]
    (target, target_tree), (source, _) = clouds
    t1 = time.perf_counter()
    iterations = 0
    result = None
    for max_dist in settings.schedule_m:
        result = small_gicp.align(
            target,
            source,
            target_tree,
            init_T_target_source=T,
            registration_type=settings.method,
            max_correspondence_distance=max_dist,
            num_threads=settings.threads,
            max_iterations=settings.iterations,
        )
        T = np.asarray(result.T_target_source)
        iterations += int(result.iterations)
    t2 = time.perf_counter()
    return IcpAnswer(
        T=T,
        converged=bool(result.converged),
        fitness=float(result.num_inliers) / max(source.size(), 1),
        inliers=int(result.num_inliers),
        iterations=iterations,
        prepare_ms=(t1 - t0) * 1e3,
        register_ms=(t2 - t1) * 1e3,
    )


@dataclass
class Row:
    pair: str
    group: str
    distance_m: float
    icp_right: bool | None  # None: no reference (a pair without overlap)
    icp_t_err_m: float | None
    icp_r_err_deg: float | None
    icp_along_m: float | None  # signed, along the baseline (ego sensor -> peer sensor)
    icp_across_m: float | None
    icp_off_poses_m: float | None  # no-overlap pairs: the answer's distance from the dataset's poses
    icp_converged: bool
    icp_fitness: float
    icp_iterations: int
    icp_prepare_ms: float
    icp_register_ms: float
    bb_outcome: str  # right | wrong | refused (bb_align.lab.realpairs.score)
    bb_reason: str | None
    bb_t_err_m: float | None
    bb_r_err_deg: float | None
    bb_align_ms: float


def icp_row(pair: RealPair, answer: IcpAnswer, bb: dict) -> Row:
    """One pair's row: ICP's answer scored as `bb-align real-pairs` scores, beside bb-align's record ``bb``."""
    T_truth = pair.T_ref if pair.T_ref is not None else pair.T_poses
    G = ground_se2(T_truth)
    base = G[:2, 2] / max(np.linalg.norm(G[:2, 2]), 1e-9)
    perp = np.array([-base[1], base[0]])
    t_err, r_err = pose_error(answer.T, T_truth)
    d = answer.T[:2, 3] - G[:2, 2]
    scored = pair.T_ref is not None
    return Row(
        pair=pair.name,
        group=pair.group,
        distance_m=pair.distance_m,
        icp_right=(t_err < RIGHT_M and r_err < RIGHT_DEG) if scored else None,
        icp_t_err_m=t_err if scored else None,
        icp_r_err_deg=r_err if scored else None,
        icp_along_m=float(d @ base) if scored else None,
        icp_across_m=float(d @ perp) if scored else None,
        icp_off_poses_m=None if scored else t_err,
        icp_converged=answer.converged,
        icp_fitness=answer.fitness,
        icp_iterations=answer.iterations,
        icp_prepare_ms=answer.prepare_ms,
        icp_register_ms=answer.register_ms,
        bb_outcome=bb["outcome"],
        bb_reason=bb.get("reason"),
        bb_t_err_m=bb.get("t_err_m"),
        bb_r_err_deg=bb.get("r_err_deg"),
        bb_align_ms=float(bb.get("align_ms", 0.0)),
    )


def bb_records(path: Path) -> dict[str, dict]:
    """bb-align's records with the prior from a `bb-align real-pairs` records.jsonl, by pair name."""
    out = {}
    for line in path.read_text().splitlines():
        r = json.loads(line)
        if r["prior"]:
            out[r["pair"]] = r
    return out


def run(data: Path, settings: IcpSettings, bb_from: Path | None = None, groups: set[str] | None = None) -> list[Row]:
    """Every pair (``groups``: only these): ICP from the seeded prior, beside bb-align with the same prior (aligned
    here, or read from ``bb_from``)."""
    from tqdm import tqdm

    from bb_align.io.clouds import load_cloud

    pairs = [p for p in discover(data) if groups is None or p.group in groups]
    recorded = bb_records(bb_from) if bb_from is not None else None
    aligner = None
    if recorded is None:
        from bb_align import AlignConfig, Aligner

        aligner = Aligner(AlignConfig())
        aligner.warm_up()  # compile once, so the first pair's time is the engine's, not the compiler's
    rows = []
    for pair in tqdm(pairs, desc="icp from prior"):
        ego_pts, peer_pts = load_cloud(pair.ego), load_cloud(pair.peer)
        prior = seeded_prior(pair)
        answer = icp(ego_pts, peer_pts, prior, settings)
        if recorded is not None:
            if pair.name not in recorded:
                raise SystemExit(f"icp_from_prior: --bb-records: no record with the prior for {pair.name}")
            bb = recorded[pair.name]
        else:
            from bb_align.lab.realpairs import score

            ego, peer = aligner.warm(aligner.prepare(ego_pts)), aligner.prepare(peer_pts)  # as real-pairs does
            bb = asdict(score(pair, aligner.align(ego, peer, T_prior=prior), prior=True))
        rows.append(icp_row(pair, answer, bb))
    return rows


GROUP_NAMES = {
    "far": "far (KITTI 00, 73-80 m)",
    "near": "near (0.7-28.5 m)",
    "no_overlap": "no overlap (130 m)",
}


def summarise(rows: list[Row]) -> dict:
    """Per group: pairs; ICP right / converged / converged but not right / median error; bb-align right / wrong /
    refused / median error of its successes."""
    out: dict = {}
    for group in GROUP_NAMES:
        rs = [r for r in rows if r.group == group]
        if not rs:
            continue
        scored = [r for r in rs if r.icp_right is not None]
        bb_ok = [r for r in rs if r.bb_outcome in ("right", "wrong") and r.bb_t_err_m is not None]
        out[group] = {
            "pairs": len(rs),
            "icp_right": sum(bool(r.icp_right) for r in scored),
            "icp_converged": sum(r.icp_converged for r in rs),
            "icp_converged_not_right": sum(r.icp_converged and not r.icp_right for r in rs),
            "icp_median_t_err_m": float(np.median([r.icp_t_err_m for r in scored])) if scored else None,
            "icp_max_t_err_m": float(max(r.icp_t_err_m for r in scored)) if scored else None,
            "icp_median_fitness": float(np.median([r.icp_fitness for r in rs])),
            "icp_median_ms": float(np.median([r.icp_prepare_ms + r.icp_register_ms for r in rs])),
            "bb_right": sum(r.bb_outcome == "right" for r in rs),
            "bb_wrong": sum(r.bb_outcome == "wrong" for r in rs),
            "bb_refused": sum(r.bb_outcome == "refused" for r in rs),
            "bb_pose_within": sum(  # its pose within 1 m and 1 deg, answered or refused
                r.bb_t_err_m is not None and r.bb_t_err_m < RIGHT_M and r.bb_r_err_deg < RIGHT_DEG for r in rs
            ),
            "bb_median_t_err_m": float(np.median([r.bb_t_err_m for r in bb_ok])) if bb_ok else None,
            "bb_median_ms": float(np.median([r.bb_align_ms for r in rs])),
        }
    return out


def _f(v, spec: str) -> str:
    return "" if v is None else format(v, spec)


def markdown(rows: list[Row], summary: dict, settings: IcpSettings, command: str, bb_source: str) -> str:
    lines = [
        "# ICP from the same prior on the full clouds, beside bb-align",
        "",
        f"Made by `{command}` (benchmarks/icp_from_prior.py; times on a shared, loaded 2-core machine). ICP: "
        f"small_gicp {settings.method}, both full clouds voxel-downsampled to {settings.voxel_m:g} m, normals from "
        f"{settings.neighbours} neighbours, max correspondence distance "
        f"{' -> '.join(f'{d:g}' for d in settings.schedule_m)} m ({settings.iterations} iterations per stage, "
        f"{settings.threads} thread), started from the seeded 2 m / 2 deg prior of `bb-align real-pairs` lifted "
        "level at z = 0. Right: within 1 m and 1 deg of the reference (ICP never refuses). bb-align: "
        f"{bb_source}, the same prior. Converged / fitness: ICP's own last-stage claim / inliers per downsampled "
        "peer point.",
        "",
        "| group | pairs | ICP right | ICP converged | converged, not right | ICP median / max err m | "
        "ICP median fitness | bb-align right / wrong / refused | bb-align pose within 1 m & 1 deg, answered or not | "
        "bb-align median err m (answers) | ICP ms | bb-align ms |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for group, s in summary.items():
        icp_right = "-" if group == "no_overlap" else str(s["icp_right"])
        lines.append(
            f"| {GROUP_NAMES[group]} | {s['pairs']} | {icp_right} | {s['icp_converged']} | "
            f"{s['icp_converged_not_right']} | {_f(s['icp_median_t_err_m'], '.2f')} / "
            f"{_f(s['icp_max_t_err_m'], '.2f')} | {s['icp_median_fitness']:.3f} | "
            f"{s['bb_right']} / {s['bb_wrong']} / {s['bb_refused']} | "
            f"{'-' if group == 'no_overlap' else s['bb_pose_within']} | "
            f"{_f(s['bb_median_t_err_m'], '.2f')} | {s['icp_median_ms']:.0f} | {s['bb_median_ms']:.0f} |"
        )
    lines += [
        "",
        "| pair | m | ICP t err m | ICP r err deg | ICP along m | ICP across m | ICP converged | ICP fitness | "
        "ICP ms | bb-align | bb-align reason | bb-align t err m | bb-align r err deg |",
        "| --- | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | --- | --- | ---: | ---: |",
    ]
    for r in rows:
        if r.icp_right is None:
            icp_err = f"({r.icp_off_poses_m:.1f} from poses) | | | "
        else:
            mark = "" if r.icp_right else " (wrong)"
            icp_err = (
                f"{r.icp_t_err_m:.2f}{mark} | {r.icp_r_err_deg:.2f} | {r.icp_along_m:+.2f} | {r.icp_across_m:+.2f} "
            )
        lines.append(
            f"| {r.pair} | {r.distance_m:.1f} | {icp_err}| {'yes' if r.icp_converged else 'no'} | "
            f"{r.icp_fitness:.3f} | {r.icp_prepare_ms + r.icp_register_ms:.0f} | {r.bb_outcome} | {r.bb_reason or ''} "
            f"| {_f(r.bb_t_err_m, '.2f')} | {_f(r.bb_r_err_deg, '.2f')} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"), help="folder of real scans (../shared/data)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"where the records go (default {DEFAULT_OUT})")
    ap.add_argument("--record", action="store_true", help=f"write to {RECORD_DIR}/icp_from_prior.* (the docs' copy)")
    ap.add_argument("--bb-records", type=Path, default=None, help="bb-align's side from this records.jsonl")
    ap.add_argument("--group", action="append", choices=sorted(GROUP_NAMES), help="only these groups (repeatable)")
    ap.add_argument("--voxel", type=float, default=IcpSettings.voxel_m, help="downsampling voxel, m")
    ap.add_argument("--schedule", default=",".join(f"{d:g}" for d in IcpSettings.schedule_m),
                    help="max correspondence distances, m, comma-separated")  # fmt: skip
    ap.add_argument("--threads", type=int, default=IcpSettings.threads)
    ap.add_argument("--method", choices=("PLANE_ICP", "GICP"), default=IcpSettings.method,
                    help="small_gicp's registration (default PLANE_ICP: point-to-plane)")  # fmt: skip
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        ap.error(f"--data: {args.data} is not a folder of real scans")
    try:
        schedule = tuple(float(s) for s in args.schedule.split(","))
    except ValueError:
        ap.error(f"--schedule: comma-separated distances in metres, got {args.schedule!r}")
    if not schedule or min(schedule) <= 0 or args.voxel <= 0 or args.threads < 1:
        ap.error("--schedule, --voxel: positive metres; --threads: at least 1")
    if args.bb_records is not None and not args.bb_records.is_file():
        ap.error(f"--bb-records: {args.bb_records} is not a file")
    settings = IcpSettings(voxel_m=args.voxel, schedule_m=schedule, threads=args.threads, method=args.method)
    rows = run(args.data, settings, args.bb_records, set(args.group) if args.group else None)
    if not rows:
        ap.error(f"--data: no real pairs found under {args.data}")
    summary = summarise(rows)
    command = "benchmarks/icp_from_prior.py --data " + str(args.data)
    for flag, value, default in (("--voxel", args.voxel, IcpSettings.voxel_m), ("--threads", args.threads, 1)):
        if value != default:
            command += f" {flag} {value:g}"
    if args.method != IcpSettings.method:
        command += f" --method {args.method}"
    if schedule != IcpSettings.schedule_m:
        command += f" --schedule {args.schedule}"
    command += "".join(f" --group {g}" for g in args.group or [])
    if args.bb_records is not None:
        command += f" --bb-records {args.bb_records}"
    bb_source = f"read from {args.bb_records}" if args.bb_records else "aligned in the same run (default config)"
    if args.record:
        command += " --record"
        out, stem = RECORD_DIR, "icp_from_prior"
    else:
        out, stem = args.out, "records"
    out.mkdir(parents=True, exist_ok=True)
    with open(out / f"{stem}.jsonl", "w") as f:
        for r in rows:
            f.write(json.dumps(asdict(r)) + "\n")
    (out / f"{stem}.json").write_text(json.dumps({"settings": asdict(settings), "summary": summary}, indent=2) + "\n")
    (out / f"{stem}.md").write_text(markdown(rows, summary, settings, command, bb_source))
    print(json.dumps(summary, indent=2))
    print(f"table: {out / (stem + '.md')}")


if __name__ == "__main__":
    main()
