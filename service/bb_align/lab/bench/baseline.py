"""The in-benchmark baseline: the same stages as the engine, done the straightforward way the reference does them.

This is the yardstick of ``bb-align bench``, never used by the service. It is written independently of the engine
modules (it imports only their configuration, 2-D geometry helpers and the FFT size choice) so that engine
speed-ups never change it:

- Log-Gabor MIM: float64 image, complex128 numpy FFTs, the filter bank rebuilt on every call, all Ns x No
  inverse FFTs one by one (as the reference);
- FAST keypoints on the image padded by half a descriptor patch, keypoints in the padding dropped, no cap;
- BVFT descriptors in a per-keypoint Python loop: cut a 2*radius (138 px) patch, dominant orientation, rotate the
  patch with ``cv2.warpAffine`` (nearest neighbour), crop J x J (96), a per-cell histogram loop, L2 norm; the
  180-degree copy with the cells in reverse order;
- brute-force nearest-neighbour matching, one query descriptor at a time;
- rigid RANSAC with a fixed 10 000 iterations of 2-point samples, one hypothesis at a time, and a closed-form
  2-D Kabsch refit on the inliers (the reference's least-squares solver, which is 180 degrees wrong about half of
  the time, is deliberately not reproduced);
- the dense BV refinement and the box stage, same algorithms, nothing cached, fixed iteration counts.

Every parameter is read from :class:`bb_align.engine.config.AlignConfig`, so baseline and engine agree on what they
compute and differ only in how. Not followed: the engine's own shortcuts and additions beyond the reference
(sub-sampled orientation disc or window, extra ego-side orientation offsets, prior-pose gating, the RANSAC
ambiguity test): the baseline computes what the reference computes, and the benchmark reports where the
answers differ.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from bb_align.engine import loggabor as lg
from bb_align.engine import refine as rf
from bb_align.engine.bev import BevImage
from bb_align.engine.config import AlignConfig, BoxConfig, FeatureConfig, MimConfig, RefineConfig
from bb_align.engine.geometry import kabsch_2d, se2, se2_params, se3_from_se2
from bb_align.engine.keypoints import FAST_THRESHOLD
from bb_align.engine.loggabor import fft_shape
from bb_align.engine.pipeline import RECHECK_DEG, RECHECK_M, RECHECK_MIN_GAIN

RANSAC_ITERATIONS = 10_000  # the reference's fixed count
# box.apply = "auto": a box correction this large is checked by refining again from it, and kept when the lit
# pixels then overlap better by this much (the engine's rule, docs/engine.md).
# An even J puts every sample of the unrotated window (and of the quarter turn) exactly half-way between two
# pixels. OpenCV's nearest-neighbour warp rounds such ties to even; a tiny bias sends them to the higher pixel
# (round half up, floor(x + 0.5)), so the window stays symmetric about the keypoint.
_TIE_BIAS_PX = 1e-5


@contextmanager
def _timed(timings: dict[str, float], name: str):
    t0 = time.perf_counter()
    yield
    timings[name] = timings.get(name, 0.0) + (time.perf_counter() - t0) * 1e3


# ---- Log-Gabor bank and MIM ------------------------------------------------------------------------------------
def log_gabor_mim(image: np.ndarray, cfg: MimConfig) -> tuple[np.ndarray, np.ndarray]:
    """(MIM uint8 0..No, max amplitude float64) of a BV image (0..255), complex128 throughout."""
    img = np.asarray(image, dtype=np.float64)
    h, w = img.shape
    m = cfg.fft_margin_px
    rows, cols = fft_shape((h, w), m)  # the engine's padded size: the same discrete filters, the same result
    padded = np.zeros((rows, cols))
    padded[m : m + h, m : m + w] = img
    spectrum = np.fft.fft2(padded)

    # The bank, rebuilt on every call: frequencies in [-0.5, 0.5), shifted into FFT order.
    u = np.fft.ifftshift((np.arange(cols) - cols // 2) / cols)
    v = np.fft.ifftshift((np.arange(rows) - rows // 2) / rows)
    uu, vv = np.meshgrid(u, v)
    radius = np.sqrt(uu**2 + vv**2)
    theta = np.arctan2(-vv, uu)
    radius[0, 0] = 1.0
    lowpass = 1.0 / (1.0 + (radius / lg.LOWPASS_CUTOFF) ** (2 * lg.LOWPASS_ORDER))

    amplitude = np.zeros((cfg.n_orient, h, w))
    for s in range(lg.N_SCALES):
        f0 = 1.0 / (lg.MIN_WAVELENGTH_PX * lg.MULT**s)
        radial = np.exp(-(np.log(radius / f0) ** 2) / (2.0 * np.log(lg.SIGMA_ON_F) ** 2)) * lowpass
        radial[0, 0] = 0.0
        for o in range(cfg.n_orient):
            phi = o * np.pi / cfg.n_orient
            dtheta = np.abs(np.arctan2(np.sin(theta - phi), np.cos(theta - phi)))
            dtheta = np.minimum(dtheta * cfg.n_orient, np.pi)
            angular = (np.cos(dtheta) + 1.0) / 2.0
            eo = np.fft.ifft2(spectrum * (radial * angular))
            amplitude[o] += np.abs(eo[m : m + h, m : m + w])
    max_amp = amplitude.max(axis=0)
    mim = (amplitude.argmax(axis=0) + 1).astype(np.uint8)
    mim[max_amp <= cfg.min_amplitude] = 0
    return mim, max_amp


# ---- FAST keypoints --------------------------------------------------------------------------------------------
def descriptor_radius(cfg: FeatureConfig) -> int:
    """Half the side of the patch cut around a keypoint: J*sqrt(2)/2 (69 px for J = 96)."""
    return int(np.ceil(cfg.patch_px * np.sqrt(2) / 2))


def fast_keypoints(image: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """(K, 2) int (row, col) FAST corners, all of them, strongest first."""
    pad = descriptor_radius(cfg)
    padded = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    fast = cv2.FastFeatureDetector_create(
        threshold=FAST_THRESHOLD, nonmaxSuppression=True, type=cv2.FAST_FEATURE_DETECTOR_TYPE_9_16
    )
    h, w = image.shape
    kept = []
    for kp in sorted(fast.detect(padded, None), key=lambda k: -k.response):
        r, c = int(round(kp.pt[1])) - pad, int(round(kp.pt[0])) - pad
        if 0 <= r < h and 0 <= c < w:  # drop corners in the padding
            kept.append((r, c))
    return np.array(kept, dtype=np.int64).reshape(-1, 2)


# ---- BVFT descriptors ------------------------------------------------------------------------------------------
def bvft_descriptors(
    mim: np.ndarray, amp: np.ndarray, rc: np.ndarray, cfg: FeatureConfig, n_orient: int = 12
) -> np.ndarray:
    """(K, D) float32 unit descriptors (all-zero for an empty patch), one keypoint at a time."""
    radius = descriptor_radius(cfg)
    side = 2 * radius  # 138 px: rows/cols kp - radius .. kp + radius - 1, the keypoint at index `radius`
    J, grid = cfg.patch_px, cfg.grid
    n_bins = n_orient // 2 if cfg.merge_bins else n_orient
    cell_px = J // grid
    crop = (side - J) // 2  # first row/col of the central J x J window of the rotated patch
    centre = crop + (J - 1) / 2.0  # that window's centre, half a pixel before the keypoint when J is even
    mim_p = np.pad(mim, radius)
    amp_p = np.pad(np.asarray(amp, dtype=np.float64), radius)
    rr, cc = np.mgrid[0:side, 0:side]
    d = np.hypot(rr - radius, cc - radius)
    weight = (1.0 - np.minimum(1.0, d / radius)) ** 2

    out = np.zeros((len(rc), grid * grid * n_bins), dtype=np.float32)
    for k, (r, c) in enumerate(np.asarray(rc, dtype=np.int64).reshape(-1, 2)):
        patch = mim_p[r : r + side, c : c + side]  # padded coords: the keypoint (r, c) sits at (radius, radius)
        patch_amp = amp_p[r : r + side, c : c + side]

        # Dominant orientation: amplitude- and distance-weighted histogram of MIM values.
        hist = np.bincount(patch.ravel(), weights=(weight * patch_amp).ravel(), minlength=n_orient + 1)[1:]
        if hist.max() > 0:
            m0 = int(hist.argmax())
            if hist[(m0 - 1) % n_orient] > hist[(m0 + 1) % n_orient]:
                m0 = (m0 - 1) % n_orient
            m = m0 + 1
        else:
            m = 0

        # Rotate the patch by 180/No deg * (m - 1) about the keypoint, nearest neighbour; crop J x J. Output
        # pixel o of the crop samples keypoint + R (o - (J - 1)/2), symmetric about the keypoint.
        a = (max(m, 1) - 1) * np.pi / n_orient
        ca, sa = np.cos(a), np.sin(a)
        M = np.array(
            [
                [ca, sa, radius - centre * (ca + sa) + _TIE_BIAS_PX],  # src col = radius + ca*qc + sa*qr
                [-sa, ca, radius - centre * (ca - sa) + _TIE_BIAS_PX],
            ]
        )  # src row = radius + ca*qr - sa*qc
        rotated = cv2.warpAffine(
            patch,
            M,
            (side, side),
            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        window = rotated[crop : crop + J, crop : crop + J].astype(np.int64)

        # Shift the values so that m becomes 1, then a count histogram per grid cell.
        shifted = np.where(window > 0, (window - max(m, 1)) % n_orient + 1, 0)
        bins = (shifted - 1) // 2 if cfg.merge_bins else shifted - 1
        for ci in range(grid):
            r0, r1 = ci * cell_px, (ci + 1) * cell_px if ci < grid - 1 else J
            for cj in range(grid):
                c0, c1 = cj * cell_px, (cj + 1) * cell_px if cj < grid - 1 else J
                cell_bins = bins[r0:r1, c0:c1][shifted[r0:r1, c0:c1] > 0]
                start = (ci * grid + cj) * n_bins
                out[k, start : start + n_bins] = np.bincount(cell_bins, minlength=n_bins)
        norm = np.linalg.norm(out[k])
        if norm > 0:
            out[k] /= norm
    return out


def flip_180(desc: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """The descriptors of the same patches turned by 180 deg: the grid cells in reverse order."""
    n_cells = cfg.grid * cfg.grid
    k, dim = desc.shape
    return desc.reshape(k, n_cells, dim // n_cells)[:, ::-1, :].reshape(k, dim).copy()


# ---- matching --------------------------------------------------------------------------------------------------
def nn_match(
    query: np.ndarray, train: np.ndarray, *, mutual: bool = False, ratio: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force L2 nearest neighbour of each non-empty query descriptor, one query at a time."""
    i_q, i_t = [], []
    if len(query) == 0 or len(train) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    q64, t64 = np.asarray(query, np.float64), np.asarray(train, np.float64)
    for i, q in enumerate(q64):
        if not q.any():
            continue
        dist = np.sqrt(((t64 - q) ** 2).sum(axis=1))
        j = int(dist.argmin())
        if ratio < 1.0 and len(dist) > 1 and not dist[j] < ratio * np.partition(dist, 1)[1]:
            continue
        if mutual and int(np.sqrt(((q64 - t64[j]) ** 2).sum(axis=1)).argmin()) != i:
            continue
        i_q.append(i)
        i_t.append(j)
    return np.array(i_q, dtype=np.int64), np.array(i_t, dtype=np.int64)


# ---- RANSAC ----------------------------------------------------------------------------------------------------
def fixed_ransac(
    src: np.ndarray,
    dst: np.ndarray,
    *,
    threshold: float,
    min_sample_dist: float,
    iterations: int = RANSAC_ITERATIONS,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray] | None:
    """dst ~ T @ src by 2-point rigid RANSAC, ``iterations`` one at a time, then a Kabsch refit on the inliers.
    Returns (T 3x3, inlier mask) or None when no valid sample exists."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    n = len(src)
    if n < 2:
        return None
    rng = np.random.default_rng(seed)
    thr2 = threshold * threshold
    best_count, best_T = -1, None
    for _ in range(iterations):
        i, j = rng.integers(0, n, 2)
        vs, vd = src[j] - src[i], dst[j] - dst[i]
        if i == j or np.hypot(*vs) < min_sample_dist:
            continue
        yaw = np.arctan2(vd[1], vd[0]) - np.arctan2(vs[1], vs[0])
        T = se2(yaw, 0.0, 0.0)
        T[:2, 2] = (dst[i] + dst[j]) / 2 - T[:2, :2] @ ((src[i] + src[j]) / 2)
        count = int((((src @ T[:2, :2].T + T[:2, 2] - dst) ** 2).sum(axis=1) < thr2).sum())
        if count > best_count:
            best_count, best_T = count, T
    if best_T is None:
        return None
    inliers = ((src @ best_T[:2, :2].T + best_T[:2, 2] - dst) ** 2).sum(axis=1) < thr2
    if inliers.sum() >= 2:  # least-squares refit on the best hypothesis' inliers (as the reference, but right)
        best_T = kabsch_2d(src[inliers], dst[inliers])
        inliers = ((src @ best_T[:2, :2].T + best_T[:2, 2] - dst) ** 2).sum(axis=1) < thr2
    return best_T, inliers


# ---- dense BV refinement ---------------------------------------------------------------------------------------
def lit_pixels_m(bev: BevImage, min_value: int) -> np.ndarray:
    return bev.pixel_to_metre(np.argwhere(bev.image >= min_value))


@dataclass
class Refined:
    T: np.ndarray  # 3x3: the refined pose, or T_init when the refinement was rejected
    accepted: bool
    fitness: float  # fraction of the peer points within the finest gate of an ego lit pixel, under T


def refine_pose(ego: BevImage, peer: BevImage, T_init: np.ndarray, cfg: RefineConfig, seed: int = 0) -> Refined:
    """Point-to-line ICP of the peer's lit pixels onto the ego's, from T_init; the ego's KD-tree and normals
    are rebuilt on every call."""
    T_init = np.array(T_init, dtype=float)
    xy_ego = lit_pixels_m(ego, cfg.min_pixel_value)
    pts = lit_pixels_m(peer, cfg.min_pixel_value)
    if len(pts) > cfg.max_peer_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), cfg.max_peer_points, replace=False)]
    if len(xy_ego) == 0 or len(pts) == 0:
        return Refined(T_init, False, 0.0)
    tree = cKDTree(xy_ego)

    def fitness(T: np.ndarray) -> float:
        d, _ = tree.query(pts @ T[:2, :2].T + T[:2, 2], distance_upper_bound=cfg.gates_m[-1])
        return float(np.isfinite(d).mean())

    if len(xy_ego) < cfg.min_points or len(pts) < cfg.min_points:
        return Refined(T_init, False, fitness(T_init))
    _, nn = tree.query(xy_ego, k=min(rf.NORMAL_NEIGHBOURS, len(xy_ego)))
    nb = xy_ego[nn] - xy_ego[nn].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    normals = np.linalg.eigh(cov)[1][:, :, 0]  # eigenvector of the smallest eigenvalue: across the line
    T = T_init.copy()
    for gate in cfg.gates_m:
        for _ in range(cfg.iters_per_gate):
            p = pts @ T[:2, :2].T + T[:2, 2]
            d, j = tree.query(p, distance_upper_bound=gate)
            ok = np.isfinite(d)
            if ok.sum() < cfg.min_points:
                return Refined(T_init, False, fitness(T_init))
            p, q, nrm = p[ok], xy_ego[j[ok]], normals[j[ok]]
            r_line = ((p - q) * nrm).sum(1)
            w = 1.0 / np.maximum(1.0, np.abs(r_line) / (rf.HUBER_FRACTION * gate))  # Huber
            # Unknowns (dyaw, dtx, dty) of a small motion applied after T; d p / d yaw = (-p_y, p_x).
            J_line = np.column_stack([nrm[:, 1] * p[:, 0] - nrm[:, 0] * p[:, 1], nrm[:, 0], nrm[:, 1]])
            J_x = np.column_stack([-p[:, 1], np.ones(len(p)), np.zeros(len(p))])
            J_y = np.column_stack([p[:, 0], np.zeros(len(p)), np.ones(len(p))])
            H = (J_line * w[:, None]).T @ J_line + rf.POINT_WEIGHT**2 * (J_x.T @ J_x + J_y.T @ J_y)
            g = (J_line * (w * r_line)[:, None]).T.sum(1) + rf.POINT_WEIGHT**2 * (
                J_x.T @ (p[:, 0] - q[:, 0]) + J_y.T @ (p[:, 1] - q[:, 1])
            )
            delta = np.linalg.solve(H, -g)
            T = se2(*delta) @ T
            if abs(delta[0]) < rf.CONVERGED_RAD and np.abs(delta[1:]).max() < rf.CONVERGED_M:
                break
    yaw, tx, ty = se2_params(T @ np.linalg.inv(T_init))
    accepted = bool(np.hypot(tx, ty) <= cfg.max_correction_m and abs(np.degrees(yaw)) <= cfg.max_correction_deg)
    T_out = T if accepted else T_init
    return Refined(T_out, accepted, fitness(T_out))


# ---- box stage -------------------------------------------------------------------------------------------------
def _box_corners(box: np.ndarray) -> np.ndarray:
    """(4, 2) BV corners of one box: front-right, front-left, rear-left, rear-right."""
    x, y, _, length, width, _, yaw = box
    c, s = np.cos(yaw), np.sin(yaw)
    local = [(length / 2, -width / 2), (length / 2, width / 2), (-length / 2, width / 2), (-length / 2, -width / 2)]
    return np.array([(x + c * a - s * b, y + s * a + c * b) for a, b in local])


def box_stage(
    boxes_ego: np.ndarray, boxes_peer: np.ndarray, T_bv: np.ndarray, cfg: BoxConfig, seed: int = 0
) -> tuple[np.ndarray, int, int]:
    """(T_box 3x3, corner inliers, box pairs): peer boxes moved by T_bv, paired one-to-one with the ego's
    (centres within the gate), corners paired by the best cyclic shift, rigid RANSAC on the corner pairs."""
    yaw_bv = se2_params(T_bv)[0]
    moved = []
    for b in boxes_peer:
        xy = T_bv[:2, :2] @ b[:2] + T_bv[:2, 2]
        moved.append([xy[0], xy[1], b[2], b[3], b[4], b[5], b[6] + yaw_bv])
    moved = np.array(moved).reshape(-1, 7)
    if len(boxes_ego) == 0 or len(moved) == 0:
        return np.eye(3), 0, 0
    dist = np.array([[np.hypot(*(e[:2] - p[:2])) for p in moved] for e in boxes_ego])
    ia, ib = linear_sum_assignment(np.where(dist < cfg.pair_gate_m, dist, 1e6))
    pairs = [(a, b) for a, b in zip(ia, ib) if dist[a, b] < cfg.pair_gate_m]
    if not pairs:
        return np.eye(3), 0, 0
    src, dst = [], []
    for a, b in pairs:
        ce, cp = _box_corners(boxes_ego[a]), _box_corners(moved[b])
        shift = min(range(4), key=lambda k: np.linalg.norm(np.roll(cp, -k, axis=0) - ce, axis=1).sum())
        src.append(np.roll(cp, -shift, axis=0))
        dst.append(ce)
    fit = fixed_ransac(
        np.concatenate(src),
        np.concatenate(dst),
        threshold=cfg.ransac.inlier_threshold_m,
        min_sample_dist=cfg.ransac.min_sample_dist_m,
        iterations=cfg.ransac.max_iterations,
        seed=seed,
    )
    if fit is None:
        return np.eye(3), 0, len(pairs)
    return fit[0], int(fit[1].sum()), len(pairs)


# ---- the pipeline ----------------------------------------------------------------------------------------------
@dataclass
class BaselineFeatures:
    bev: BevImage
    boxes: np.ndarray
    keypoints_rc: np.ndarray
    keypoints_xy: np.ndarray
    descriptors: np.ndarray
    descriptors_flipped: np.ndarray
    timings_ms: dict[str, float] = field(default_factory=dict)
    mim: np.ndarray | None = None


@dataclass
class BaselineResult:
    success: bool
    reason: str | None
    T_ego_peer: np.ndarray  # 4x4
    T_bv: np.ndarray  # 3x3 after refinement
    inliers_bv: int = 0
    inliers_box: int = 0
    matches_bv: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)


class BaselineAligner:
    """``prepare`` and ``align`` with the engine's meaning and defaults (same AlignConfig), baseline speed."""

    def __init__(self, config: AlignConfig | None = None, ransac_iterations: int = RANSAC_ITERATIONS):
        self.config = config or AlignConfig()
        self.ransac_iterations = ransac_iterations

    def prepare(self, bev: BevImage, boxes=None) -> BaselineFeatures:
        cfg = self.config
        if abs(bev.resolution_m - cfg.bev.resolution_m) > 1e-9:
            raise ValueError(
                f"bev.resolution_m {bev.resolution_m} differs from the configured "
                f"{cfg.bev.resolution_m}; the baseline does not resample"
            )
        timings: dict[str, float] = {}
        with _timed(timings, "mim"):
            mim, amp = log_gabor_mim(bev.image, cfg.mim)
        with _timed(timings, "keypoints"):
            rc = fast_keypoints(bev.image, cfg.features)
        with _timed(timings, "descriptors"):
            desc = bvft_descriptors(mim, amp, rc, cfg.features, cfg.mim.n_orient)
            desc_flip = flip_180(desc, cfg.features)
        boxes = np.zeros((0, 7)) if boxes is None else np.asarray(boxes, dtype=float).reshape(-1, 7)
        return BaselineFeatures(bev, boxes, rc, bev.pixel_to_metre(rc), desc, desc_flip, timings, mim)

    def align(self, ego: BaselineFeatures, peer: BaselineFeatures) -> BaselineResult:
        cfg = self.config
        m, rule, seed = cfg.match, cfg.success, cfg.seed
        timings: dict[str, float] = {}
        T_bv, T_box = np.eye(3), np.eye(3)
        res = BaselineResult(False, None, np.eye(4), T_bv, timings_ms=timings)

        def finish(reason: str | None) -> BaselineResult:
            res.T_bv = T_bv
            res.T_ego_peer = se3_from_se2(T_box @ T_bv)
            res.success, res.reason = reason is None, reason
            timings["align_total"] = sum(v for k, v in timings.items() if k != "align_total")
            return res

        if len(ego.keypoints_rc) < 3 or len(peer.keypoints_rc) < 3:
            return finish("no_keypoints")
        with _timed(timings, "matching"):
            train = np.concatenate([ego.descriptors, ego.descriptors_flipped])
            i_peer, i_ego = nn_match(peer.descriptors, train, mutual=m.mutual, ratio=m.ratio)
            i_ego = i_ego % len(ego.descriptors)
        res.matches_bv = len(i_peer)
        with _timed(timings, "ransac"):
            fit = fixed_ransac(
                peer.keypoints_xy[i_peer],
                ego.keypoints_xy[i_ego],
                threshold=cfg.ransac.inlier_threshold_m,
                min_sample_dist=cfg.ransac.min_sample_dist_m,
                iterations=self.ransac_iterations,
                seed=seed,
            )
        if fit is None:
            return finish("too_few_matches")
        T_bv, inliers = fit
        res.inliers_bv = int(inliers.sum())
        if res.inliers_bv <= rule.min_inliers_bv:
            return finish("too_few_inliers_bv")
        ref = None
        if cfg.refine.enabled:
            with _timed(timings, "refine"):
                ref = refine_pose(ego.bev, peer.bev, T_bv, cfg.refine, seed=seed)
            T_bv = ref.T
            if ref.fitness < rule.min_refine_fitness:
                return finish("inconsistent_overlap")
        if len(ego.boxes) == 0 or len(peer.boxes) == 0:
            return finish("no_boxes" if rule.require_boxes else None)
        with _timed(timings, "boxes"):
            T_fit, res.inliers_box, pairs = box_stage(ego.boxes, peer.boxes, T_bv, cfg.box, seed=seed)
        failure = (
            "no_box_overlap"
            if pairs == 0
            else ("too_few_inliers_box" if res.inliers_box <= rule.min_inliers_box else None)
        )
        if failure is not None:
            return finish(failure)
        yaw, tx, ty = se2_params(T_fit)
        if np.hypot(tx, ty) > cfg.box.max_correction_m or abs(np.degrees(yaw)) > cfg.box.max_correction_deg:
            return finish("box_correction_too_large")
        refined = ref is not None and ref.accepted
        if cfg.box.apply == "always" or not refined:
            T_box = T_fit
        elif cfg.box.apply == "auto" and (np.hypot(tx, ty) > RECHECK_M or abs(np.degrees(yaw)) > RECHECK_DEG):
            # A large box correction: refine again from the box-corrected pose, keep it if the images agree more.
            alt = refine_pose(ego.bev, peer.bev, T_fit @ T_bv, cfg.refine, seed=seed)
            if alt.accepted and alt.fitness > ref.fitness + RECHECK_MIN_GAIN:
                T_box = alt.T @ np.linalg.inv(T_bv)
        return finish(None)
