"""Each hot-path stage against its lower bound (issue 45, docs/performance.md "Each stage against its lower bound").

    PYTHONPATH=service:client .venv/bin/python benchmarks/stage_bounds.py [--record] [--runs 7]

The workload is benchmarks/hot_path.py's: three seeded simulated pairs (20, 30 and 45 m apart), the ego frame
prepared once, the peer frame (PNG bytes in) prepared and aligned against it. Per pair the script

1. times today's engine on the hot path (``--runs`` calls; the stage timers ``PreparedFrame.timings_ms`` and
   ``AlignResult.timings_ms``), and during one extra call records what each stage computes: the FFT shapes and
   filter boxes of the MIM, the keypoints, the descriptor and candidate counts, the pose votes cast, the ICP calls
   of the verification, the landscape's poses x points and the free-space map;
2. times the least that work costs on this machine with the best tool for it, each a micro-benchmark on the same
   arrays, two threads where the work splits:

   - MIM: the forward DFT and the 48 inverse DFTs at today's sizes (the 2 coarse scales on the half grid): OpenCV's
     (IPP) DFT on 2 threads, scipy.fft (pocketfft) complex64 batched with ``workers=2``, and pocketfft pruned to the
     filter's box (the rows outside the box are zero: only those rows are transformed first, then only the image's
     columns); the fastest, plus the amplitude/arg-max passes (the engine's compiled loop, split in two);
   - descriptors: the two histogram passes (orientation disc, rotated window) as compiled loops over the
     keypoints (two halves on 2 threads), nothing else (no padding, no bin shuffles);
   - matching: the float32 GEMM (BLAS) of peer x ego descriptions in two row blocks on 2 threads, the best over
     descriptions and ``argpartition``;
   - hypotheses: the vote (``kernels.cast`` + ``scatter``) on 2 threads, i.e. the votes at today's count with the
     engine's compiled loops; the rest of the stage (peaks, refits, Python) is the gap;
   - verification: the compiled ICP loops the stage calls (``coarse_verification_loop``, ``_icp_loop``), their
     single-thread time split over 2 threads;
   - landscape: the engine's own ``_score_grid`` (its translation loop already contiguous vector adds) on the
     recorded grids alone, the yaws split over 2 threads: what is left is the Python around it;
   - free space: the compiled map kernel (``_free_map``) split in two, plus the conflict look-ups as one gather.

Prints a table (stage, today's p50, bound, gap) with progress on stderr; ``--record`` writes docs/stage_bounds.json
(what ``bb-align bench`` prints beside its stage table). The machine may be shared: the load average is recorded.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import scipy.fft as sfft
from numba import njit
from tqdm import tqdm

from bb_align import AlignConfig, Aligner, make_bev
from bb_align.engine import freespace as freespace_mod
from bb_align.engine import landscape as landscape_mod
from bb_align.engine import loggabor
from bb_align.engine import refine as refine_mod
from bb_align.engine.acquisition import hypotheses as hyp_mod
from bb_align.engine.acquisition import verification as ver_mod
from bb_align.engine.bev import BevImage
from bb_align.engine.descriptors import _orientation_window, _rotated_grids, descriptor_radius
from bb_align.engine.landscape import _score_grid  # the engine's kernel, before the recording wraps it
from bb_align.engine.parallel import contiguous, run_parts
from bb_align.engine.pipeline import _single_threaded_blas
from bb_align.lab.sim import simulate_sequence

ROOT = Path(__file__).resolve().parents[1]
PAIRS = [(3, 30.0), (5, 20.0), (7, 45.0)]  # benchmarks/hot_path.py's
STAGES = ["mim", "descriptors", "matching", "hypotheses", "verify", "free_space", "landscape"]
THREADS = 2


def median_ms(fn, reps: int) -> float:
    fn()  # warm (JIT, caches, pools)
    out = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(out))


# ---- recording what each stage computes ----------------------------------------------------------------------


@contextmanager
def recording(module, name: str, calls: list):
    """Replace module.name by a wrapper appending (args, single-call ms) to ``calls``."""
    original = getattr(module, name)

    def wrapper(*args):
        t0 = time.perf_counter()
        out = original(*args)
        calls.append((args, (time.perf_counter() - t0) * 1e3))
        return out

    setattr(module, name, wrapper)
    try:
        yield
    finally:
        setattr(module, name, original)


# ---- the bound kernels ---------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _desc_bound(mim_p, amp_p, base, disc_off, disc_w, win_off, grid_index, cell, disc, win, lo, hi):
    """Both descriptor histograms of keypoints lo..hi: the disc (weighted) and the window, nothing else."""
    for i in range(lo, hi):
        b = base[i]
        for j in range(len(disc_off)):
            p = b + disc_off[j]
            disc[i, mim_p[p]] += amp_p[p] * disc_w[j]
        row = win_off[grid_index[i]]
        for j in range(len(cell)):
            win[i, cell[j], mim_p[b + row[j]]] += 1


@njit(cache=True, nogil=True)
def _gather_sum(table, idx, lo, hi):
    """Sum of table[idx[i]] for i in lo..hi (one random look-up each)."""
    s = 0.0
    for i in range(lo, hi):
        s += table[idx[i]]
    return s


def _halves(n: int) -> list[tuple[int, int]]:
    return [(t * n // THREADS, (t + 1) * n // THREADS) for t in range(THREADS)]


def _two_threads(fns) -> None:
    run_parts(lambda group: [f() for f in group], contiguous(fns, THREADS))


def mim_bounds(image: np.ndarray, cfg) -> dict:
    """What the MIM computes at today's defaults and the least it costs (see the module docstring)."""
    mc = cfg.mim
    h, w = image.shape
    wrapped, shape = loggabor._spectrum(image.astype(np.float32), mc)
    blocks = loggabor._blocks(shape, mc, loggabor.lattice_shift((h, w), mc))
    full = [b for bs in blocks for b in bs if b.stride == 1]
    coarse = [b for bs in blocks for b in bs if b.stride > 1]
    sub = (shape[0] // mc.coarse_stride, shape[1] // mc.coarse_stride)
    padded = np.zeros(shape, np.float32)
    padded[:h, :w] = image

    def fwd():
        cv2.dft(padded, flags=cv2.DFT_COMPLEX_OUTPUT)

    # OpenCV (IPP): each inverse DFT into its own preallocated buffer, the transforms split over 2 threads.
    bufs = [(np.zeros(shape + (2,), np.float32), np.empty(shape + (2,), np.float32)) for _ in range(THREADS)]
    sbufs = [(np.zeros(sub + (2,), np.float32), np.empty(sub + (2,), np.float32)) for _ in range(THREADS)]

    def cv_part(t: int, n_full: int, n_coarse: int):
        src, dst = bufs[t]
        for _ in range(n_full):
            cv2.idft(src, dst=dst, flags=cv2.DFT_COMPLEX_OUTPUT)
        src, dst = sbufs[t]
        for _ in range(n_coarse):
            cv2.idft(src, dst=dst, flags=cv2.DFT_COMPLEX_OUTPUT)

    def opencv():
        nf, nc = len(full), len(coarse)
        run_parts(lambda t: cv_part(t, nf // THREADS + (t < nf % THREADS), nc // THREADS + (t < nc % THREADS)),
                  list(range(THREADS)))  # fmt: skip

    stack_full = np.zeros((len(full),) + shape, np.complex64)
    stack_coarse = np.zeros((len(coarse),) + sub, np.complex64)

    def scipy_batched():
        sfft.ifft2(stack_full, workers=THREADS, overwrite_x=False)
        sfft.ifft2(stack_coarse, workers=THREADS, overwrite_x=False)

    # pocketfft pruned to the box: the spectrum is zero outside the box's bh rows (the narrower axis taken first),
    # so transform those rows along the other axis, then each needed column (the image's, not the margin's).
    def pruned_sizes(blist, grid):
        sizes = []
        for b in blist:
            bh, bw = b.values.shape[:2]
            first_n, second_n = (grid[1], grid[0]) if bh <= bw else (grid[0], grid[1])
            sizes.append((min(bh, bw), first_n, second_n))
        return sizes

    pr_full = pruned_sizes(full, shape)
    pr_coarse = pruned_sizes(coarse, sub)
    crop_full = min(h, w)
    crop_coarse = -(-crop_full // mc.coarse_stride) + 2
    pr_bufs = {}
    for nnz, n1, _ in pr_full + pr_coarse:
        pr_bufs.setdefault((nnz, n1), np.zeros((nnz, n1), np.complex64))
    col_bufs = {(n2, crop_full): np.zeros((n2, crop_full), np.complex64) for _, _, n2 in pr_full} | {
        (n2, crop_coarse): np.zeros((n2, crop_coarse), np.complex64) for _, _, n2 in pr_coarse
    }

    def pruned_one(nnz, n1, n2, crop):
        sfft.ifft(pr_bufs[(nnz, n1)], axis=1, overwrite_x=False)
        sfft.ifft(col_bufs[(n2, crop)], axis=0, overwrite_x=False)

    def pruned():
        jobs = [(s + (crop_full,)) for s in pr_full] + [(s + (crop_coarse,)) for s in pr_coarse]
        _two_threads([lambda j=j: pruned_one(*j) for j in jobs])

    # The amplitude pass: the engine's compiled loop over each response, split over 2 threads; the arg-max with cv2.
    resp = np.zeros(shape + (2,), np.float32)
    sresp = np.zeros(sub + (2,), np.float32)
    accs = [np.zeros((h, w), np.float32) for _ in range(THREADS)]
    saccs = [np.zeros(sub, np.float32) for _ in range(THREADS)]
    rows = [np.empty(max(shape), np.float32) for _ in range(THREADS)]

    def amp_part(t: int):
        for _ in range(len(full) // THREADS):
            loggabor._add_amplitude(accs[t], resp, mc.fft_margin_px, rows[t])
        for _ in range(len(coarse) // THREADS):
            loggabor._add_amplitude(saccs[t], sresp, 0, rows[t])

    def amplitudes():
        run_parts(amp_part, list(range(THREADS)))

    t_fwd = median_ms(fwd, 9)
    t_cv = median_ms(opencv, 5)
    t_sp = median_ms(scipy_batched, 5)
    t_pr = median_ms(pruned, 5)
    t_amp = median_ms(amplitudes, 5)
    best = min(t_cv, t_sp, t_pr)
    return {
        "must_compute": f"1 forward DFT {shape[0]}x{shape[1]}; {len(full)} inverse complex DFTs {shape[0]}x{shape[1]} "
        f"and {len(coarse)} at {sub[0]}x{sub[1]} (coarse scales); {len(full) + len(coarse)} amplitude passes, "
        f"an arg-max over {mc.n_orient} orientations on {h}x{w} px",
        "bound_ms": t_fwd + best + t_amp,
        "parts_ms": {
            "forward_dft": t_fwd,
            "inverse_dfts_opencv_2threads": t_cv,
            "inverse_dfts_scipy_batched_workers2": t_sp,
            "inverse_dfts_scipy_pruned_2threads": t_pr,
            "amplitudes_2threads": t_amp,
        },
        "best_library": min(
            [("OpenCV DFT", t_cv), ("scipy.fft batched", t_sp), ("scipy.fft pruned to the box", t_pr)],
            key=lambda x: x[1],
        )[0],
    }


def descriptor_bounds(peer, cfg) -> dict:
    fc, no = cfg.features, cfg.mim.n_orient
    mim, amp = loggabor.maximum_index_map(peer.bev.image, cfg.mim)
    rc = np.asarray(peer.keypoints_rc, np.int64)
    radius = descriptor_radius(fc)
    width = mim.shape[1] + 2 * radius
    disc_off, disc_w = _orientation_window(radius, width, fc.orientation_stride)
    win_off, cell = _rotated_grids(fc.patch_px, fc.grid, no, width, fc.window_stride)
    mim_p = np.pad(mim, radius).ravel()
    amp_p = np.pad(amp.astype(np.float64), radius).ravel()
    base = (rc[:, 0] + radius) * width + rc[:, 1] + radius
    gi = (np.arange(len(rc)) % no).astype(np.int64)

    def run():
        disc = np.zeros((len(rc), no + 1))
        win = np.zeros((len(rc), fc.grid**2, no + 1), np.int32)  # integer counts: no float-add chain
        run_parts(
            lambda r: _desc_bound(mim_p, amp_p, base, disc_off, disc_w, win_off, gi, cell, disc, win, *r),
            _halves(len(rc)),
        )

    return {
        "must_compute": f"{len(rc)} keypoints x ({len(disc_off)} disc + {win_off.shape[1]} window) histogram samples",
        "bound_ms": median_ms(run, 7),
        "best_library": "compiled histogram loops, keypoints split over 2 threads",
    }


def matching_bounds(ego, peer, cfg) -> dict:
    q = np.ascontiguousarray(peer.descriptors, np.float32)
    t = np.ascontiguousarray(ego.reference_descriptors(cfg.features, cfg.mim.n_orient), np.float32)
    n_ego, k = len(ego.descriptors), cfg.acquire.top_k

    parts = _halves(len(q))

    def block(r: tuple[int, int]) -> None:
        d = q[r[0] : r[1]] @ t.T  # unit vectors: the largest dot product is the smallest distance
        best = d.reshape(r[1] - r[0], -1, n_ego).max(axis=1)
        np.argpartition(best, n_ego - k, axis=1)

    def run():
        with _single_threaded_blas():  # as the engine: BLAS on one thread, two row blocks in parallel
            run_parts(block, parts)

    return {
        "must_compute": f"{len(q)} x {len(t)} distances in {q.shape[1]}-D, the min over {len(t) // max(1, n_ego)} "
        f"descriptions, top {k} per peer keypoint",
        "bound_ms": median_ms(run, 9),
        "best_library": "float32 GEMM (OpenBLAS), two row blocks on 2 threads, + argpartition",
    }


def landscape_bounds(calls) -> dict:
    total, ok, lookups = 0.0, True, 0
    for args, _ in calls:
        fields, pts, yaws, n_off, cx, cy, range_m, step_m, out = args
        mine = np.zeros_like(out)
        parts = _halves(len(yaws))

        def run(a=args, m=mine, parts=parts):
            run_parts(lambda r: _score_grid(*a[:2], a[2][r[0] : r[1]], *a[3:8], m[r[0] : r[1]]), parts)

        total += median_ms(run, 3)  # the yaws of this call split over 2 threads
        ok = ok and bool(np.array_equal(mine, out))
        lookups += 2 * len(yaws) * (2 * n_off + 1) ** 2 * len(pts)
    return {
        "must_compute": f"{lookups / 1e6:.1f} M field look-ups in {len(calls)} grid(s)",
        "bound_ms": total,
        "best_library": "the engine's kernel alone (compiled, contiguous vector adds), yaws split over 2 threads",
        "same_numbers": ok,
    }


def free_space_bounds(calls, conflict_lookups: int) -> dict:
    kernel = 0.0
    for args, _ in calls:
        kernel += median_ms(lambda a=args: _orig_free_map(*a), 5) / THREADS
    table = np.random.default_rng(0).random(500 * 500)
    idx = np.random.default_rng(1).integers(0, len(table), max(1, conflict_lookups))
    gather = median_ms(lambda: run_parts(lambda r: _gather_sum(table, idx, *r), _halves(len(idx))), 9)
    return {
        "must_compute": f"{len(calls)} free-space map(s) (2 passes over the image), {conflict_lookups} conflict "
        "look-ups",
        "bound_ms": kernel + gather,
        "best_library": "the compiled map split over 2 cores + one numba gather",
    }


_orig_free_map = freespace_mod._free_map


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=7, help="timed hot-path calls per pair (after 2 warm-ups)")
    ap.add_argument("--record", action="store_true", help="write docs/stage_bounds.json")
    ap.add_argument("--json", type=Path, default=None, help="write the result here")
    args = ap.parse_args()
    cfg = AlignConfig()
    aligner = Aligner(cfg)
    aligner.warm_up()
    load_start = os.getloadavg()
    today: dict[str, list[float]] = {s: [] for s in STAGES + ["total"]}
    bounds: dict[str, list[dict]] = {s: [] for s in STAGES}
    bar = tqdm(total=len(PAIRS) * (2 + len(STAGES)), desc="stage bounds", file=sys.stderr, dynamic_ncols=True)
    for seed, distance_m in PAIRS:
        frame = simulate_sequence(seed, 1, 2, distance_m)[0]
        ego_car, peer_car = frame.agents["0"], frame.agents["1"]
        ego = aligner.warm(aligner.prepare(make_bev(ego_car.points, cfg.bev), ego_car.boxes))
        bev_peer = make_bev(peer_car.points, cfg.bev)
        png = bev_peer.to_png()

        def hot(png=png, meta=bev_peer.meta(), boxes=peer_car.boxes, ego=ego):
            peer = aligner.prepare(BevImage.from_png(png, **meta), boxes)
            return peer, aligner.align(ego, peer)

        for i in range(args.runs + 2):
            t0 = time.perf_counter()
            peer, result = hot()
            ms = (time.perf_counter() - t0) * 1e3
            if i >= 2:
                t = {**peer.timings_ms, **result.timings_ms}
                for s in STAGES:
                    today[s].append(t.get(s, 0.0))
                today["total"].append(ms)
        bar.update(1)
        # One recorded call: what the stages compute on this pair.
        votes, land, ver_c, ver_i, fmap = [], [], [], [], []
        with (
            recording(hyp_mod, "vote", votes),
            recording(landscape_mod, "_score_grid", land),
            recording(ver_mod, "coarse_verification_loop", ver_c),
            recording(refine_mod, "_icp_loop", ver_i),
            recording(freespace_mod, "_free_map", fmap),
        ):
            peer, result = hot()
        hyps = result.acquisition.hypotheses if result.acquisition is not None else []
        n_tall = len(freespace_mod.tall_points(peer.bev, cfg.free_space, cfg.seed))
        bar.update(1)
        bounds["mim"].append(mim_bounds(peer.bev.image, cfg))
        bar.update(1)
        bounds["descriptors"].append(descriptor_bounds(peer, cfg))
        bar.update(1)
        bounds["matching"].append(matching_bounds(ego, peer, cfg))
        bar.update(1)
        hyp_ms = sum(median_ms(lambda a=a: hyp_mod.vote(*a), 3) for a, _ in votes)
        n_votes = sum(int(len(a[0].cand)) for a, _ in votes)
        bounds["hypotheses"].append(
            {
                "must_compute": f"{len(votes)} vote(s) over {n_votes} peer keypoints' candidate pairs",
                "bound_ms": hyp_ms,
                "best_library": "the engine's compiled vote on 2 threads",
            }
        )
        bar.update(1)
        ver_ms = sum(ms for _, ms in ver_c) + sum(ms for _, ms in ver_i)
        n_poses = sum(len(a[4]) for a, _ in ver_c) + len(ver_i)
        bounds["verify"].append(
            {
                "must_compute": f"ICP of {n_poses} poses ({len(ver_c)} coarse batch(es), {len(ver_i)} full ICP)",
                "bound_ms": ver_ms / THREADS,
                "best_library": "the engine's compiled ICP loops, split over 2 cores",
            }
        )
        bar.update(1)
        bounds["free_space"].append(free_space_bounds(fmap, 2 * n_tall * max(1, len(hyps))))
        bar.update(1)
        bounds["landscape"].append(landscape_bounds(land))
        bar.update(1)
    bar.close()
    rows = {}
    for s in STAGES:
        p50 = float(np.median(today[s]))
        bound = float(np.median([b["bound_ms"] for b in bounds[s]]))
        rows[s] = {
            "today_p50_ms": round(p50, 2),
            "bound_ms": round(bound, 2),
            "gap_x": round(p50 / bound, 1) if bound > 0 else None,
            "must_compute": bounds[s][0]["must_compute"],
            "best_library": bounds[s][0]["best_library"],
            "per_pair": bounds[s],
        }
    out = {
        "command": "benchmarks/stage_bounds.py " + " ".join(sys.argv[1:]),
        "hot_path_p50_ms": round(float(np.median(today["total"])), 1),
        "stages": rows,
        "workload": {"pairs": [list(p) for p in PAIRS], "runs": args.runs, "threads": THREADS},
        "machine": {"cpus": os.cpu_count(), "cpu_model": _cpu_model(), "python": platform.python_version()},
        "load_avg": {"start": list(load_start), "end": list(os.getloadavg())},
        "git": _git(),
    }
    print(f"hot path p50 {out['hot_path_p50_ms']} ms (load average {load_start[0]:.1f} -> {os.getloadavg()[0]:.1f})")
    print(f"{'stage':<12} {'today p50':>10} {'bound':>8} {'gap':>6}  best tool")
    for s, r in rows.items():
        print(f"{s:<12} {r['today_p50_ms']:>8.1f}ms {r['bound_ms']:>6.1f}ms {r['gap_x']:>5}x  {r['best_library']}")
    text = json.dumps(out, indent=1, default=float)
    if args.record:
        (ROOT / "docs" / "stage_bounds.json").write_text(text + "\n")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")


def _cpu_model() -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def _git() -> dict:
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    except OSError:
        commit = ""
    return {"commit": commit or None}


if __name__ == "__main__":
    main()
