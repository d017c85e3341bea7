"""The pose landscape around an answer: how well every nearby pose explains the two images, and the honest
uncertainty that follows (not in the paper).

The point-to-line refinement (engine.refine) converges to the nearest basin of its own objective. On real streets
at 70-100 m that basin is not the best overlap: on the KITTI 00 pairs the refinement started at the reference pose
moved 0.3-1.5 m along the street and lost a fifth of the overlap. And its covariance, from the curvature at one
point, cannot see a second basin a few metres along the street.

So the answer is judged on a grid instead (a correlative scan match, as in Olson's real-time correlative matching):
every pose within ``half_width_m`` / ``half_yaw_deg`` of the refined one is scored at the peer's lit pixels by the
ego image's likelihood fields, ``S(T) = sum_i f(d_i) / sum_i g(d_i)`` (``d_i``: the distance of peer pixel i under
T to the nearest ego lit pixel; ``f`` a narrow Gaussian, ``g`` a wide one): how well the structure that lands near
ego structure lies on it, not how much of it lands there (a pose moved towards the denser near field would
otherwise gain). The pose is the grid's peak; its distribution is ``p(T) ~ exp(effective_points S(T))``, whose
covariance is the answer's, never finer than the images' pixels.
``effective_points`` says how many independent measurements the peer's pixels are worth: neighbouring pixels of one
wall are one measurement seen many times (calibrated, see LandscapeConfig).

Further modes widen that covariance: the coarse grid's mass away from the peak, other poses the search found
(``with_rivals``) and the refinement's own pose when the landscape rules it out (``with_refinement``: the two
estimators disagree). A window whose peak lies near its edge in x / y moves onto the peak once (``follow_peak``):
a refinement that stopped a few metres off puts the peak, not a corridor, at the edge. A landscape whose mass still
reaches the edge of its window, or whose answer then lies outside the first window, has no bounded peak there (a
corridor): its covariance is unbounded and the pose stays where the refinement put it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from .config import LandscapeConfig
from .geometry import se2, se2_params
from .parallel import contiguous, run_parts
from .refine import BevCloud

_UNBOUNDED = 1e6  # variance (m^2 or rad^2) reported along an axis whose mass reaches the window's edge


@dataclass
class Landscape:
    """The scored grid around a pose and what follows from it."""

    T: np.ndarray  # 3x3 ego <- peer: the grid's peak (sub-cell: the distribution's mean near the peak)
    score: float  # S at the peak (mean likelihood-field value of the peer's pixels)
    covariance: np.ndarray  # 3x3 of (yaw rad, tx m, ty m) of T's own parameters
    at_edge: bool  # the distribution's mass reaches the window's edge: not bounded within it


@dataclass(frozen=True)
class GaussianPrior:
    """A prior pose with its 1-sigma (e.g. both cars' GNSS poses composed): weighs the rivals of an answer."""

    T: np.ndarray  # 3x3 ego <- peer
    sigma_m: float
    sigma_deg: float

    def log_density(self, poses: np.ndarray) -> np.ndarray:
        """log N (up to a constant) of (n, 3) poses (yaw rad, tx m, ty m)."""
        d = np.atleast_2d(poses) - np.array(se2_params(self.T))
        d[:, 0] = np.arctan2(np.sin(d[:, 0]), np.cos(d[:, 0]))
        return -0.5 * ((d[:, 0] / np.radians(self.sigma_deg)) ** 2 + (d[:, 1] ** 2 + d[:, 2] ** 2) / self.sigma_m**2)


def _exp_field(ego: BevCloud, sigma_m: float) -> np.ndarray:
    """(H, W) float32 at the ego image's pixels: exp(-d^2 / 2 sigma^2) of the distance d to the nearest lit pixel."""
    d = ego.clearance.astype(np.float64) * ego.resolution_m
    return np.exp(-0.5 * (d / sigma_m) ** 2).astype(np.float32)


def _exp_field_into(d_m: np.ndarray, sigma_m: float, work: np.ndarray) -> np.ndarray:
    """``_exp_field`` from the distances ``d_m`` (float64 m), computed in ``work``: the same operations in place."""
    np.divide(d_m, sigma_m, out=work)
    np.square(work, out=work)
    work *= -0.5
    np.exp(work, out=work)
    return work.astype(np.float32)


def _cells(field: np.ndarray, range_m: float, step_m: float) -> np.ndarray:
    n = int(round(2 * range_m / step_m))
    return cv2.resize(field, (n, n), interpolation=cv2.INTER_LINEAR)


def likelihood_field(ego: BevCloud, sigma_m: float, step_m: float) -> np.ndarray:
    """(H', W') float32 on a grid of ``step_m`` cells over the ego image (bilinear from its pixel centres):
    exp(-d^2 / 2 sigma^2) of the distance d to the nearest ego lit pixel. The grid's translations are whole cells
    of it, so scoring a pose is one look-up per point."""
    return _cells(_exp_field(ego, sigma_m), ego.range_m, step_m)


@njit(cache=True, nogil=True)
def _score_grid(fields, pts, yaws, n_off, cx, cy, range_m, step_m, out):
    """out[k, a, b] = the sum of the narrow field over the sum of the wide one at ``pts`` rotated by yaws[k] and
    moved to (cx + (a - n_off) step_m, cy + (b - n_off) step_m); a point off the fields counts in neither.
    ``fields``: ``_layout``'s (H, 2 W), the columns reversed and the two fields interleaved, so that one point's
    (2 n_off + 1) column offsets in a row are one contiguous run of both fields, added to one contiguous run of the
    sums (a loop the compiler turns into vector adds). Point by point, each adding its block, where pose by pose
    every point would be a cache miss; each sum still runs over the points in order: the same to the bit."""
    h_img, w_img = fields.shape[0], fields.shape[1] // 2
    n = len(pts)
    size = 2 * n_off + 1
    sums = np.empty((size, 2 * size))  # [a, 2 b]: narrow, [a, 2 b + 1]: wide
    for k in range(len(yaws)):
        c, s = np.cos(yaws[k]), np.sin(yaws[k])
        sums[:] = 0.0
        for i in range(n):
            x = c * pts[i, 0] - s * pts[i, 1] + cx
            y = s * pts[i, 0] + c * pts[i, 1] + cy
            r0 = int(np.floor((range_m - x) / step_m)) + n_off  # the row at offset a is r0 - a
            q0 = int(np.floor((range_m - y) / step_m)) + n_off  # the column at offset b is q0 - b
            a_lo, a_hi = max(0, r0 - h_img + 1), min(size, r0 + 1)
            b_lo, b_hi = max(0, q0 - w_img + 1), min(size, q0 + 1)
            if b_hi <= b_lo:
                continue
            first = 2 * (w_img - 1 - q0 + b_lo)  # reversed column of offset b_lo, interleaved
            width = 2 * (b_hi - b_lo)
            for a in range(a_lo, a_hi):
                src = fields[r0 - a, first : first + width]
                dst = sums[a, 2 * b_lo : 2 * b_hi]
                for j in range(width):  # slices: no index wrap-around, so the loop vectorises
                    dst[j] += src[j]
        for a in range(size):
            for b in range(size):
                norm = sums[a, 2 * b + 1]
                out[k, a, b] = sums[a, 2 * b] / norm if norm > 0 else 0.0


def _layout(narrow: np.ndarray, wide: np.ndarray) -> np.ndarray:
    """The two fields as ``_score_grid`` reads them: (H, 2 W) float32, columns reversed, narrow and wide
    interleaved per cell (OpenCV's merge and flip: one copy each, cheaper than numpy's stack and reversed copy)."""
    both = cv2.flip(cv2.merge([np.asarray(narrow, np.float32), np.asarray(wide, np.float32)]), 1)
    return both.reshape(narrow.shape[0], 2 * narrow.shape[1])


def score_grid(
    fields: np.ndarray | tuple[np.ndarray, np.ndarray],
    ego: BevCloud,
    pts_peer: np.ndarray,
    T: np.ndarray,
    yaws: np.ndarray,
    n_off: int,
    step_m: float,
) -> np.ndarray:
    """S over the grid of poses (yaw of T + yaws[k], translation of T + (a, b) step_m for a, b in -n_off..n_off);
    ``fields``: the narrow and the wide likelihood field at ``step_m`` cells as ``Fields`` keeps them (``_layout``),
    or a pair (H, W) each. The yaws are cut into parts scored in parallel. Rotation is about the peer's sensor (T's
    own parameters)."""
    yaw0, tx, ty = se2_params(T)
    pts = np.ascontiguousarray(pts_peer, dtype=np.float64)
    size = 2 * n_off + 1
    stacked = fields if isinstance(fields, np.ndarray) else _layout(*fields)

    def part(ks: np.ndarray) -> np.ndarray:
        out = np.zeros((len(ks), size, size))
        _score_grid(stacked, pts, yaw0 + ks, n_off, tx, ty, ego.range_m, step_m, out)
        return out

    return np.concatenate(run_parts(part, contiguous(np.asarray(yaws, dtype=np.float64), 2)), axis=0)  # fmt: skip


def landscape(
    ego: BevCloud,
    fields: Fields,
    pts_peer: np.ndarray,
    T: np.ndarray,
    cfg: LandscapeConfig,
) -> Landscape:
    """Score the grid around T (3x3 ego <- peer) and take its peak and distribution (module doc). Coarse to fine:
    the whole window on cells twice ``step_m`` and three times ``step_deg``, then ``fine_cells`` fine cells each way
    around the coarse peak. The fine grid gives the peak's shape; the coarse grid's mass outside it (other modes)
    widens the covariance about the answer. When the coarse mass reaches the window's edge and its peak is off
    the centre in x / y, the window moves onto that peak's translation once (``follow_peak``) to see the whole of
    it; the answer must still lie inside the first window: the grid recentres on a peak it saw and never climbs."""
    T_start = np.array(T, dtype=float)
    first, coarse, pts_peer = _coarse_window(ego, fields, pts_peer, T_start, cfg)
    fine = _grid(
        fields.fine,
        ego,
        pts_peer,
        se2(*coarse.peak),
        cfg.fine_cells * cfg.step_m,
        cfg.step_m,
        cfg.fine_cells * cfg.step_deg,
        cfg.step_deg,
        cfg.effective_points,
    )
    answer = np.where(np.abs(fine.mean - fine.peak) <= fine.step, fine.mean, fine.peak)
    # The coarse mass outside the fine window: further modes, about the answer.
    outside = ~fine.covers(coarse.poses)
    share = float(coarse.p[outside].sum())
    d = coarse.poses[outside] - answer
    d[:, 0] = np.arctan2(np.sin(d[:, 0]), np.cos(d[:, 0]))
    spread = (d * coarse.p[outside][:, None]).T @ d / max(share, 1e-300)
    cov = (1.0 - share) * fine.covariance + share * spread
    # Neither can the answer be finer than the images: a wall is quantised to one pixel in each image, the same
    # for all its points (res^2 / 12 per image, two images), nor than the grid's yaw cells.
    cov += np.diag([fine.step[0] ** 2 / 12.0, ego.resolution_m**2 / 6.0, ego.resolution_m**2 / 6.0])
    if coarse.edge_mass() > cfg.max_edge_mass or not first.covers(answer[None, :])[0]:
        # No bounded peak (or one only beyond the first window): the pose stays where it was, unbounded.
        return Landscape(T_start, max(coarse.best, fine.best), np.diag([_UNBOUNDED] * 3), True)
    return Landscape(se2(*answer), max(coarse.best, fine.best), 0.5 * (cov + cov.T), False)


def _coarse(ego: BevCloud, fields: Fields, pts_peer: np.ndarray, T: np.ndarray, cfg: LandscapeConfig):
    """The whole window around T on coarse cells, scored on the peer points that stay on the ego image."""
    pts = _inside(ego, pts_peer, [T], cfg.half_width_m + np.radians(cfg.half_yaw_deg) * ego.range_m)
    grid = _grid(
        fields.coarse,
        ego,
        pts,
        T,
        cfg.half_width_m,
        2 * cfg.step_m,
        cfg.half_yaw_deg,
        3 * cfg.step_deg,
        cfg.effective_points,
    )
    return grid, pts


def _coarse_window(ego: BevCloud, fields: Fields, pts_peer: np.ndarray, T: np.ndarray, cfg: LandscapeConfig):
    """(the first coarse grid, the one the answer is read from, its points). When the first grid's mass reaches its
    edge with the peak off the centre in x / y, the window's translation moves onto the peak once. Only the
    translation follows (the refinement's known failure is to stop short along a street); a peak at the yaw edge is
    a disagreement in yaw, left to the verdict."""
    first, pts = _coarse(ego, fields, pts_peer, T, cfg)
    shift = first.peak[1:] - first.centre[1:]
    if cfg.follow_peak and first.edge_mass() > cfg.max_edge_mass and np.any(np.abs(shift) > first.step[1] + 1e-9):
        return first, *_coarse(ego, fields, pts_peer, se2(first.centre[0], *first.peak[1:]), cfg)
    return first, first, pts


def _inside(ego: BevCloud, pts_peer: np.ndarray, poses: list[np.ndarray], margin_m: float) -> np.ndarray:
    """The peer points that land on the ego image, ``margin_m`` inside its edge, under every one of ``poses``: each
    pose of a grid is then scored on the same points (a pose that pushes points off the image would otherwise lose
    them, one that pulls points on would gain, whatever the images say)."""
    keep = np.ones(len(pts_peer), dtype=bool)
    for T in poses:
        p = pts_peer @ T[:2, :2].T + T[:2, 2]
        keep &= np.all(np.abs(p) <= ego.range_m - margin_m, axis=1)
    return pts_peer[keep]


@dataclass
class Fields:
    """The ego image's likelihood field at the coarse and the fine grid's cells (built once per ego frame)."""

    coarse: np.ndarray  # (H, 2 W) float32: narrow and wide as _score_grid reads them (_layout)
    fine: np.ndarray

    @classmethod
    def of(cls, ego: BevCloud, cfg: LandscapeConfig) -> Fields:
        """Built for every ego frame (10 Hz) from as few multi-MB temporaries as give the same fields to the bit
        (each costs page faults where the service maps every large block, server.allocator): the two fields share
        one distance image, each grid's layout is flipped in place."""
        d = ego.clearance.astype(np.float64)
        d *= ego.resolution_m
        t = np.empty_like(d)
        narrow, wide = (_exp_field_into(d, sigma, t) for sigma in (cfg.sigma_m, cfg.wide_sigma_m))

        def cells(step: float) -> np.ndarray:
            both = cv2.merge([_cells(narrow, ego.range_m, step), _cells(wide, ego.range_m, step)])
            cv2.flip(both, 1, dst=both)
            return both.reshape(both.shape[0], 2 * both.shape[1])  # _layout's, without its copies

        return cls(cells(2 * cfg.step_m), cells(cfg.step_m))


@dataclass
class _Grid:
    scores: np.ndarray  # (n_yaw, n, n)
    poses: np.ndarray  # (n_yaw * n * n, 3) yaw, tx, ty
    p: np.ndarray  # (n_yaw * n * n,) the normalised distribution
    step: np.ndarray  # (3,) rad, m, m
    half: np.ndarray  # (3,) rad, m, m
    centre: np.ndarray  # (3,)

    @property
    def best(self) -> float:
        return float(self.scores.max())

    @property
    def peak(self) -> np.ndarray:
        return self.poses[int(np.argmax(self.scores))]

    @property
    def mean(self) -> np.ndarray:
        return self.p @ self.poses

    @property
    def covariance(self) -> np.ndarray:
        d = self.poses - self.mean
        return (d * self.p[:, None]).T @ d

    def covers(self, poses: np.ndarray) -> np.ndarray:
        d = poses - self.centre
        d[:, 0] = np.arctan2(np.sin(d[:, 0]), np.cos(d[:, 0]))
        return np.all(np.abs(d) <= self.half + 0.5 * self.step, axis=1)

    def edge_mass(self) -> float:
        """The probability on the grid's outer faces (any axis)."""
        p = self.p.reshape(self.scores.shape)
        inner = p[1:-1, 1:-1, 1:-1].sum() if min(p.shape) > 2 else 0.0
        return float(p.sum() - inner)


def _grid(field, ego, pts_peer, T, half_m, step_m, half_deg, step_deg, effective_points) -> _Grid:
    n_t = max(1, int(round(half_m / step_m)))
    n_r = max(1, int(round(half_deg / step_deg)))
    yaws = np.radians(np.arange(-n_r, n_r + 1) * step_deg)
    scores = score_grid(field, ego, pts_peer, T, yaws, n_t, step_m)
    centre = np.array(se2_params(T))
    offsets = np.arange(-n_t, n_t + 1) * step_m
    g = np.meshgrid(centre[0] + yaws, centre[1] + offsets, centre[2] + offsets, indexing="ij")
    poses = np.stack([x.ravel() for x in g], axis=1)
    log_p = effective_points * scores.ravel()
    p = np.exp(log_p - log_p.max())
    step = np.array([np.radians(step_deg), step_m, step_m])
    half = np.array([yaws[-1], offsets[-1], offsets[-1]])
    return _Grid(scores, poses, p / p.sum(), step, half, centre)


def with_rivals(
    main: Landscape,
    ego: BevCloud,
    fields: Fields,
    pts_peer: np.ndarray,
    rivals: list[np.ndarray],
    cfg: LandscapeConfig,
    prior: GaussianPrior | None = None,
) -> tuple[np.ndarray, list[float]]:
    """The covariance of ``main``'s answer once the other poses the search found (``rivals``, 3x3 each) are counted
    as further modes of one distribution: each outside ``main``'s grid is moved to the peak of its own small grid and
    weighted ``exp(effective_points (S_rival - S_main))``; the mixture's spread about the answer is the covariance.
    A rival as good as the answer weighs as much as it: the covariance then spans both. ``prior``: each mode's weight
    is also multiplied by the prior's density there. Returns (covariance, the rivals' weights)."""
    # A rival is weighed where the search left it (its small window does not follow its peak).
    small = cfg.model_copy(
        update={"half_width_m": 4 * cfg.step_m, "half_yaw_deg": 3 * cfg.step_deg, "follow_peak": False}
    )
    y0, x0, t0 = se2_params(main.T)
    total_w, second = 1.0, main.covariance.copy()
    weights = []
    for T_r in rivals:
        d = _offset(main.T, T_r)
        if (
            abs(d[1]) <= cfg.half_width_m
            and abs(d[2]) <= cfg.half_width_m
            and abs(d[0]) <= np.radians(cfg.half_yaw_deg)
        ):
            continue  # inside main's grid: already counted
        # Both modes scored on the points that land on the ego image under each: the same evidence.
        shared = _inside(
            ego, pts_peer, [main.T, T_r], small.half_width_m + np.radians(small.half_yaw_deg) * ego.range_m
        )
        if len(shared) < 10:
            continue  # the two poses see the ego image through different points: nothing to weigh them by
        local = landscape(ego, fields, shared, T_r, small)
        here = landscape(ego, fields, shared, main.T, small)
        log_w = cfg.effective_points * (local.score - here.score)
        if prior is not None:
            log_w += float(
                prior.log_density(np.array(se2_params(local.T)))[0] - prior.log_density(np.array([y0, x0, t0]))[0]
            )
        w = float(np.exp(min(50.0, log_w)))
        d = _offset(main.T, local.T)
        second += w * (local.covariance if not local.at_edge else main.covariance) + w * np.outer(d, d)
        total_w += w
        weights.append(w)
    cov = second / total_w
    return 0.5 * (cov + cov.T), weights


def _offset(T_from: np.ndarray, T_to: np.ndarray) -> np.ndarray:
    """(yaw rad wrapped, tx m, ty m) of ``T_to`` minus ``T_from`` (3x3 each)."""
    y0, x0, t0 = se2_params(T_from)
    y, x, t = se2_params(T_to)
    return np.array([np.arctan2(np.sin(y - y0), np.cos(y - y0)), x - x0, t - t0])


def mahalanobis_d2(main: Landscape, T: np.ndarray) -> float:
    """Squared Mahalanobis distance of the pose ``T`` (3x3) from ``main``'s answer under its covariance."""
    d = _offset(main.T, T)
    return float(d @ np.linalg.solve(main.covariance, d))


def with_refinement(main: Landscape, T_refined: np.ndarray, max_d2: float) -> tuple[np.ndarray, np.ndarray]:
    """The answer and its covariance once the refinement's own pose (``T_refined``) is weighed
    against ``main``: within 1 sigma of the landscape's answer, the refinement's (continuous, finer than the grid's
    cells) pose stands; beyond ``max_d2`` (squared Mahalanobis distance) the two estimators disagree and both count
    as modes of equal weight (the landscape's score is biased where one car sees the near face of a thing and the
    other its far face); between the two, the landscape's answer."""
    d = _offset(main.T, T_refined)
    d2 = mahalanobis_d2(main, T_refined)
    if d2 <= 1.0:
        return np.array(T_refined, dtype=float), main.covariance
    if d2 <= max_d2:
        return main.T, main.covariance
    cov = main.covariance + 0.5 * np.outer(d, d)
    return main.T, 0.5 * (cov + cov.T)
