"""Figures like the paper's Fig. 7-14 and Table I, from per-pair records (matplotlib, PNG).

Error CDFs count a failed pair as an infinite error (its curve never reaches it), except where a caption
says "raw".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bb_align.io.plot import pyplot

from .runner import PairRecord
from .summary import (
    BOX_INLIER_BUCKETS,
    BV_INLIER_BUCKETS,
    CAR_BUCKETS,
    CHI2_3_99,
    DIST_BUCKETS,
    detection_ap,
    mahalanobis2_of,
)


def _cdf(ax, values, ok, label, xmax, **kw):
    v = np.where(np.asarray(ok, bool), np.asarray(values, float), np.inf)
    n = len(v)
    if n == 0:
        return
    xs = np.sort(v[np.isfinite(v)])
    ys = np.arange(1, len(xs) + 1) / n
    ax.step(
        np.concatenate([[0], xs, [xmax]]),
        np.concatenate([[0], ys, [ys[-1] if len(ys) else 0]]),
        where="post",
        label=f"{label} (n={n})",
        **kw,
    )


def _pair_cdfs(fig_path, groups: dict[str, tuple], title: str, t_max=5.0, r_max=5.0):
    """Two panels (translation, rotation) with one CDF per group: name -> (t, r, ok)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name, (t, r, ok) in groups.items():
        _cdf(axes[0], t, ok, name, t_max)
        _cdf(axes[1], r, ok, name, r_max)
    for ax, lab, xmax in ((axes[0], "translation error (m)", t_max), (axes[1], "rotation error (deg)", r_max)):
        ax.set_xlim(0, xmax)
        ax.set_ylim(0, 1)
        ax.axvline(1.0, color="grey", lw=0.8, ls=":")
        ax.set_xlabel(lab)
        ax.set_ylabel("fraction of pairs")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(fig_path, dpi=110)
    plt.close(fig)


def _sel(records, key, lo, hi, inclusive):
    return [x for x in records if (lo <= key(x) <= hi if inclusive else lo <= key(x) < hi)]


def _full(rs):
    return [x.t_err_m for x in rs], [x.r_err_deg for x in rs], [x.success for x in rs]


def _raw(rs):
    return [x.t_err_m for x in rs], [x.r_err_deg for x in rs], [True] * len(rs)


def _stage1(rs):
    return [x.stage1_t_err_m for x in rs], [x.stage1_r_err_deg for x in rs], [x.stage1_success for x in rs]


def _baseline(rs):
    return [x.baseline_t_err_m for x in rs], [x.baseline_r_err_deg for x in rs], [x.baseline_success for x in rs]


def write_plots(records: list[PairRecord], out_dir: str | Path) -> list[Path]:
    """Write every figure into ``out_dir``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []

    def p(name):
        paths.append(out / name)
        return out / name

    _pair_cdfs(
        p("fig07_bbalign_vs_graph_matching.png"),
        {"BB-Align": _full(records), "graph matching (VIPS-style)": _baseline(records)},
        "Fig. 7: pose recovery accuracy, BB-Align vs graph matching (all pairs)",
    )
    _box_by_cars(p("fig08_error_by_common_cars.png"), records)
    _pair_cdfs(
        p("fig09a_by_inliers_bv.png"),
        {
            f"Inliers_bv {k}": _raw(_sel(records, lambda x: x.inliers_bv, lo, hi, True))
            for k, (lo, hi) in BV_INLIER_BUCKETS.items()
        },
        "Fig. 9a: accuracy by BV-matching inliers (raw pose, failures included)",
    )
    _pair_cdfs(
        p("fig09b_by_inliers_box.png"),
        {
            f"Inliers_box {k}": _raw(_sel(records, lambda x: x.inliers_box, lo, hi, True))
            for k, (lo, hi) in BOX_INLIER_BUCKETS.items()
        },
        "Fig. 9b: accuracy by box-alignment inliers (raw pose, failures included)",
    )
    dist_groups = {k: _sel(records, lambda x: x.distance_m, lo, hi, False) for k, (lo, hi) in DIST_BUCKETS.items()}
    dist_groups["0-70 (all)"] = _sel(records, lambda x: x.distance_m, 0, 70, False)
    _pair_cdfs(
        p("fig10_by_distance.png"),
        {f"{k} m": _full(v) for k, v in dist_groups.items()},
        "Fig. 10: accuracy by distance between the cars",
    )
    _pair_cdfs(
        p("fig11_stage1_by_distance.png"),
        {f"{k} m": _stage1(v) for k, v in dist_groups.items()},
        "Fig. 11: BV image matching alone (stage 1) by distance",
    )
    _pair_cdfs(
        p("fig12_by_common_cars.png"),
        {
            f"{k} cars": _full(_sel(records, lambda x: x.common_cars, lo, hi, True))
            for k, (lo, hi) in CAR_BUCKETS.items()
        },
        "Fig. 12: accuracy by number of commonly observed cars",
    )
    sensors = sorted({x.peer_sensor for x in records})
    _pair_cdfs(
        p("fig13_by_peer_sensor.png"),
        {f"peer {s}": _full([x for x in records if x.peer_sensor == s]) for s in sensors},
        "Fig. 13 (variant): accuracy by the peer's LiDAR model",
    )
    _pair_cdfs(
        p("fig14_with_without_box_alignment.png"),
        {"stage 1 + 2 (BB-Align)": _full(records), "stage 1 only": _stage1(records)},
        "Fig. 14: accuracy with and without box alignment",
    )
    _ap_table(p("table1_late_fusion_ap.png"), records)
    _scatter_distance(p("errors_vs_distance.png"), records)
    _covariance_figure(p("fig15_covariance_vs_true_error.png"), records)
    return paths


def _box_by_cars(path, records):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    pos, data, labels = [], [], []
    for i, (k, (lo, hi)) in enumerate(CAR_BUCKETS.items()):
        rs = _sel(records, lambda x: x.common_cars, lo, hi, True)
        for j, (name, fn) in enumerate((("BB-Align", _full), ("graph", _baseline))):
            t, _, _ = fn(rs)
            v = np.clip(np.asarray(t, float), 1e-3, 100.0)  # the pose each method reported, success or not
            data.append(v if len(v) else np.array([np.nan]))
            pos.append(i * 3 + j)
            labels.append(f"{k}\n{name}\nn={len(rs)}")
    ax.boxplot(data, positions=pos, whis=(10, 90), showfliers=False)
    ax.set_xticks(pos)
    ax.set_xticklabels(labels, fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("translation error (m), clipped at 100")
    ax.set_title("Fig. 8: translation error of the reported pose by commonly observed cars (whiskers 10/90 %)")
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _ap_table(path, records):
    plt = pyplot()
    ap = detection_ap(records)
    ranges = list(next(iter(ap.values())).keys())
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, iou in zip(axes, ("0.5", "0.7")):
        w = 0.27
        for k, pose in enumerate(ap):
            vals = [ap[pose][r][f"ap@{iou}"] or 0.0 for r in ranges]
            bars = ax.bar(np.arange(len(ranges)) + (k - 1) * w, vals, w, label=f"{pose} pose")
            ax.bar_label(bars, fmt="%.2f", fontsize=6)
        ax.set_xticks(np.arange(len(ranges)))
        ax.set_xticklabels([f"{r} m" for r in ranges])
        ax.set_ylim(0, 1)
        ax.set_ylabel(f"AP@{iou}")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle("Table I (late fusion): AP with noisy (2 m, 2 deg), recovered and true peer pose")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _ellipse(ax, cov2, k, **kw):
    """The k-sigma ellipse of a 2x2 covariance, centred at the origin."""
    w, v = np.linalg.eigh(cov2)
    a = np.linspace(0, 2 * np.pi, 100)
    xy = v @ (k * np.sqrt(np.maximum(w, 0))[:, None] * np.stack([np.cos(a), np.sin(a)]))
    ax.plot(xy[0], xy[1], **kw)


def _covariance_figure(path, records):
    """What the covariance claims against the true errors: translation ellipses of pairs across distance with
    their true error, the squared Mahalanobis distance against chi2(3), and its spread with distance."""
    from scipy.stats import chi2

    plt = pyplot()
    rs = sorted((x for x in records if x.success and mahalanobis2_of(x) is not None), key=lambda x: x.distance_m)
    fig = plt.figure(figsize=(14, 6.5))
    grid = fig.add_gridspec(2, 6)
    picks = [rs[int(i)] for i in np.linspace(0, len(rs) - 1, 8)] if len(rs) >= 8 else rs
    for i, x in enumerate(picks):
        ax = fig.add_subplot(grid[i // 4, i % 4])
        C = np.asarray(x.covariance)[1:, 1:]
        _ellipse(ax, C, 1.0, color="C0", lw=1, label="1 sigma")
        _ellipse(ax, C, 3.0, color="C0", lw=1, ls="--", label="3 sigma")
        e = np.asarray(x.error_params)
        ax.plot(e[1], e[2], "x", color="C3", ms=8, mew=2, label="true error")
        lim = max(3.2 * np.sqrt(np.linalg.eigvalsh(C).max()), 1.2 * abs(e[1:]).max(), 0.05)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        ax.set_title(f"{x.distance_m:.0f} m, d2={mahalanobis2_of(x):.1f}", fontsize=8)
        if i == 0:
            ax.legend(fontsize=6, loc="lower left")
        if i >= 4:
            ax.set_xlabel("x error (m)", fontsize=7)
        if i % 4 == 0:
            ax.set_ylabel("y error (m)", fontsize=7)
    d2 = np.array([mahalanobis2_of(x) for x in rs])
    ax = fig.add_subplot(grid[0, 4:])
    if len(d2):
        v = np.sort(d2)
        ax.step(v, np.arange(1, len(v) + 1) / len(v), where="post", label=f"{len(v)} successful pairs")
    grid_d2 = np.linspace(0, 25, 200)
    ax.plot(grid_d2, chi2.cdf(grid_d2, 3), "k--", lw=1, label="chi2(3): an exact covariance")
    ax.axvline(CHI2_3_99, color="grey", lw=0.8, ls=":")
    ax.set_xlim(0, 25)
    ax.set_xlabel("squared Mahalanobis distance of the true error (yaw, x, y)")
    ax.set_ylabel("fraction of pairs")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    ax.set_title(f"{100 * np.mean(d2 <= CHI2_3_99) if len(d2) else 0:.1f} % within the chi2(3) 99 % bound", fontsize=9)
    ax = fig.add_subplot(grid[1, 4:])
    ax.scatter([x.distance_m for x in rs], np.sqrt(d2), s=10)
    ax.axhline(np.sqrt(CHI2_3_99), color="grey", lw=0.8, ls=":", label="chi2(3) 99 % bound")
    ax.set_yscale("log")
    ax.set_xlabel("distance between the cars (m)")
    ax.set_ylabel("Mahalanobis distance")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.suptitle("Covariance vs true error: translation error ellipses (8 pairs across distance) and coverage")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _scatter_distance(path, records):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    d = np.array([x.distance_m for x in records])
    t = np.array([x.t_err_m for x in records])
    ok = np.array([x.success for x in records])
    ax.scatter(d[ok], np.maximum(t[ok], 1e-3), s=10, label="success")
    ax.scatter(d[~ok], np.maximum(t[~ok], 1e-3), s=10, marker="x", label="failed (reported pose)")
    ax.set_yscale("log")
    ax.axhline(1.0, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("distance between the cars (m)")
    ax.set_ylabel("translation error (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Translation error vs distance, every pair")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
