"""Numbers from per-pair records: the paper's metrics, overall and broken down.

Conventions: a pair counts as "under 1 m & 1 deg" only when the engine reported success AND both errors are
under the limits (a failure is a failure, whatever pose came with it). Medians count a failure as an infinite
error (so a median is ``None`` in JSON when half the pairs or more failed). The ``*_raw`` numbers use the
reported pose regardless of success, for diagnosis.

The anchors' metrics (V2X-Reg++ Table III, and the DAIR-V2X pose-recovery papers after it): ``success_at_m[l]``
is the fraction of pairs with a reported pose whose translation error is under l m AND rotation error under
l deg, for l = 1, 2, 3; ``mRTE_m[l]`` / ``mRRE_deg[l]`` are the mean translation / rotation errors over those
successes (None when there are none). Errors are this project's: ground-plane translation and yaw.
"""

from __future__ import annotations

import math

import numpy as np

from bb_align.engine.covariance import mahalanobis2

from .ap import ApAccumulator
from .runner import AP_IOUS, AP_RANGES, DIST_BUCKETS, POSES, PairRecord

CAR_BUCKETS = {"0-2": (0, 2), "3-5": (3, 5), "6-10": (6, 10), ">10": (11, 10**9)}
BV_INLIER_BUCKETS = {"<=25": (0, 25), "26-50": (26, 50), "51-100": (51, 100), ">100": (101, 10**9)}
BOX_INLIER_BUCKETS = {"<=6": (0, 6), "7-12": (7, 12), "13-20": (13, 20), ">20": (21, 10**9)}
ANCHOR_LAMBDAS = (1, 2, 3)  # metres and degrees: success when t < lambda m AND r < lambda deg


def _median(x: np.ndarray) -> float | None:
    if not len(x):
        return None
    m = float(np.median(x))
    return m if math.isfinite(m) else None


def _mean(x: np.ndarray) -> float | None:
    return float(np.mean(x)) if len(x) else None


def anchor_metrics(t: np.ndarray, r: np.ndarray, ok: np.ndarray) -> dict:
    """success_at_m, mRTE_m and mRRE_deg for each lambda of :data:`ANCHOR_LAMBDAS` (keys "1", "2", "3").

    A refused alignment (``ok`` False) is never a success, whatever pose came with it."""
    t, r, ok = np.asarray(t, float), np.asarray(r, float), np.asarray(ok, bool)
    out: dict = {"success_at_m": {}, "mRTE_m": {}, "mRRE_deg": {}}
    for lam in ANCHOR_LAMBDAS:
        hit = ok & (t < lam) & (r < lam)
        key = str(lam)
        out["success_at_m"][key] = float(hit.mean()) if len(t) else None
        out["mRTE_m"][key] = _mean(t[hit])
        out["mRRE_deg"][key] = _mean(r[hit])
    return out


def accuracy(t: np.ndarray, r: np.ndarray, ok: np.ndarray) -> dict:
    """The headline numbers for one set of pairs."""
    t, r, ok = np.asarray(t, float), np.asarray(r, float), np.asarray(ok, bool)
    n = len(t)
    if n == 0:
        return {"pairs": 0}
    under = ok & (t < 1.0) & (r < 1.0)
    raw_under = (t < 1.0) & (r < 1.0)
    return {
        "pairs": int(n),
        "success_rate": float(ok.mean()),
        "frac_under_1m_1deg": float(under.mean()),
        "median_t_err_m": _median(np.where(ok, t, np.inf)),
        "median_r_err_deg": _median(np.where(ok, r, np.inf)),
        "frac_under_1m_1deg_raw": float(raw_under.mean()),
        "median_t_err_m_raw": _median(t),
        "median_r_err_deg_raw": _median(r),
        "frac_success_but_over_1m_or_1deg": float((ok & ~under).mean()),
        **anchor_metrics(t, r, ok),
    }


def _arrays(records: list[PairRecord], which: str):
    if which == "bbalign":
        return ([x.t_err_m for x in records], [x.r_err_deg for x in records], [x.success for x in records])
    if which == "stage1":
        return (
            [x.stage1_t_err_m for x in records],
            [x.stage1_r_err_deg for x in records],
            [x.stage1_success for x in records],
        )
    if which == "baseline":
        return (
            [x.baseline_t_err_m for x in records],
            [x.baseline_r_err_deg for x in records],
            [x.baseline_success for x in records],
        )
    raise ValueError(which)


def _by(records, key, buckets, which="bbalign") -> dict:
    """Accuracy per bucket. Float buckets (distances) are [lo, hi); integer buckets (counts) are [lo, hi]."""
    out = {}
    for name, (lo, hi) in buckets.items():
        inclusive = isinstance(lo, int) and isinstance(hi, int)
        sel = [x for x in records if (lo <= key(x) <= hi if inclusive else lo <= key(x) < hi)]
        out[name] = accuracy(*_arrays(sel, which))
    return out


def _block(records, which) -> dict:
    d = accuracy(*_arrays(records, which))
    d["by_distance"] = _by(records, lambda x: x.distance_m, DIST_BUCKETS, which)
    d["within_70m"] = accuracy(*_arrays([x for x in records if x.distance_m < 70], which))
    d["by_common_cars"] = _by(records, lambda x: x.common_cars, CAR_BUCKETS, which)
    return d


def detection_ap(records: list[PairRecord]) -> dict:
    """AP@IoU per pose source and range, pooled over all pairs."""
    out: dict = {}
    for pose in POSES:
        out[pose] = {}
        for rng in AP_RANGES:
            accs = {iou: ApAccumulator() for iou in AP_IOUS}
            for x in records:
                e = x.ap.get(pose, {}).get(rng)
                if e is None:
                    continue
                for iou in AP_IOUS:
                    accs[iou].add(e["scores"], e[f"tp@{iou}"], e["n_gt"])
            out[pose][rng] = {f"ap@{iou}": _nan_none(accs[iou].ap()) for iou in AP_IOUS}
            out[pose][rng]["n_gt"] = accs[AP_IOUS[0]].n_gt
    return out


def _nan_none(v: float) -> float | None:
    return None if not math.isfinite(v) else float(v)


def _diagnosis(records: list[PairRecord]) -> dict:
    """Medians per distance bucket: repeatable keypoints (overlap), correct matches (descriptors), inliers."""
    out = {}
    for name, (lo, hi) in DIST_BUCKETS.items():
        rs = [x for x in records if lo <= x.distance_m < hi]
        if rs:
            out[name] = {
                k: float(np.median([getattr(x, k) for x in rs]))
                for k in ("oracle_repeatable_kp", "oracle_correct_matches", "inliers_bv", "matches_bv")
            }
    return out


CHI2_3_99 = 11.345  # the chi-square (3 degrees of freedom) 99 % quantile


def mahalanobis2_of(x: PairRecord) -> float | None:
    """The squared Mahalanobis distance of a pair's true error under its own covariance (None without one)."""
    if x.covariance is None or x.error_params is None:
        return None
    return mahalanobis2(np.asarray(x.covariance, float), x.error_params)


def covariance_coverage(records: list[PairRecord]) -> dict:
    """Over the successful pairs: how often the covariance covers the true error (chi2(3) 99 % bound on the
    squared Mahalanobis distance; each parameter within 3 sigma), overall and by distance."""

    def block(rs: list[PairRecord]) -> dict:
        rs = [x for x in rs if x.success and mahalanobis2_of(x) is not None]
        if not rs:
            return {"pairs": 0}
        d2 = np.array([mahalanobis2_of(x) for x in rs])
        z = np.array([np.abs(x.error_params) / np.sqrt(np.diag(x.covariance)) for x in rs])
        sigma_t = np.array([np.sqrt(np.linalg.eigvalsh(np.asarray(x.covariance)[1:, 1:]).max()) for x in rs])
        return {
            "pairs": len(rs),
            "frac_d2_within_chi2_99": float(np.mean(d2 <= CHI2_3_99)),
            "frac_within_3sigma_each": float(np.mean((z <= 3).all(axis=1))),
            "median_d2": float(np.median(d2)),  # chi2(3) median: 2.37
            "median_worst_sigma_m": float(np.median(sigma_t)),
        }

    out = block(records)
    out["by_distance"] = {
        k: block([x for x in records if lo <= x.distance_m < hi]) for k, (lo, hi) in DIST_BUCKETS.items()
    }
    return out


def summarize(records: list[PairRecord]) -> dict:
    """The JSON summary: top-level keys as the issue asks, then the breakdowns."""
    if not records:
        raise ValueError("no pairs to summarize")
    top = accuracy(*_arrays(records, "bbalign"))
    reasons: dict[str, int] = {}
    for x in records:
        reasons[x.reason or "success"] = reasons.get(x.reason or "success", 0) + 1
    sources: dict[str, int] = {}  # agent frames per detection source (ego and peer of every pair)
    for x in records:
        for src in (x.ego_detections, x.peer_detections):
            sources[src or "unknown"] = sources.get(src or "unknown", 0) + 1
    sensors: dict[str, list[PairRecord]] = {}
    for x in records:
        sensors.setdefault(f"{x.ego_sensor}<-{x.peer_sensor}", []).append(x)
    return {
        **top,
        "by_distance": _by(records, lambda x: x.distance_m, DIST_BUCKETS),
        "within_70m": accuracy(*_arrays([x for x in records if x.distance_m < 70], "bbalign")),
        "paper_subset_ge2_common_cars": _block([x for x in records if x.common_cars >= 2], "bbalign"),
        "by_common_cars": _by(records, lambda x: x.common_cars, CAR_BUCKETS),
        "by_inliers_bv": _by(records, lambda x: x.inliers_bv, BV_INLIER_BUCKETS),
        "by_inliers_box": _by(records, lambda x: x.inliers_box, BOX_INLIER_BUCKETS),
        "by_sensor_pair": {k: accuracy(*_arrays(v, "bbalign")) for k, v in sorted(sensors.items())},
        "stage1_only": _block(records, "stage1"),
        "baseline_graph_matching": _block(records, "baseline"),
        "detections_used": dict(sorted(sources.items())),
        "pairs_deskewed": sum(x.deskewed for x in records),
        "failure_reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])),
        "stage1_diagnosis_by_distance": _diagnosis(records),
        "covariance_coverage": covariance_coverage(records),
        "detection_ap": detection_ap(records),
        "timing_ms": {
            "prepare_per_frame_median": float(np.median([x.prepare_ms / 2 for x in records])),
            "align_median": float(np.median([x.align_ms for x in records])),
        },
    }
