"""What a stream of frames knows together: recent frames' own measurements of the odometry offset, fused.

With odometry on both cars, every frame's own measurement of ``T_ego_peer`` (its pose landscape, with the boxes
when they agree) is a measurement of the same nearly constant offset ``X = O_e T_ego_peer O_p^-1`` between the two
odometry frames. A frame measured ``dt`` seconds ago still measures today's offset, less sharply by the odometry's
drift over ``dt``. So the last frames of a window are fused by information on left increments of X, and the fused
covariance is widened for what they share: successive frames see the same buildings through the same aliasing,
so their errors are correlated. With ``rho`` the mean product of two frames' errors in units of their own
covariances (the whitened errors' cross moment: their correlation when the covariances are exact, less when the
covariances are wider than the errors), n frames are worth at least ``n / (1 + rho (n - 1))`` independent ones
(the design effect of an equicorrelated sample); the information-weighted covariance is multiplied by
``1 + rho (n - 1)``. ``rho`` is measured on real and simulated runs (``benchmarks/evidence_correlation.py``), not
assumed zero.

A frame that disagrees with the fusion of the newer frames ends the window there: what is older than a
disagreement is not evidence about the present (a relocalisation, a lying peer's odometry). The errors the frames
share cancel in their difference, so two frames must agree within a share ``agreement`` of their covariances
(plus the odometry's drift between them; ``1 - rho`` when the covariances are exact), judged at ``gate_chi2``:
with a share of 0.1 a peer whose odometry drifts 0.3 m a frame keeps two or three frames in its window, not ten.
A window cut short only costs evidence, so the share is chosen tight. The window is the stream's evidence; the
track's filter only predicts.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from .geometry import se2

_FLOOR = np.diag([1e-12, 1e-9, 1e-9])  # keeps the spread invertible when every error is shared (rho 1, no drift)


def moved_m(places: list[np.ndarray | None]) -> np.ndarray:
    """(n, n): how far the cars moved between frames i and j taken at ``places`` ((2, 2) each: each car's position
    in its own odometry frame), the larger of the two cars' moves; 0 (one place) when any place is unknown."""
    if any(p is None for p in places):
        return np.zeros((len(places),) * 2)
    xy = np.asarray(places, dtype=float)  # (n, 2 cars, 2)
    return np.linalg.norm(xy[:, None] - xy[None, :], axis=-1).max(axis=-1)


@dataclass(frozen=True)
class SharedError:
    """What two frames' errors share (their whitened errors' cross moment, ``rho``) by how far the cars moved
    between them: ``near`` while both stay within ``same_place_m`` (metres, the larger of the two cars' moves),
    decaying over ``decay_m`` towards ``far`` as the structure both images see is replaced."""

    near: float
    far: float | None = None  # None: ``near`` wherever the cars go
    same_place_m: float = 0.0
    decay_m: float = 1.0

    def rho(self, moved_m: np.ndarray) -> np.ndarray:
        if self.far is None:
            return np.full_like(moved_m, self.near, dtype=float)
        beyond = np.maximum(0.0, moved_m - self.same_place_m) / self.decay_m
        return self.far + (self.near - self.far) * np.exp(-beyond)

    def matrix(self, places: list[np.ndarray | None]) -> np.ndarray:
        """(n, n) correlations of frames taken at ``places`` ((2, 2): each car's position in its own odometry
        frame; None: unknown, taken as the same place), 1 on the diagonal, projected onto the PSD cone (a
        correlation by moved distance need not be one)."""
        R = self.rho(moved_m(places))
        np.fill_diagonal(R, 1.0)
        try:
            np.linalg.cholesky(R)
            return R
        except np.linalg.LinAlgError:
            vals, vecs = np.linalg.eigh(R)
            return (vecs * np.maximum(vals, 0.0)) @ vecs.T


@dataclass(frozen=True)
class OffsetSample:
    """One frame's own measurement of the odometry offset X (3x3) with the covariance of X's left increments, the
    rate (per second) at which its covariance grows with age (the two odometries' drift at that frame), and where
    the two cars were (``places``: (2, 2), the ego's and the peer's position in its own odometry frame, metres)."""

    stamp: float
    X: np.ndarray
    covariance: np.ndarray
    drift_per_s: np.ndarray
    places: np.ndarray | None = None


@dataclass(frozen=True)
class FusedOffset:
    X: np.ndarray  # 3x3: the fused offset
    covariance: np.ndarray  # 3x3, left increments of X, widened for the frames' correlation
    frames: int  # how many frames the fusion holds


def _log_left_all(Xs: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(n, 3) left increments (yaw wrapped, tx, ty) of each (3x3) of ``Xs`` about ``ref``: ``log_left`` at once."""
    rel = Xs @ np.linalg.inv(ref)
    return np.stack([np.arctan2(rel[:, 1, 0], rel[:, 0, 0]), rel[:, 0, 2], rel[:, 1, 2]], axis=1)


class StreamEvidence:
    """The last frames' measurements of the offset, at most ``max_frames`` and ``window_s`` old (see the module)."""

    def __init__(
        self,
        window_s: float,
        max_frames: int,
        correlation: float | SharedError,
        gate_chi2: float,
        agreement: float | None = None,
    ):
        self.shared = correlation if isinstance(correlation, SharedError) else SharedError(float(correlation))
        self.window_s, self.gate_chi2 = window_s, gate_chi2
        self.agreement = 1.0 - self.shared.near if agreement is None else agreement
        self.samples: deque[OffsetSample] = deque(maxlen=max_frames)

    def clear(self) -> None:
        self.samples.clear()

    def add(self, sample: OffsetSample) -> None:
        self.samples.append(sample)

    def fused(self, stamp: float, trim: bool = True) -> FusedOffset | None:
        """The fusion at ``stamp`` of the newest frames that agree with each other (newest first: a frame that
        disagrees with the fusion of the newer ones ends the window and is forgotten with everything older).
        ``trim=False``: the same fusion, nothing forgotten (a look that must leave the stream as it was)."""
        if not trim:
            kept = self.samples.copy()
            try:
                return self.fused(stamp)
            finally:
                self.samples = kept
        while self.samples and stamp - self.samples[0].stamp > self.window_s:
            self.samples.popleft()
        if not self.samples:
            return None
        newest = list(reversed(self.samples))
        ref = newest[0].X  # left increments about the newest frame's offset
        d = _log_left_all(np.array([f.X for f in newest]), ref)
        age = np.maximum(0.0, stamp - np.array([f.stamp for f in newest]))
        own = np.array([f.covariance for f in newest])
        drift = np.array([f.drift_per_s for f in newest]) * age[:, None, None]
        covs = own + drift
        W = np.linalg.inv(covs)
        info = np.cumsum(W, axis=0)  # info[k]: frames 0..k (newest first)
        vec = np.cumsum((W @ d[..., None])[..., 0], axis=0)
        kept = len(newest)
        if kept > 1:
            # Each frame against the fusion of the newer ones: errors shared by all frames cancel in the difference,
            # so frames must agree within a share of their covariances (and the drift between them).
            fused_cov = np.linalg.inv(info[:-1])
            r = d[1:] - (fused_cov @ vec[:-1, :, None])[..., 0]
            spread = self.agreement * (own[1:] + fused_cov) + drift[1:] + _FLOOR
            d2 = np.einsum("ni,ni->n", r, np.linalg.solve(spread, r[..., None])[..., 0])
            apart = np.flatnonzero(d2 > self.gate_chi2)
            if len(apart):
                kept = int(apart[0]) + 1
                for _ in range(len(newest) - kept):
                    self.samples.popleft()
        P = np.linalg.inv(info[kept - 1])
        cov = self._shared_covariance(P, covs[:kept], [f.places for f in newest[:kept]])
        return FusedOffset(se2(*(P @ vec[kept - 1])) @ ref, cov, kept)

    def _shared_covariance(self, P: np.ndarray, covs: np.ndarray, places: list) -> np.ndarray:
        """The information-weighted fusion's covariance when frame i's and j's errors share rho_ij (module doc),
        never finer than the independent fusion ``P``."""
        S = np.linalg.cholesky(covs)
        A = P @ (np.linalg.inv(covs) @ S)  # (n, 3, 3): P W_i S_i
        RA = np.tensordot(self.shared.matrix(places), A, axes=(1, 0))  # sum_j rho_ij A_j
        M = A.transpose(1, 0, 2).reshape(3, -1) @ RA.transpose(1, 0, 2).reshape(3, -1).T  # sum_i A_i RA_i^T
        # In P's whitened coordinates, no direction may be finer than P itself (rho >= 0 adds, never removes).
        L = np.linalg.cholesky(P)
        Li = np.linalg.inv(L)
        vals, vecs = np.linalg.eigh(Li @ (0.5 * (M + M.T)) @ Li.T)
        cov = L @ ((vecs * np.maximum(vals, 1.0)) @ vecs.T) @ L.T
        return 0.5 * (cov + cov.T)
