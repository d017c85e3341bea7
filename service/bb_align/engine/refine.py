"""Dense refinement of the stage-1 pose on the BV images themselves (an addition to the paper).

Keypoint RANSAC leaves a residual of a few decimetres and tenths of a degree: corresponding FAST corners seen
from two cars sit a pixel or two apart. Starting from T_bv, a robust 2-D point-to-line ICP between the lit
pixels of the two images (ego pixels with PCA normals, cached per ego frame) removes most of it. The correction
is bounded: a refinement that wanders off (degenerate scene) is discarded and stage 1's pose kept.

The ego points are pixel centres, so a peer point's nearest ego point within a gate is found exactly by looking
at the few pixels around it (a compiled loop over an index image) instead of a KD-tree search.

A LiDAR sees the face of an object turned towards it. Between two cars the ego car sees the near face of a parked
car, a pole or a trunk and the peer its far face: pairing the two faces pulls the cars together by the object's
thickness (measured: the refinement started at the true pose drifted a median 0.83 m towards the ego car at 85-100 m
apart). So every normal faces its own sensor, and a pair whose two normals disagree (``RefineConfig.facing_min_cos``)
is not a correspondence: it is two sides of one thing (docs/acquisition.md, session 14).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from .bev import BevImage
from .config import RefineConfig
from .geometry import se2_params

# The ICP's fixed numbers (the verification's margins and the covariance's inflation were calibrated with them):
NORMAL_NEIGHBOURS = 8  # ego pixels in each ego pixel's PCA normal
PEER_NORMAL_PX = 2  # half window (pixels) of the peer pixels' PCA normals
HUBER_FRACTION = 0.25  # Huber threshold of the point-to-line residual, as a fraction of the current gate
POINT_WEIGHT = 0.1  # weight of the point-to-point terms beside the point-to-line ones: pins motion along a line
# A Gauss-Newton step continuing the previous one is lengthened this much: ICP creeps along shallow valleys in small
# steps of one direction (2: KITTI 0.04 m / 0.07 deg in 12 steps instead of 24).
STEP_RELAXATION = 2.0
CONVERGED_RAD, CONVERGED_M = 2e-5, 0.002  # a step under both (yaw, translation) ends a gate


@dataclass
class BevCloud:
    """The lit pixels of one BV image as 2-D points (metres, sensor frame), with normals, and the image of their
    indices (-1 where unlit) for nearest-point look-ups."""

    xy: np.ndarray  # (N, 2)
    normals: np.ndarray  # (N, 2) unit
    index: np.ndarray  # (H, W) int32: row of xy at each lit pixel, -1 elsewhere
    range_m: float
    resolution_m: float
    clearance: np.ndarray  # (H, W) float32: each pixel centre's distance (pixels) to the nearest lit one

    def nearest(self, pts: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
        """For each (M, 2) point: (distance, index) of the nearest point of this cloud closer than ``gate``
        metres; (inf, -1) when there is none (as a KD-tree query with distance_upper_bound)."""
        pts = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, 2)
        return _nearest_on_grid(self.index, self.clearance, self.xy, pts, self.range_m, self.resolution_m, float(gate))

    @property
    def grid(self) -> EgoGrid:
        """What the compiled loops read."""
        return EgoGrid(self.index, self.clearance, self.xy, self.normals, float(self.range_m), float(self.resolution_m))


def bev_points(bev: BevImage, min_value: int = 1, max_points: int | None = None, seed: int = 0) -> np.ndarray:
    """(N, 2) metres of the pixels with value >= min_value (optionally a seeded random subset)."""
    return bev_samples(bev, min_value, [max_points], seed)[0]


def bev_samples(bev: BevImage, min_value: int, sizes: list[int | None], seed: int = 0) -> list[np.ndarray]:
    """``bev_points(bev, min_value, n, seed)`` for each n of ``sizes`` (the same subsets), from one scan of the
    image."""
    rc = np.argwhere(bev.image >= min_value)
    rng = np.random.default_rng
    return [
        bev.pixel_to_metre(rc if n is None or len(rc) <= n else rc[rng(seed).choice(len(rc), n, replace=False)])
        for n in sizes
    ]


def bev_cloud(bev: BevImage, cfg: RefineConfig | None = None) -> BevCloud:
    """The ego side of the refinement: lit pixels (>= cfg.min_pixel_value) with PCA normals of their
    NORMAL_NEIGHBOURS nearest pixels."""
    cfg = cfg or RefineConfig()
    k = NORMAL_NEIGHBOURS
    rc = np.argwhere(bev.image >= cfg.min_pixel_value)
    xy = bev.pixel_to_metre(rc)
    index = np.full(bev.shape, -1, dtype=np.int32)
    index[rc[:, 0], rc[:, 1]] = np.arange(len(rc), dtype=np.int32)
    clearance = clearance_map(index >= 0)
    if len(xy) < 3:
        return BevCloud(xy, np.zeros_like(xy), index, bev.range_m, bev.resolution_m, clearance)
    _, nn = cKDTree(xy).query(xy, k=min(k, len(xy)))
    nb = xy[nn] - xy[nn].mean(axis=1, keepdims=True)
    sxx, syy, sxy = (nb[..., 0] ** 2).sum(1), (nb[..., 1] ** 2).sum(1), (nb[..., 0] * nb[..., 1]).sum(1)
    # Normal = eigenvector of the smaller eigenvalue of [[sxx, sxy], [sxy, syy]]: the line's perpendicular.
    angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # direction of the larger eigenvalue (the line)
    normals = facing_sensor(xy, np.stack([-np.sin(angle), np.cos(angle)], axis=1))
    return BevCloud(xy, normals, index, bev.range_m, bev.resolution_m, clearance)


def facing_sensor(xy: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The unit normals turned towards the sensor (the frame's origin): the side of the surface it saw. The
    point-to-line residual is the same either way."""
    flip = (normals * xy).sum(axis=1) > 0  # n . (0 - xy) < 0: pointing away
    return np.where(flip[:, None], -normals, normals)


def peer_normals(bev: BevImage, pts: np.ndarray, cfg: RefineConfig) -> np.ndarray:
    """(N, 2) unit normals at the peer points ``pts`` (pixel centres of ``bev``), facing the peer's sensor: the PCA
    of the lit pixels within ``PEER_NORMAL_PX`` of each (a compiled window scan: the peer pays no KD-tree). A
    pixel with no line around it (alone, or in a round blob) gets the direction to the sensor: the face it shows."""
    pts = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, 2)
    lit = np.ascontiguousarray(bev.image >= cfg.min_pixel_value)
    n = _window_normals(lit, pts, float(bev.range_m), float(bev.resolution_m), PEER_NORMAL_PX)
    return facing_sensor(pts, n)


@njit(cache=True, nogil=True)
def _window_normals(lit, pts, range_m, resolution_m, half):
    n_rows, n_cols = lit.shape
    out = np.empty_like(pts)
    for i in range(len(pts)):
        r0 = int(np.floor((range_m - pts[i, 0]) / resolution_m))
        c0 = int(np.floor((range_m - pts[i, 1]) / resolution_m))
        m, sx, sy, sxx, syy, sxy = 0, 0.0, 0.0, 0.0, 0.0, 0.0
        for r in range(max(0, r0 - half), min(n_rows, r0 + half + 1)):
            for c in range(max(0, c0 - half), min(n_cols, c0 + half + 1)):
                if lit[r, c]:
                    x, y = float(r - r0), float(c - c0)  # pixel offsets: the normal is turned to metres below
                    m += 1
                    sx += x
                    sy += y
                    sxx += x * x
                    syy += y * y
                    sxy += x * y
        cxx, cyy, cxy = 0.0, 0.0, 0.0
        if m >= 3:
            cxx, cyy, cxy = sxx / m - (sx / m) ** 2, syy / m - (sy / m) ** 2, sxy / m - (sx / m) * (sy / m)
        # A line: the eigenvalue gap at least half their sum (~0 for a round blob; 0 for fewer than 3 pixels).
        if m >= 3 and np.hypot(cxx - cyy, 2 * cxy) >= 0.5 * (cxx + cyy):
            angle = 0.5 * np.arctan2(2 * cxy, cxx - cyy)  # the line's direction in (row, col) offsets
            # rows grow towards -x, columns towards -y: the line's direction in metres is (-cos, -sin); its normal:
            out[i, 0], out[i, 1] = np.sin(angle), -np.cos(angle)
        else:
            d = max(np.hypot(pts[i, 0], pts[i, 1]), 1e-9)
            out[i, 0], out[i, 1] = -pts[i, 0] / d, -pts[i, 1] / d
    return out


def clearance_map(lit: np.ndarray) -> np.ndarray:
    """(H, W) float32: the Euclidean distance (pixels) from each pixel centre to the nearest lit one (OpenCV's
    exact transform, within 1e-5 of scipy's distance_transform_edt); inf everywhere without a lit pixel."""
    if not lit.any():
        return np.full(lit.shape, np.inf, np.float32)
    return cv2.distanceTransform((~lit).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


@dataclass
class Refinement:
    T: np.ndarray  # 3x3 refined T_ego_peer
    fitness: float  # fraction of peer points with an ego point within the final gate, at the returned T
    rmse_m: float
    accepted: bool


class Refiner:
    """The dense refinement as a pipeline step, built once from its config: ``sample`` the peer's lit pixels
    (seeded subset), ``refine`` them onto an ego frame's cloud from a start pose."""

    def __init__(self, cfg: RefineConfig, seed: int = 0):
        self.cfg, self.seed = cfg, seed

    @property
    def enabled(self) -> bool:
        return self.cfg.enabled

    def sample(self, peer: BevImage) -> tuple[np.ndarray, np.ndarray]:
        """(points, their normals facing the peer's sensor): what ``refine`` takes."""
        pts = bev_points(peer, self.cfg.min_pixel_value, self.cfg.max_peer_points, seed=self.seed)
        return pts, peer_normals(peer, pts, self.cfg)

    def refine(self, ego: BevCloud, sample: tuple[np.ndarray, np.ndarray], T_init: np.ndarray) -> Refinement:
        pts_peer, normals_peer = sample
        return refine_icp(ego, pts_peer, T_init, self.cfg, normals_peer)


def refine_icp(
    ego: BevCloud,
    pts_peer: np.ndarray,
    T_init: np.ndarray,
    cfg: RefineConfig | None = None,
    normals_peer: np.ndarray | None = None,
) -> Refinement:
    """Robust 2-D point-to-line ICP of peer points onto the ego cloud, from T_init (3x3, ego <- peer).
    ``normals_peer`` (``peer_normals``): pairs whose faces disagree are left out (module doc); None: all pair.

    ICP creeps along shallow valleys in small steps of the same direction; a step that continues the previous
    one is lengthened by ``STEP_RELAXATION``."""
    cfg = cfg or RefineConfig()
    gates = cfg.gates_m
    T = np.array(T_init, dtype=float)
    if len(ego.xy) < cfg.min_points or len(pts_peer) < cfg.min_points:
        return Refinement(T, *overlap_fitness(ego, pts_peer, T, gates[-1]), False)
    T, ok = _icp(ego, np.ascontiguousarray(pts_peer, dtype=np.float64), T, cfg, normals_peer)
    if not ok:
        T0 = np.array(T_init, dtype=float)
        return Refinement(T0, *overlap_fitness(ego, pts_peer, T0, gates[-1]), False)
    yaw, tx, ty = se2_params(T @ np.linalg.inv(T_init))
    accepted = bool(np.hypot(tx, ty) <= cfg.max_correction_m and abs(np.degrees(yaw)) <= cfg.max_correction_deg)
    T_out = T if accepted else np.array(T_init, dtype=float)
    fitness, rmse = overlap_fitness(ego, pts_peer, T_out, gates[-1])
    return Refinement(T_out, fitness, rmse, accepted)


def _icp(
    ego: BevCloud, pts: np.ndarray, T: np.ndarray, cfg: RefineConfig, normals_peer: np.ndarray | None
) -> tuple[np.ndarray, bool]:
    """The ICP iterations of refine_icp (compiled): (the pose they end at, False when a step matched fewer than
    cfg.min_points points)."""
    pn, min_cos = facing_args(pts, normals_peer, cfg.facing_min_cos)
    return _icp_loop(ego.grid, pts, pn, T, icp_params(cfg, min_cos))


def facing_args(pts: np.ndarray, normals_peer: np.ndarray | None, min_cos: float) -> tuple[np.ndarray, float]:
    """The compiled loops' (peer normals, min_cos) for ``facing``: without normals every pair faces alike (-1)."""
    if normals_peer is None:
        return np.zeros((len(pts), 2)), -1.0
    return np.ascontiguousarray(normals_peer, dtype=np.float64).reshape(-1, 2), float(min_cos)


class EgoGrid(NamedTuple):
    """A BevCloud as the compiled loops read it (``BevCloud.grid``)."""

    index: np.ndarray
    clearance: np.ndarray
    xy: np.ndarray
    normals: np.ndarray
    range_m: float
    resolution_m: float


class IcpParams(NamedTuple):
    """The refinement config as the compiled ICP loop reads it (``icp_params``)."""

    gates: np.ndarray  # metres, coarse to fine
    iters: int
    huber_fraction: float
    point_weight: float
    relaxation: float
    converged_rad: float
    converged_m: float
    min_points: int
    min_cos: float  # the facing test (``facing``); -1: off


def icp_params(cfg: RefineConfig, min_cos: float) -> IcpParams:
    """``cfg`` as _icp_loop's parameters, with the facing test's ``min_cos`` (``facing_args``)."""
    return IcpParams(
        np.asarray(cfg.gates_m, dtype=np.float64),
        cfg.iters_per_gate,
        HUBER_FRACTION,
        POINT_WEIGHT,
        STEP_RELAXATION,
        CONVERGED_RAD,
        CONVERGED_M,
        cfg.min_points,
        min_cos,
    )


@njit(cache=True, nogil=True)
def transform_into(pts, T, out):
    """out[i] = T applied to the 2-D point pts[i] (3x3 T)."""
    for i in range(len(pts)):
        x, y = pts[i, 0], pts[i, 1]
        out[i, 0] = T[0, 0] * x + T[0, 1] * y + T[0, 2]
        out[i, 1] = T[1, 0] * x + T[1, 1] * y + T[1, 2]


@njit(cache=True, nogil=True)
def _icp_loop(grid, pts, pn, T_init, params):
    """refine_icp's iterations: per gate up to ``iters`` Gauss-Newton steps (nearest ego pixel within the gate,
    point-to-line normal equations, the step lengthened by ``relaxation`` when it continues the previous one),
    the gate left when a step is below converged_rad and converged_m (``params``: IcpParams; ``grid``: EgoGrid).
    Returns (T, ok); ok False (and T_init) when a step finds fewer than min_points matches facing alike (``pn``,
    ``min_cos``: _normal_equations)."""
    index, clearance, xy, normals, range_m, resolution_m = grid
    gates, iters, huber_fraction, point_weight, relaxation, converged_rad, converged_m, min_points, min_cos = params
    T = T_init.copy()
    p = np.empty_like(pts)
    prev = np.zeros(3)
    have_prev = False
    for gate in gates:
        for _ in range(iters):
            transform_into(pts, T, p)
            _, j = _nearest_on_grid(index, clearance, xy, p, range_m, resolution_m, gate)
            H, g, m = _normal_equations(
                p, xy, normals, j, huber_fraction * gate, point_weight, pn, T[0, 0], T[1, 0], min_cos
            )
            if m < min_points:
                return T_init.copy(), False
            delta = np.linalg.solve(H, -g)
            if have_prev and delta[0] * prev[0] + delta[1] * prev[1] + delta[2] * prev[2] > 0:
                delta = delta * relaxation  # the same way again: ICP creeps along a valley
            prev = delta
            have_prev = True
            c, s = np.cos(delta[0]), np.sin(delta[0])
            T2 = np.empty((3, 3))
            for col in range(3):
                T2[0, col] = c * T[0, col] - s * T[1, col] + delta[1] * T[2, col]
                T2[1, col] = s * T[0, col] + c * T[1, col] + delta[2] * T[2, col]
                T2[2, col] = T[2, col]
            T = T2
            if abs(delta[0]) < converged_rad and max(abs(delta[1]), abs(delta[2])) < converged_m:
                break
    return T, True


@njit(cache=True, nogil=True)
def coarse_verification_loop(grid, covis, pts, pn, Ts, params, bounds):
    """The acquisition's coarse verification of the poses Ts (acquisition.verification.coarse_verification): per
    pose the ICP iterations (``params``: IcpParams), the correction kept when within ``bounds`` = (max_correction_m,
    max_correction_deg, final_gate) of the start (as refine_icp), then the overlap within final_gate
    (overlap_fitness: fraction of points with an ego pixel, RMS distance of those) and the fraction of points on the
    co-visibility mask ``covis`` (acquisition.verification.covisible_fraction). Here, beside the loops it calls:
    numba's on-disk cache is invalidated by its own file's changes only."""
    index, clearance, xy, normals, range_m, resolution_m = grid
    max_correction_m, max_correction_deg, final_gate = bounds
    min_points = params.min_points
    n_h, n = len(Ts), len(pts)
    out = np.empty_like(Ts)
    fitness, rmse, covisible = np.zeros(n_h), np.full(n_h, np.inf), np.zeros(n_h)
    p = np.empty_like(pts)
    for h in range(n_h):
        T0 = Ts[h]
        T = T0.copy()
        if len(xy) >= min_points and n >= min_points:
            T, ok = _icp_loop(grid, pts, pn, T0, params)
            if ok:
                rel = T @ np.linalg.inv(T0)
                yaw = np.arctan2(rel[1, 0], rel[0, 0])
                if not (
                    np.hypot(rel[0, 2], rel[1, 2]) <= max_correction_m and abs(np.degrees(yaw)) <= max_correction_deg
                ):
                    T = T0.copy()
        out[h] = T
        if n == 0:
            continue
        transform_into(pts, T, p)
        if len(xy) > 0:
            d, _ = _nearest_on_grid(index, clearance, xy, p, range_m, resolution_m, final_gate)
            m, ss = 0, 0.0
            for i in range(n):
                if d[i] < np.inf:
                    m += 1
                    ss += d[i] * d[i]
            fitness[h] = m / n
            if m > 0:
                rmse[h] = np.sqrt(ss / m)
        covisible[h] = covisible_share(covis, p, range_m, resolution_m)
    return out, fitness, rmse, covisible


@njit(cache=True, nogil=True)
def covisible_share(covis, p, range_m, resolution_m):
    """Fraction of the (N, 2) ego-frame points ``p`` on a pixel of the uint8 mask ``covis`` (covisible_map)."""
    h_img, w_img = covis.shape
    seen = 0
    for i in range(len(p)):
        r = int(np.floor((range_m - p[i, 0]) / resolution_m))
        c = int(np.floor((range_m - p[i, 1]) / resolution_m))
        if 0 <= r < h_img and 0 <= c < w_img:
            seen += covis[r, c]
    return seen / len(p)


def overlap_fitness(ego: BevCloud, pts_peer: np.ndarray, T: np.ndarray, gate: float) -> tuple[float, float]:
    """(fraction of peer points within ``gate`` of an ego lit pixel under T, RMS distance of those)."""
    if len(ego.xy) == 0 or len(pts_peer) == 0:
        return 0.0, float("inf")
    p = pts_peer @ T[:2, :2].T + T[:2, 2]
    d, _ = ego.nearest(p, gate)
    ok = np.isfinite(d)
    return float(ok.mean()), (float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else float("inf"))


_HALF_DIAGONAL_PX = 0.7072  # above sqrt(2) / 2: the farthest a point lies from its nearest pixel centre


@njit(cache=True, nogil=True)
def _nearest_on_grid(index, clearance, xy, pts, range_m, resolution_m, gate):
    """Exact nearest lit pixel centre within ``gate`` (strictly closer) of each point, scanning the pixels whose
    centres can be that close; (inf, -1) when none is. Among equally near ones, the first in row-major order.

    ``clearance``: each pixel centre's distance (pixels) to the nearest lit one. The point's nearest lit centre is
    within half a pixel diagonal of its pixel's clearance either way, which narrows the square scanned from the
    gate's to that distance's (a point on structure looks at 3x3 pixels, not 11x11) and skips the points with
    nothing within the gate. The square still holds every centre as near as the nearest, scanned in the same
    order: the result is that of the full square's scan."""
    n_rows, n_cols = index.shape
    dist = np.full(len(pts), np.inf)
    nearest = np.full(len(pts), -1, dtype=np.int64)
    reach_gate = gate / resolution_m
    gate2 = gate * gate
    for i in range(len(pts)):
        r = (range_m - pts[i, 0]) / resolution_m - 0.5  # continuous pixel coordinates (bev.metre_to_pixel)
        c = (range_m - pts[i, 1]) / resolution_m - 0.5
        if not (
            r + reach_gate >= 0
            and r - reach_gate <= n_rows - 1
            and c + reach_gate >= 0
            and c - reach_gate <= n_cols - 1
        ):
            continue  # off the image by more than the gate (or not a number): no pixel can be that close
        reach = reach_gate
        ra, ca = int(np.floor(r + 0.5)), int(np.floor(c + 0.5))  # the pixel the point falls in
        if 0 <= ra < n_rows and 0 <= ca < n_cols:
            near = clearance[ra, ca]
            if near - _HALF_DIAGONAL_PX - 1e-3 >= reach_gate:
                continue  # every lit centre at least a gate away
            reach = min(reach_gate, near + _HALF_DIAGONAL_PX + 1e-3)
        r0, r1 = max(0, int(np.ceil(r - reach))), min(n_rows - 1, int(np.floor(r + reach)))
        c0, c1 = max(0, int(np.ceil(c - reach))), min(n_cols - 1, int(np.floor(c + reach)))
        best = gate2
        for rr in range(r0, r1 + 1):
            for cc in range(c0, c1 + 1):
                j = index[rr, cc]
                if j >= 0:
                    dx = xy[j, 0] - pts[i, 0]
                    dy = xy[j, 1] - pts[i, 1]
                    d2 = dx * dx + dy * dy
                    if d2 < best:
                        best = d2
                        nearest[i] = j
        if nearest[i] >= 0:
            dist[i] = np.sqrt(best)
    return dist, nearest


@njit(cache=True, nogil=True, inline="always")
def facing(normals, j, pn, i, c, s, min_cos):
    """Whether the ego normal ``normals[j]`` and the peer normal ``pn[i]`` turned by the pose's rotation (c, s) agree
    within ``min_cos``: the two pixels are one face of one thing (module doc)."""
    return normals[j, 0] * (c * pn[i, 0] - s * pn[i, 1]) + normals[j, 1] * (s * pn[i, 0] + c * pn[i, 1]) >= min_cos


@njit(cache=True, nogil=True)
def _normal_equations(p, xy, normals, nearest, huber, point_weight, pn, c, s, min_cos):
    """Gauss-Newton normal equations (H, g) of the pose increment (yaw, tx, ty) applied on the left, over the
    points p[i] with a match q = xy[nearest[i]] whose normals face alike (``facing``; pn: the peer normals, (c, s)
    the pose's rotation): rows are the point-to-line residual n.(p - q), Huber-weighted (threshold ``huber``
    metres), plus weak point-to-point terms (weight point_weight^2) that pin the motion along the line. Returns
    (H, g, the number of pairs that took part)."""
    H = np.zeros((3, 3))
    g = np.zeros(3)
    pw2 = point_weight * point_weight
    m = 0
    for i in range(len(p)):
        j = nearest[i]
        if j < 0 or not facing(normals, j, pn, i, c, s, min_cos):
            continue
        m += 1
        px, py = p[i, 0], p[i, 1]
        dx, dy = px - xy[j, 0], py - xy[j, 1]
        nx, ny = normals[j, 0], normals[j, 1]
        jac = (nx * -py + ny * px, nx, ny)
        r = nx * dx + ny * dy
        w = 1.0 / max(1.0, abs(r) / huber)
        jac_x = (-py, 1.0, 0.0)  # d(p_x)/d(yaw, tx, ty)
        jac_y = (px, 0.0, 1.0)
        for a in range(3):
            g[a] += w * jac[a] * r + pw2 * (jac_x[a] * dx + jac_y[a] * dy)
            for b in range(3):
                H[a, b] += w * jac[a] * jac[b] + pw2 * (jac_x[a] * jac_x[b] + jac_y[a] * jac_y[b])
    return H, g, m
