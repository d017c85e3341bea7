"""Diagnostic figure of one alignment (paper Fig. 4g): the two BV images with the stage-1 inlier matches, and
the peer image warped into the ego frame over the ego image, with both cars' boxes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from bb_align.engine.bev import BevImage
from bb_align.engine.boxes import box_corners_bev, transform_boxes
from bb_align.engine.geometry import se2, se2_params
from bb_align.engine.result import AlignResult

from .errors import MissingExtraError


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend (no screen here; every figure is written as a PNG).
    Plotting is part of the ``lab`` extra: without matplotlib this raises MissingExtraError naming it."""
    try:
        import matplotlib
    except ImportError:
        raise MissingExtraError("matplotlib", "lab", "plotting (--plot, --plots)") from None

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def warp_to_ego(peer: BevImage, ego: BevImage, T_ego_peer: np.ndarray) -> np.ndarray:
    """The peer image resampled on the ego image's pixel grid through T_ego_peer (3x3 or 4x4), nearest."""
    yaw, tx, ty = se2_params(T_ego_peer)
    T_peer_ego = np.linalg.inv(se2(yaw, tx, ty))
    h, w = ego.shape
    rr, cc = np.mgrid[0:h, 0:w]
    xy_ego = ego.pixel_to_metre(np.stack([rr.ravel(), cc.ravel()], 1))
    xy_peer = xy_ego @ T_peer_ego[:2, :2].T + T_peer_ego[:2, 2]
    rc = peer.metre_to_pixel(xy_peer).astype(np.float32)
    return cv2.remap(
        peer.image,
        rc[:, 1].reshape(h, w),
        rc[:, 0].reshape(h, w),
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


SCALE_STEPS_M = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0)  # scale-bar lengths to choose from


def scale_bar_m(width_m: float, fraction: float = 0.2) -> float:
    """The longest of SCALE_STEPS_M not over ``fraction`` of the image width (the shortest if none fits)."""
    fits = [s for s in SCALE_STEPS_M if s <= fraction * width_m]
    return fits[-1] if fits else SCALE_STEPS_M[0]


def _label_and_scale(ax, bev: BevImage, label: str, col0: int = 0) -> tuple[float, float]:
    """Name an image drawn at columns col0.. of ``ax`` and draw a metre scale bar at its lower left.
    Returns (bar length m, bar length px)."""
    h, w = bev.shape
    box = {"facecolor": "white", "edgecolor": "0.4", "alpha": 0.85, "pad": 2}
    ax.text(col0 + 0.02 * w, 0.03 * h, label, va="top", ha="left", fontsize=10, weight="bold", bbox=box)
    length_m = scale_bar_m(w * bev.resolution_m)
    length_px = length_m / bev.resolution_m
    x0, y0 = col0 + 0.04 * w, 0.95 * h
    ax.plot([x0, x0 + length_px], [y0, y0], "-", color="black", lw=3, solid_capstyle="butt")
    ax.text(x0 + length_px / 2, y0 - 0.015 * h, f"{length_m:g} m", ha="center", va="bottom", fontsize=9, bbox=box)
    return length_m, length_px


def plot_alignment(
    path: str | Path,
    ego: BevImage,
    peer: BevImage,
    result: AlignResult,
    boxes_ego: np.ndarray | None = None,
    boxes_peer: np.ndarray | None = None,
    title: str | None = None,
) -> Path:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(16, 8.4))
    # (a) side by side with inlier matches
    h = max(ego.shape[0], peer.shape[0])
    canvas = np.zeros((h, ego.shape[1] + peer.shape[1]), np.uint8)
    canvas[: ego.shape[0], : ego.shape[1]] = ego.image
    canvas[: peer.shape[0], ego.shape[1] :] = peer.image
    axes[0].imshow(canvas > 0, cmap="gray_r", interpolation="nearest")
    if len(result.inlier_xy_ego):
        a = ego.metre_to_pixel(result.inlier_xy_ego)
        b = peer.metre_to_pixel(result.inlier_xy_peer)
        for (r0, c0), (r1, c1) in zip(a, b):
            axes[0].plot([c0, c1 + ego.shape[1]], [r0, r1], "-", lw=0.6, color="tab:green", alpha=0.7)
    _label_and_scale(axes[0], ego, "ego")
    _label_and_scale(axes[0], peer, "peer", col0=ego.shape[1])
    axes[0].axvline(ego.shape[1] - 0.5, color="0.5", lw=1)
    axes[0].set_title(f"ego | peer BV images, {result.inliers_bv} stage-1 inliers of {result.matches_bv} matches")
    axes[0].axis("off")
    # (b) overlay in the ego frame
    warped = warp_to_ego(peer, ego, result.T_ego_peer)
    rgb = np.full(ego.shape + (3,), 255, np.uint8)
    rgb[ego.image > 0] = (220, 40, 40)
    rgb[warped > 0] = (40, 140, 40)
    rgb[(ego.image > 0) & (warped > 0)] = (30, 30, 30)
    axes[1].imshow(rgb, interpolation="nearest")
    T2 = result.T_box @ result.T_bv
    for boxes, color in (
        (boxes_ego, "tab:red"),
        (None if boxes_peer is None else transform_boxes(T2, boxes_peer), "tab:green"),
    ):
        if boxes is None or len(boxes) == 0:
            continue
        for corners in box_corners_bev(boxes):
            rc = ego.metre_to_pixel(np.vstack([corners, corners[:1]]))
            axes[1].plot(rc[:, 1], rc[:, 0], "-", lw=0.8, color=color)
    _label_and_scale(axes[1], ego, "overlay (ego frame)")
    status = "success" if result.success else f"FAILED: {result.reason}"
    axes[1].set_title(
        f"ego (red) + aligned peer (green), overlap black\n{status}; yaw {result.yaw_deg:.2f} deg, "
        f"t = ({result.tx:.2f}, {result.ty:.2f}) m, confidence {result.confidence:.2f}"
    )
    axes[1].axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
