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

from .geometry import log_left, se2

_FLOOR = np.diag([1e-12, 1e-9, 1e-9])  # keeps the spread invertible when every error is shared (rho 1, no drift)


@dataclass(frozen=True)
class OffsetSample:
    """One frame's own measurement of the odometry offset X (3x3) with the covariance of X's left increments, and
    the rate (per second) at which its covariance grows with age (the two odometries' drift at that frame)."""

    stamp: float
    X: np.ndarray
    covariance: np.ndarray
    drift_per_s: np.ndarray


@dataclass(frozen=True)
class FusedOffset:
    X: np.ndarray  # 3x3: the fused offset
    covariance: np.ndarray  # 3x3, left increments of X, widened for the frames' correlation
    frames: int  # how many frames the fusion holds


class StreamEvidence:
    """The last frames' measurements of the offset, at most ``max_frames`` and ``window_s`` old (see the module)."""

    def __init__(
        self, window_s: float, max_frames: int, correlation: float, gate_chi2: float, agreement: float | None = None
    ):
        self.window_s, self.correlation, self.gate_chi2 = window_s, correlation, gate_chi2
        self.agreement = 1.0 - correlation if agreement is None else agreement
        self.samples: deque[OffsetSample] = deque(maxlen=max_frames)

    def clear(self) -> None:
        self.samples.clear()

    def add(self, sample: OffsetSample) -> None:
        self.samples.append(sample)

    def fused(self, stamp: float) -> FusedOffset | None:
        """The fusion at ``stamp`` of the newest frames that agree with each other (newest first: a frame that
        disagrees with the fusion of the newer ones ends the window and is forgotten with everything older)."""
        while self.samples and stamp - self.samples[0].stamp > self.window_s:
            self.samples.popleft()
        if not self.samples:
            return None
        ref = self.samples[-1].X  # left increments about the newest frame's offset
        info, vec, kept = np.zeros((3, 3)), np.zeros(3), 0
        for i, s in enumerate(reversed(self.samples)):
            d = log_left(s.X, ref)
            drift = s.drift_per_s * max(0.0, stamp - s.stamp)
            cov = s.covariance + drift
            w = np.linalg.inv(cov)
            if kept:
                # Against the newer frames' fusion: errors shared by all frames cancel in the difference, so frames
                # must agree within a share of their covariances (and the drift between them).
                mean, fused_cov = np.linalg.solve(info, vec), np.linalg.inv(info)
                spread = self.agreement * (s.covariance + fused_cov) + drift + _FLOOR
                if float((d - mean) @ np.linalg.solve(spread, d - mean)) > self.gate_chi2:
                    for _ in range(len(self.samples) - i):
                        self.samples.popleft()
                    break
            info, vec, kept = info + w, vec + w @ d, kept + 1
        cov = np.linalg.inv(info) * (1.0 + self.correlation * (kept - 1))
        return FusedOffset(se2(*np.linalg.solve(info, vec)) @ ref, 0.5 * (cov + cov.T), kept)
