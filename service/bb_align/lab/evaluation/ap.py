"""Detection average precision in bird's-eye view, the way OpenCOOD evaluates V2V detectors.

- IoU of two boxes = area of the intersection of their BV rectangles over the union (heights ignored).
- Per frame, detections sorted by score; each is a true positive if its best IoU with a not yet matched ground
  truth box reaches the threshold (that box is then used up), else a false positive.
- AP over a set of frames: every frame's (score, tp) pooled and sorted by score, precision made monotone
  (VOC envelope), area under the precision-recall steps (recall points where it changes).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from bb_align.engine.boxes import as_boxes


def bev_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(Ka, 7) x (Kb, 7) boxes [x, y, z, l, w, h, yaw] -> (Ka, Kb) BV IoU."""
    a, b = as_boxes(a), as_boxes(b)
    out = np.zeros((len(a), len(b)))
    if not len(a) or not len(b):
        return out
    ra = np.hypot(a[:, 3], a[:, 4]) / 2
    rb = np.hypot(b[:, 3], b[:, 4]) / 2
    d = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    for i, j in zip(*np.nonzero(d < ra[:, None] + rb[None, :])):
        ri = ((float(a[i, 0]), float(a[i, 1])), (float(a[i, 3]), float(a[i, 4])), float(np.degrees(a[i, 6])))
        rj = ((float(b[j, 0]), float(b[j, 1])), (float(b[j, 3]), float(b[j, 4])), float(np.degrees(b[j, 6])))
        kind, pts = cv2.rotatedRectangleIntersection(ri, rj)
        if kind == cv2.INTERSECT_NONE or pts is None or len(pts) < 3:
            continue
        inter = float(cv2.contourArea(cv2.convexHull(pts)))
        union = a[i, 3] * a[i, 4] + b[j, 3] * b[j, 4] - inter
        out[i, j] = inter / union if union > 0 else 0.0
    return out


def nms_bev(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float = 0.15) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression on BV IoU (highest score first)."""
    boxes = as_boxes(boxes)
    order = np.argsort(-np.asarray(scores), kind="stable")
    iou = bev_iou(boxes, boxes)
    keep: list[int] = []
    suppressed = np.zeros(len(boxes), dtype=bool)
    for i in order:
        if suppressed[i]:
            continue
        keep.append(int(i))
        suppressed |= iou[i] > iou_threshold
    return np.asarray(keep, dtype=np.int64)


def match_frame(pred: np.ndarray, scores: np.ndarray, gt: np.ndarray, iou_threshold: float) -> np.ndarray:
    """True-positive flags (in the order of ``pred``) for one frame."""
    pred, gt = as_boxes(pred), as_boxes(gt)
    tp = np.zeros(len(pred), dtype=bool)
    if not len(pred) or not len(gt):
        return tp
    iou = bev_iou(pred, gt)
    free = np.ones(len(gt), dtype=bool)
    for i in np.argsort(-np.asarray(scores), kind="stable"):
        cand = np.where(free, iou[i], -1.0)
        j = int(np.argmax(cand))
        if cand[j] >= iou_threshold:
            tp[i] = True
            free[j] = False
    return tp


def voc_ap(scores: np.ndarray, tp: np.ndarray, n_gt: int) -> float:
    """AP from pooled detections: all-point interpolated area under the precision-recall curve."""
    if n_gt <= 0:
        return float("nan")
    order = np.argsort(-np.asarray(scores, dtype=float), kind="stable")
    tp = np.asarray(tp, dtype=float)[order]
    ctp, cfp = np.cumsum(tp), np.cumsum(1.0 - tp)
    rec = ctp / n_gt
    prec = ctp / np.maximum(ctp + cfp, 1e-12)
    mrec = np.concatenate([[0.0], rec, [1.0]])
    mpre = np.concatenate([[0.0], prec, [0.0]])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]
    idx = np.flatnonzero(mrec[1:] != mrec[:-1]) + 1
    return float(np.sum((mrec[idx] - mrec[idx - 1]) * mpre[idx]))


@dataclass
class ApAccumulator:
    """Pools frames for one (condition, range, IoU threshold)."""

    scores: list[np.ndarray] = field(default_factory=list)
    tps: list[np.ndarray] = field(default_factory=list)
    n_gt: int = 0

    def add(self, scores: np.ndarray, tp: np.ndarray, n_gt: int) -> None:
        self.scores.append(np.asarray(scores, dtype=float))
        self.tps.append(np.asarray(tp, dtype=bool))
        self.n_gt += int(n_gt)

    def ap(self) -> float:
        if not self.scores:
            return float("nan") if self.n_gt == 0 else 0.0
        return voc_ap(np.concatenate(self.scores), np.concatenate(self.tps), self.n_gt)
