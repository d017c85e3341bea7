"""Covariance of the refined ground-plane pose (yaw [rad], tx [m], ty [m]) from the dense refinement.

At the final pose the point-to-line residuals r_i = n_i . (T p_i - q_i) of the peer pixels that found an ego pixel
within the finest gate give the Gauss-Newton information H = sum w_i J_i J_i^T (J = d r / d(yaw, tx, ty), the
pose increment applied on the left as in bb_align.refine; Huber weights w_i). Only the point-to-line rows count:
the refinement's weak point-to-point terms pin the motion along a line numerically but are not measurements.
sigma^2 = sum w_i r_i^2 / (sum w_i - 3) and Cov = inflation * sigma^2 * H^-1.

A plain inverse over thousands of pixels would be far too optimistic: neighbouring pixels of one wall are one
measurement seen many times, and the two cars' sensors differ (model error). ``CovarianceConfig.inflation`` scales
the variance for that; it is calibrated on seeded simulated pairs so that the Mahalanobis distance of the true error
lies within the chi2(3) 99 % bound for about 97-99 % of the correct pairs (benchmarks/acquisition_range.py).
A direction no line constrains (a long straight corridor) has almost no information: its variance is huge, and the
answer rule (``probability_within`` against answer.confidence) refuses such a pose.
"""

from __future__ import annotations

from math import erf, radians, sqrt

import numpy as np
from numba import njit

from .config import CovarianceConfig
from .geometry import log_left, se2
from .refine import BevCloud, facing, facing_args

_HUGE = 1e6  # variance reported along a direction with no information at all (m^2 or rad^2)


@njit(cache=True, nogil=True)
def _line_information(p, xy, normals, nearest, gate, pn, c, s, min_cos):
    H = np.zeros((3, 3))
    wrr = 0.0
    wsum = 0.0
    huber = 0.25 * gate
    for i in range(len(p)):
        j = nearest[i]
        if j < 0 or not facing(normals, j, pn, i, c, s, min_cos):  # the refinement's correspondences only
            continue
        px, py = p[i, 0], p[i, 1]
        nx, ny = normals[j, 0], normals[j, 1]
        r = nx * (px - xy[j, 0]) + ny * (py - xy[j, 1])
        w = 1.0 / max(1.0, abs(r) / huber)
        jac = (nx * -py + ny * px, nx, ny)
        wrr += w * r * r
        wsum += w
        for a in range(3):
            for b in range(3):
                H[a, b] += w * jac[a] * jac[b]
    return H, wrr, wsum


def pose_covariance(
    ego: BevCloud,
    pts_peer: np.ndarray,
    T: np.ndarray,
    gate: float,
    inflation: float = 1.0,
    min_sigma_m: float = 0.1,
    normals_peer: np.ndarray | None = None,
    min_cos: float = -1.0,
) -> np.ndarray:
    """3x3 covariance of (yaw, tx, ty) at pose T (3x3 ego <- peer). ``min_sigma_m`` floors the residual sigma
    (the pixel quantisation: residuals are not smaller than the cell allows). ``normals_peer``, ``min_cos``: the
    refinement's facing test (bb_align.engine.refine); None: every pair counts."""
    p = np.ascontiguousarray(pts_peer @ T[:2, :2].T + T[:2, 2], dtype=np.float64)
    _, j = ego.nearest(p, gate)
    pn, min_cos = facing_args(p, normals_peer, min_cos)
    H, wrr, wsum = _line_information(p, ego.xy, ego.normals, j, float(gate), pn, T[0, 0], T[1, 0], min_cos)
    if wsum <= 3:
        return np.diag([_HUGE, _HUGE, _HUGE])
    sigma2 = max(wrr / (wsum - 3.0), min_sigma_m**2, 1e-12)
    # Pseudo-inverse with a floor on the eigenvalues: a direction with (numerically) no information gets _HUGE.
    evals, evecs = np.linalg.eigh(H)
    inv = np.where(evals > sigma2 / _HUGE, 1.0 / np.maximum(evals, 1e-300), _HUGE / sigma2)
    cov = inflation * sigma2 * (evecs * inv) @ evecs.T
    return 0.5 * (cov + cov.T)


def motion_response(
    ego: BevCloud,
    pts_peer: np.ndarray,
    T: np.ndarray,
    gate: float,
    normals_peer: np.ndarray | None = None,
    min_cos: float = -1.0,
) -> np.ndarray:
    """(2, 3): how the pose (left increment: yaw rad, tx m, ty m) at T moves per metre that the peer (row 0) or the
    ego (row 1) travelled, forward, during a sweep its sender did not de-skew. A rotating LiDAR that spins from the
    back through the front fires azimuth a at -a / (2 pi) of a sweep from mid-sweep (the seam behind the car), so
    a point is reported a / (2 pi) metres per metre of travel further forward than it was at mid-sweep (the
    other spin gives the opposite sign, the same covariance): each image is sheared about its own seam. The
    response is the Gauss-Newton step that this shear of the peer's points, or of the ego's structure, causes in
    the point-to-line problem at T (the refinement's correspondences and facing test)."""
    R, t = T[:2, :2], T[:2, 2]
    p = np.ascontiguousarray(pts_peer @ R.T + t, dtype=np.float64)
    _, j = ego.nearest(p, gate)
    keep = j >= 0
    n = ego.normals[j[keep]]
    if normals_peer is not None:  # the two pixels are one face of one thing (bb_align.engine.refine)
        keep[keep] = np.sum(n * (np.asarray(normals_peer)[keep] @ R.T), axis=1) >= min_cos
        n = ego.normals[j[keep]]
    p_ego, p_peer = p[keep], np.asarray(pts_peer, dtype=np.float64)[keep]
    if len(p_ego) <= 3:
        return np.zeros((2, 3))
    r = np.sum(n * (p_ego - ego.xy[j[keep]]), axis=1)
    w = 1.0 / np.maximum(1.0, np.abs(r) / (0.25 * gate))  # the covariance's Huber weights
    J = np.stack([n[:, 1] * p_ego[:, 0] - n[:, 0] * p_ego[:, 1], n[:, 0], n[:, 1]], axis=1)
    H = (J * w[:, None]).T @ J
    shear_peer = np.arctan2(p_peer[:, 1], p_peer[:, 0]) / (2.0 * np.pi)  # along the peer's x, in metres per metre
    shear_ego = np.arctan2(p_ego[:, 1], p_ego[:, 0]) / (2.0 * np.pi)  # along the ego's x
    dr = np.stack([shear_peer * (n @ R[:, 0]), -shear_ego * n[:, 0]])  # residual change per metre of travel
    try:
        return -np.linalg.solve(H, (J.T @ (w * dr).T)).T
    except np.linalg.LinAlgError:  # no information at all: the pose's own covariance is then unbounded anyway
        return np.zeros((2, 3))


def motion_covariance(
    ego: BevCloud,
    peer_sample: tuple[np.ndarray, np.ndarray | None],
    T: np.ndarray,
    gate: float,
    travel_m: float,
    min_cos: float = -1.0,
) -> np.ndarray:
    """3x3 covariance of T's own parameters (yaw, tx, ty) that each car's unknown travel during a sweep it did not
    de-skew (``travel_m``, 1-sigma, independent per car) adds to the pose at T (3x3 ego <- peer): a model error the
    images cannot reveal, since a sheared image still fits (docs/engine.md, "Self-motion distortion")."""
    if travel_m <= 0:
        return np.zeros((3, 3))
    pts, normals = peer_sample
    A = motion_response(ego, pts, T, gate, normals, min_cos)
    return params_covariance(travel_m**2 * A.T @ A, T)


def mahalanobis2(cov: np.ndarray, err: np.ndarray) -> float:
    """Squared Mahalanobis distance of an error (yaw rad, tx m, ty m) under cov."""
    err = np.asarray(err, dtype=float)
    return float(err @ np.linalg.solve(cov, err))


def _params_jacobian(T: np.ndarray) -> np.ndarray:
    tx, ty = float(T[0, 2]), float(T[1, 2])
    return np.array([[1.0, 0.0, 0.0], [-ty, 1.0, 0.0], [tx, 0.0, 1.0]])


def left_covariance(cov_params: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The inverse of :func:`params_covariance`: a covariance of T's parameters as one of left increments."""
    J_inv = np.linalg.inv(_params_jacobian(T))
    cov = J_inv @ np.asarray(cov_params, dtype=float) @ J_inv.T
    return 0.5 * (cov + cov.T)


# Gauss-Legendre nodes for the disc probability below: 48 nodes integrate its smooth integrand to ~1e-10.
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(48)


def probability_in_disc(cov_t: np.ndarray, radius_m: float) -> float:
    """P(|t| <= radius_m) for a zero-mean 2-D normal t of covariance ``cov_t`` (2x2): along the wider principal axis
    (z in its sigmas, z = h sin(theta), h the disc's half-width) the normal density times the narrower axis's
    probability of the chord, radius cos(theta); in theta the integrand is smooth, so Gauss-Legendre converges."""
    lam = np.clip(np.linalg.eigvalsh(np.asarray(cov_t, dtype=float)), 1e-300, None)
    narrow, wide = float(lam[0]), float(lam[1])
    half = radius_m / sqrt(wide)
    theta = 0.25 * np.pi * (_GL_NODES + 1.0)  # [0, pi / 2]
    cos = np.cos(theta)
    inner = np.array([erf(c) for c in radius_m * cos / sqrt(2.0 * narrow)])
    density = np.exp(-0.5 * (half * np.sin(theta)) ** 2) / sqrt(2.0 * np.pi)
    return float(min(1.0, 0.5 * np.pi * half * np.sum(_GL_WEIGHTS * density * cos * inner)))


def probability_within(cov: np.ndarray, max_m: float, max_deg: float) -> float:
    """A lower bound on the probability that a pose with this (yaw, tx, ty) covariance is within ``max_m`` (its
    position) and ``max_deg`` (its yaw) of the truth: the yaw's and the position's own probabilities multiplied.
    Both regions are convex and symmetric about the answer, so by the Gaussian correlation inequality (Royen 2014)
    their product never exceeds the joint probability, whatever the correlation between yaw and position."""
    cov = np.asarray(cov, dtype=float)
    var_yaw = max(float(cov[0, 0]), 1e-300)
    return erf(radians(max_deg) / sqrt(2.0 * var_yaw)) * probability_in_disc(cov[1:, 1:], max_m)


def params_covariance(cov_left: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The covariance of a left increment (yaw, tx, ty) applied to T, carried to T's own parameters
    (yaw, tx, ty): a yaw increment also moves the translation by yaw x (-ty, tx)."""
    J = _params_jacobian(T)
    cov = J @ np.asarray(cov_left, dtype=float) @ J.T
    return 0.5 * (cov + cov.T)


def pose_uncertainty(
    ego_cloud: BevCloud,
    peer_sample: tuple[np.ndarray, np.ndarray | None],
    T: np.ndarray,
    gate: float,
    cfg: CovarianceConfig,
    min_cos: float = -1.0,
) -> np.ndarray:
    """3x3 covariance of (yaw, tx, ty) of the pose T (3x3 ego <- peer), from the refinement's normal equations
    (``peer_sample``: the peer points and their normals; ``min_cos``: the refinement's facing test)."""
    pts, normals = peer_sample
    cov_left = pose_covariance(ego_cloud, pts, T, gate, cfg.inflation, cfg.min_residual_sigma_m, normals, min_cos)
    return params_covariance(cov_left, T)


def fuse_poses(
    T_a: np.ndarray, C_a: np.ndarray, T_b: np.ndarray, C_b: np.ndarray, agreement_chi2: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """Two independent measurements of one pose (3x3, covariances of left increments) as one, information-weighted
    about T_a: (T, C); None when they lie farther apart than ``agreement_chi2`` (squared Mahalanobis distance under
    C_a + C_b), i.e. one of them is wrong."""
    nu = log_left(T_b, T_a)
    C_a, C_b = np.asarray(C_a, float), np.asarray(C_b, float)
    if float(nu @ np.linalg.solve(C_a + C_b, nu)) > agreement_chi2:
        return None
    C = np.linalg.inv(np.linalg.inv(C_a) + np.linalg.inv(C_b))
    C = 0.5 * (C + C.T)
    return se2(*(C @ np.linalg.solve(C_b, nu))) @ T_a, C
