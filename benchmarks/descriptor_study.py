"""Would a richer descriptor find more right candidates at range? (issue #11, item 5: "a better descriptor")

    PYTHONPATH=service:client .venv/bin/python benchmarks/descriptor_study.py SIM_ROOT [SIM_ROOT ...]
        [--min-distance 40] [--range 100] [--workers 2] [--limit N] [--plot fig.png]

Per pair (the same prepared frames as `bb-align eval`) and per descriptor variant: the peer keypoints that have a
true partner (an ego keypoint within 2 m under the true pose) and how many of them hold one among their k nearest
ego descriptors (k = 1, 3 and the multi path's top_k 12): a pose found by voting needs a few right candidates
that agree, and at 70+ m the truth is often not among the hypotheses at all. Candidates are found as the engine
finds them (``acquire.topk_candidates`` over the ego's reference descriptors: orientation offsets and 180-degree
copies). Variants, all on the engine's keypoints and dominant orientations:

- ``mim``: the engine's BVFT descriptor (J = 96, 6 x 6 cells, merged MIM bins);
- ``mim+height@w``: the same window's cells also histogram the lit pixels' BV height (4 bands), that part
  unit-normalised, weighted w and the whole renormalised (a height channel alongside the MIM histogram);
- ``mim96+64`` / ``mim96+128``: a second BVFT descriptor on a smaller / larger window, concatenated (two scales).

Then the whole alignment runs with each variant's descriptors in place of the engine's (fresh frames, default
config): the pairs aligned under 1 m & 1 deg and the wrong successes are what a variant would change; and whether a
verified hypothesis lies within 3 m & 3 deg of the truth at all (and first): where more right candidates could help.
"""

from __future__ import annotations

import argparse
import os
from multiprocessing import get_context

import numpy as np
from tqdm import tqdm

from bb_align.engine.acquisition.candidates import topk_candidates
from bb_align.engine.config import AlignConfig, BevConfig
from bb_align.engine.descriptors import (
    _cell_histograms,
    _rotated_grids,
    bvft_descriptors,
    descriptor_radius,
    flip_180,
)
from bb_align.engine.frame import REFERENCE_ORIENTATION_OFFSETS
from bb_align.engine.geometry import pose_error, se2_params
from bb_align.engine.pipeline import Aligner
from bb_align.io.dataset import iter_frames

HEIGHT_EDGES_M = (0.0, 1.0, 2.0, 3.5)  # lit pixels: [0, 1), [1, 2), [2, 3.5), >= 3.5 m (slot 0, empty, dropped)
KS = (1, 3, 12)
PARTNER_M = 2.0
NEAR_TRUTH = (3.0, 3.0)  # m, deg: a hypothesis this close is "the truth" (the refinement's reach)
BUCKETS = {"40-70": (40, 70), "70+": (70, 1e9)}

_state: dict = {}


def height_descriptors(prepared, features, n_orient: int, orientation_offset: int = 0) -> np.ndarray:
    """(K, cells * 4) per-cell counts of the lit pixels' height bands over the keypoint's rotated window, unit norm."""
    heights = prepared.bev.heights_m()
    band = np.where(prepared.bev.image > 0, np.searchsorted(HEIGHT_EDGES_M, heights, side="right"), 0)
    band = band.astype(np.uint8)
    rc = np.asarray(prepared.keypoints_rc, dtype=np.int64).reshape(-1, 2)
    radius = descriptor_radius(features)
    width = band.shape[1] + 2 * radius
    offsets, cell = _rotated_grids(features.patch_px, features.grid, n_orient, width, features.window_stride)
    m = np.asarray(prepared.orientations)
    if orientation_offset:
        m = np.where(m > 0, (m - 1 + orientation_offset) % n_orient + 1, 0)
    base = (rc[:, 0] + radius) * width + rc[:, 1] + radius
    n_cells = features.grid**2
    hist = _cell_histograms(
        np.pad(band, radius).ravel(), base, offsets, np.maximum(m, 1) - 1, cell, n_cells, len(HEIGHT_EDGES_M) + 1
    )[:, :, 1:].reshape(len(rc), -1)  # lit pixels only: empty ones would outweigh every band (most are empty)
    return hist / np.maximum(np.linalg.norm(hist, axis=1, keepdims=True), 1e-12)


def variant_blocks(prepared, cfg: AlignConfig, name: str, offsets: tuple[int, ...]) -> list[np.ndarray]:
    """The variant's descriptors of every keypoint, one (K, D) block per orientation offset and per 180-degree
    copy (the peer uses the first block only)."""
    f, n_orient = cfg.features, cfg.mim.n_orient
    mim, amp = prepared._maps
    out = []
    for off in offsets:
        d = bvft_descriptors(mim, amp, prepared.keypoints_rc, f, n_orient, off, prepared.orientations)
        parts, flips = [d], [flip_180(d, f)]
        if name.startswith("mim+height@"):
            w = float(name.split("@")[1])
            h = height_descriptors(prepared, f, n_orient, off)
            parts.append(w * h)
            flips.append(w * flip_180(h, f))  # cells reversed, whatever a cell holds
        elif name.startswith("mim96+"):
            f2 = f.model_copy(update={"patch_px": int(name.split("+")[1])})
            d2 = bvft_descriptors(mim, amp, prepared.keypoints_rc, f2, n_orient, off, prepared.orientations)
            parts.append(d2)
            flips.append(flip_180(d2, f2))
        for p in (parts, flips):
            v = np.concatenate(p, axis=1).astype(np.float32)
            out.append(v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12))
    return out


def _init(range_m: float, names: list[str], min_distance: float) -> None:
    from bb_align.lab.evaluation.runner import EvalConfig

    cfg = AlignConfig(bev=BevConfig(range_m=range_m))
    _state.update(cfg=cfg, prep=Aligner(cfg), eval=EvalConfig(align=cfg), names=names, min_distance=min_distance)


def _acquire(group, peer_frame, name: str, T_true: np.ndarray) -> tuple[bool, bool, int | None]:
    """The whole alignment with the variant's descriptors in place of the engine's (fresh frames: nothing derived
    from the engine's own descriptors is reused): (success under 1 m & 1 deg, success beyond it)."""
    from bb_align.lab.evaluation.runner import _load_agent

    cfg, prep = _state["cfg"], _state["prep"]
    e, p = (
        _load_agent(f, prep, _state["eval"], group.scenario, group.timestamp).prepared for f in (group.ego, peer_frame)
    )
    if name != "mim":
        ref = variant_blocks(e, cfg, name, REFERENCE_ORIENTATION_OFFSETS)
        e.descriptors, e.descriptors_flipped, e._reference = ref[0], ref[1], np.concatenate(ref)
        p.descriptors, p.descriptors_flipped = variant_blocks(p, cfg, name, (0,))
    r = prep.align(e, p)
    t_err, r_err = pose_error(r.T_ego_peer, T_true)
    right = bool(r.success) and t_err <= 1.0 and r_err <= 1.0
    yaw_t, tx_t, ty_t = se2_params(T_true)
    near = [  # the hypotheses verified, best first: where is one within NEAR_TRUTH of the truth?
        i
        for i, h in enumerate([] if r.acquisition is None else r.acquisition.to_dict()["all"])
        if np.hypot(h["tx"] - tx_t, h["ty"] - ty_t) < NEAR_TRUTH[0]
        and abs((np.degrees(yaw_t) - h["yaw_deg"] + 180.0) % 360.0 - 180.0) < NEAR_TRUTH[1]
    ]
    return right, bool(r.success) and not right, (near[0] if near else None)


def _run(group) -> list[dict]:
    from bb_align.lab.evaluation.runner import _load_agent

    cfg, prep = _state["cfg"], _state["prep"]
    ego = _load_agent(group.ego, prep, _state["eval"], group.scenario, group.timestamp)
    rows = []
    for peer_frame in group.peers:
        T_true = np.linalg.inv(ego.frame.T_world_sensor) @ peer_frame.T_world_sensor
        _, tx, ty = se2_params(T_true)
        dist = float(np.hypot(tx, ty))
        if dist < _state["min_distance"]:
            continue
        peer = _load_agent(peer_frame, prep, _state["eval"], group.scenario, group.timestamp)
        e, p = ego.prepared, peer.prepared
        xy_peer_in_ego = p.keypoints_xy @ T_true[:2, :2].T + T_true[:2, 3]
        d_true = np.linalg.norm(xy_peer_in_ego[:, None, :] - e.keypoints_xy[None, :, :], axis=2)  # (Kp, Ke)
        partner = d_true < PARTNER_M
        has_partner = partner.any(axis=1)
        row = {
            "scenario": group.scenario,
            "peer": peer_frame.agent,
            "distance_m": dist,
            "repeat": int(has_partner.sum()),
        }
        p_partner = partner.mean(axis=1)  # what k ego keypoints drawn at random would hit, per peer keypoint
        row["chance"] = {k: float((1.0 - (1.0 - p_partner) ** k).sum()) for k in KS}
        offsets = REFERENCE_ORIENTATION_OFFSETS
        for name in _state["names"]:
            ref = np.concatenate(variant_blocks(e, cfg, name, offsets))
            desc_peer = variant_blocks(p, cfg, name, (0,))[0]
            rows_q, cand = topk_candidates(desc_peer, ref, len(e.keypoints_xy), max(KS), cfg.match.threads)
            hit = partner[rows_q[:, None], cand]  # (Q, k): the candidate is a true partner
            row[name] = {k: int(hit[:, :k].any(axis=1).sum()) for k in KS}
            row[name + ":right"], row[name + ":wrong"], row[name + ":rank"] = _acquire(group, peer_frame, name, T_true)
            row[name + ":dim"] = int(desc_peer.shape[1])
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--min-distance", type=float, default=40.0)
    ap.add_argument("--range", type=float, default=100.0, dest="range_m")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--variants", default="mim,mim+height@0.5,mim+height@1,mim96+64,mim96+128", help="comma-separated")
    ap.add_argument("--plot", default=None)
    args = ap.parse_args()
    names = args.variants.split(",")
    groups = [g for root in args.roots for g in list(iter_frames(root))[: args.limit]]
    os.environ.update({k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")})
    rows: list[dict] = []
    with get_context("spawn").Pool(
        args.workers, initializer=_init, initargs=(args.range_m, names, args.min_distance)
    ) as pool:
        for out in tqdm(pool.imap(_run, groups), total=len(groups), desc="pairs", unit="pair"):
            rows += out
    print(f"\n{args.roots}: {len(rows)} pairs at >= {args.min_distance} m; right candidates per pair (median) and")
    print("pairs with >= 3 right candidates among the k nearest (the vote needs a few that agree)\n")
    print(
        "| bucket | variant | dim | pairs | repeatable kp (median) | right@1 | right@3 | right@12 | pairs >=3 @12 "
        "| truth among hypotheses | truth first | aligned under 1 m & 1 deg | wrong successes |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for b, (lo, hi) in BUCKETS.items():
        sel = [r for r in rows if lo <= r["distance_m"] < hi]
        if sel:
            med = {k: float(np.median([r["chance"][k] for r in sel])) for k in KS}
            print(
                f"| {b} | random candidates (chance) | - | {len(sel)} | - "
                f"| {med[1]:.1f} | {med[3]:.1f} | {med[12]:.1f} | - | - | - | - | - |"
            )
    for b, (lo, hi) in BUCKETS.items():
        sel = [r for r in rows if lo <= r["distance_m"] < hi]
        if not sel:
            continue
        for n in names:
            med = {k: float(np.median([r[n][k] for r in sel])) for k in KS}
            ge3 = sum(r[n][12] >= 3 for r in sel)
            print(
                f"| {b} | {n} | {sel[0][n + ':dim']} | {len(sel)} | {np.median([r['repeat'] for r in sel]):.0f} | "
                f"{med[1]:.0f} | {med[3]:.0f} | {med[12]:.0f} | {ge3} ({100 * ge3 / len(sel):.0f} %) | "
                f"{sum(r[n + ':rank'] is not None for r in sel)} | {sum(r[n + ':rank'] == 0 for r in sel)} | "
                f"{sum(r[n + ':right'] for r in sel)} | {sum(r[n + ':wrong'] for r in sel)} |"
            )
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(names) - 1, figsize=(4 * (len(names) - 1), 4), squeeze=False)
        base = [r["mim"][12] for r in rows]
        for ax, n in zip(axes[0], names[1:], strict=False):
            ax.scatter(base, [r[n][12] for r in rows], s=8, c=[r["distance_m"] for r in rows], cmap="viridis")
            lim = max(base + [r[n][12] for r in rows]) + 1
            ax.plot([0, lim], [0, lim], "k--", lw=0.8)
            ax.set(xlabel="right candidates @12, mim", ylabel=f"right candidates @12, {n}", title=n)
        fig.suptitle(f"Right candidates per pair at >= {args.min_distance:.0f} m (colour: distance)")
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)
        print(f"\nfigure: {args.plot}")


if __name__ == "__main__":
    main()
