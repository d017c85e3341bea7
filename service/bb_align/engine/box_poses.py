"""Poses proposed by the boxes both cars detected: stage 1's second source of hypotheses (docs/acquisition.md).

At 70-100 m the two views' descriptors rarely agree, but the cars both of them detected still do. Two detections
of one car agree in place, in heading (up to a detector's 180-degree flip) and in footprint size. Under a pose, a
peer box *pairs* with an ego box only when all three agree. Rows of parked cars give many wrong poses several
boxes that agree in place alone; heading and size thin those out. The poses found are ranked by a soft score (a
Gaussian of each pair's distance), so a tight fit of a few cars beats a loose fit of many.

1. seeds: every (peer box, ego box, heading flip) that agrees in size implies a pose: yaw from the two headings,
   translation from the two centres. Its support is the number of peer boxes that pair within ``box_seed_gate_m``.
2. refits: the best-supported distinct seeds are refitted by Kabsch on their paired centres (``box_seed_gate_m``,
   then ``box_gate_m``; compiled, one-to-one pairs by nearest agreeing box). The headings only seed the yaw: 3
   degrees of heading noise move a car 50 m away by 2.6 m.
3. ranking: the refitted poses with at least ``box_min_pairs`` pairs, by soft score, at most ``box_hypotheses``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .boxes import as_boxes
from .config import AcquireConfig
from .geometry import pose_is_distinct, se2, se2_params


@dataclass(frozen=True)
class BoxSet:
    """The bird's-eye part of one car's boxes as contiguous arrays, in that car's frame."""

    centres: np.ndarray  # (N, 2) metres
    headings: np.ndarray  # (N,) radians
    sizes: np.ndarray  # (N, 2) length, width in metres

    @classmethod
    def of(cls, boxes, n_max: int | None = None) -> BoxSet:
        """(N, 7) boxes [x, y, z, l, w, h, yaw]; with ``n_max``, the n_max nearest the sensor (a detector places
        those best)."""
        b = as_boxes(boxes)
        if n_max is not None and len(b) > n_max:
            b = b[np.argsort(np.hypot(b[:, 0], b[:, 1]), kind="stable")[:n_max]]
        c = np.ascontiguousarray
        return cls(c(b[:, :2], dtype=float), c(b[:, 6], dtype=float), c(b[:, 3:5], dtype=float))

    def __len__(self) -> int:
        return len(self.centres)


def same_size(peer: BoxSet, ego: BoxSet, cfg: AcquireConfig) -> np.ndarray:
    """(P, E) bool: the footprints (length, width) differ by less than ``box_size_tol_m``."""
    d = peer.sizes[:, None, :] - ego.sizes[None, :, :]
    return (d**2).sum(-1) < cfg.box_size_tol_m**2


@njit(cache=True, nogil=True, inline="always")
def _same_heading(heading_a, heading_b, heading_tol):
    """Headings within heading_tol modulo 180 degrees (a detector may report a car backwards)."""
    g = (heading_a - heading_b) % np.pi
    return min(g, np.pi - g) < heading_tol


@njit(cache=True, nogil=True)
def _nearest_agreeing(px, py, heading, size_ok_row, c_ego, h_ego, gate2, heading_tol):
    """The ego box nearest (px, py) closer than sqrt(gate2) that agrees with a peer box seen there with ``heading``
    (both in the ego frame): same footprint (``size_ok_row``) and heading within heading_tol modulo 180 degrees (a
    detector may report a car backwards). Returns (index, squared distance), or (-1, gate2) when there is none."""
    best, best_d2 = -1, gate2
    for b in range(len(c_ego)):
        if not size_ok_row[b]:
            continue
        d2 = (px - c_ego[b, 0]) ** 2 + (py - c_ego[b, 1]) ** 2
        if d2 >= best_d2:
            continue
        if _same_heading(heading, h_ego[b], heading_tol):  # the costlier test last
            best, best_d2 = b, d2
    return best, best_d2


@njit(cache=True, nogil=True)
def _agreeing_d2(yaw, tx, ty, c_peer, h_peer, c_ego, h_ego, size_ok, heading_tol):
    """Per peer box under the pose (yaw, tx, ty): the squared distance to its nearest agreeing ego box (inf: none)."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.empty(len(c_peer))
    for a in range(len(c_peer)):
        px = c * c_peer[a, 0] - s * c_peer[a, 1] + tx
        py = s * c_peer[a, 0] + c * c_peer[a, 1] + ty
        out[a] = _nearest_agreeing(px, py, h_peer[a] + yaw, size_ok[a], c_ego, h_ego, np.inf, heading_tol)[1]
    return out


def box_agreement(
    T: np.ndarray, peer: BoxSet, ego: BoxSet, cfg: AcquireConfig, size_ok: np.ndarray | None = None
) -> tuple[int, float]:
    """Under T (ego <- peer): the peer boxes paired with an agreeing ego box within ``box_gate_m``, and the soft
    score (sum over peer boxes of the nearest agreeing ego box's exp(-d^2 / 2 box_sigma_m^2)). ``size_ok``:
    ``same_size(peer, ego, cfg)`` when already computed."""
    if len(peer) == 0 or len(ego) == 0:
        return 0, 0.0
    d2 = _agreeing_d2(
        *se2_params(T),
        peer.centres,
        peer.headings,
        ego.centres,
        ego.headings,
        same_size(peer, ego, cfg) if size_ok is None else size_ok,
        np.radians(cfg.box_heading_tol_deg),
    )
    return int((d2 < cfg.box_gate_m**2).sum()), float(np.exp(-d2 / (2 * cfg.box_sigma_m**2)).sum())


@njit(cache=True, nogil=True)
def _cells(c_ego, cell):
    """The ego boxes bucketed on a square grid of side ``cell`` (metres): (x0, y0, nx, ny, start, order), where
    order[start[k]:start[k + 1]] lists the boxes of cell k = ix * ny + iy in increasing index."""
    x0, y0 = c_ego[:, 0].min(), c_ego[:, 1].min()
    nx = int((c_ego[:, 0].max() - x0) / cell) + 1
    ny = int((c_ego[:, 1].max() - y0) / cell) + 1
    key = np.empty(len(c_ego), np.int64)
    for b in range(len(c_ego)):
        key[b] = int((c_ego[b, 0] - x0) / cell) * ny + int((c_ego[b, 1] - y0) / cell)
    order = np.argsort(key, kind="mergesort")  # stable: increasing index within a cell
    start = np.zeros(nx * ny + 1, np.int64)
    for b in range(len(c_ego)):
        start[key[b] + 1] += 1
    for k in range(nx * ny):
        start[k + 1] += start[k]
    return x0, y0, nx, ny, start, order


@njit(cache=True, nogil=True)
def _seeds(c_peer, h_peer, c_ego, h_ego, size_ok, gate2, heading_tol):
    """(yaw, tx, ty, support) of every (peer box i, ego box k, flip f) seed whose two boxes agree in size (others:
    support 0). Support: the peer boxes within sqrt(gate2) of an agreeing ego box under the seed's pose (looked up
    on a grid of the ego boxes: every seed asks it for every peer box)."""
    p, e = len(c_peer), len(c_ego)
    n = p * e * 2
    yaw, tx, ty = np.zeros(n), np.zeros(n), np.zeros(n)
    sup = np.zeros(n, np.int64)
    if p == 0 or e == 0:
        return yaw, tx, ty, sup
    cell = np.sqrt(gate2)
    x0, y0, nx, ny, start, order = _cells(c_ego, cell)
    h = -1
    for i in range(p):
        for k in range(e):
            for f in range(2):
                h += 1
                if not size_ok[i, k]:
                    continue
                th = h_ego[k] - h_peer[i] + f * np.pi
                c, s = np.cos(th), np.sin(th)
                x = c_ego[k, 0] - (c * c_peer[i, 0] - s * c_peer[i, 1])
                y = c_ego[k, 1] - (s * c_peer[i, 0] + c * c_peer[i, 1])
                m = 0
                for a in range(p):
                    px = c * c_peer[a, 0] - s * c_peer[a, 1] + x
                    py = s * c_peer[a, 0] + c * c_peer[a, 1] + y
                    fx, fy = (px - x0) / cell, (py - y0) / cell
                    if fx < -1.0 or fy < -1.0 or fx >= nx + 1.0 or fy >= ny + 1.0:
                        continue
                    # Any agreeing ego box within the gate in the 3 x 3 cells around (px, py) (a side >= the gate:
                    # they hold every box that near) counts this peer box.
                    ix, iy = int(np.floor(fx)), int(np.floor(fy))
                    hit = False
                    for cx in range(max(ix - 1, 0), min(ix + 2, nx)):
                        for cy in range(max(iy - 1, 0), min(iy + 2, ny)):
                            q = cx * ny + cy
                            for n_ in range(start[q], start[q + 1]):
                                b = order[n_]
                                if hit or not size_ok[a, b]:
                                    continue
                                if (px - c_ego[b, 0]) ** 2 + (py - c_ego[b, 1]) ** 2 >= gate2:
                                    continue
                                hit = _same_heading(h_peer[a] + th, h_ego[b], heading_tol)
                    m += hit
                yaw[h], tx[h], ty[h], sup[h] = th, x, y, m
    return yaw, tx, ty, sup


@njit(cache=True, nogil=True)
def _refit(yaw, tx, ty, c_peer, h_peer, c_ego, h_ego, size_ok, gates, heading_tol, min_pairs):
    """Kabsch on the agreeing pairs at each gate in turn (the seed gate, then the final one), the pose refitted
    between them. Pairs are one-to-one: each peer box takes its nearest agreeing ego box within the gate, and an ego
    box claimed twice keeps the nearer peer box. Returns (ok, yaw, tx, ty); ok False when fewer than min_pairs
    pair at some gate."""
    p, e = len(c_peer), len(c_ego)
    for gate in gates:
        c, s = np.cos(yaw), np.sin(yaw)
        best_d = np.full(e, np.inf)
        owner = np.full(e, -1)
        for a in range(p):
            px = c * c_peer[a, 0] - s * c_peer[a, 1] + tx
            py = s * c_peer[a, 0] + c * c_peer[a, 1] + ty
            bb, bd = _nearest_agreeing(px, py, h_peer[a] + yaw, size_ok[a], c_ego, h_ego, gate * gate, heading_tol)
            if bb >= 0 and bd < best_d[bb]:
                best_d[bb], owner[bb] = bd, a
        n = 0
        mp = np.zeros(2)
        me = np.zeros(2)
        for b in range(e):
            if owner[b] >= 0:
                n += 1
                mp += c_peer[owner[b]]
                me += c_ego[b]
        if n < min_pairs:
            return False, yaw, tx, ty
        mp /= n
        me /= n
        sxx = 0.0  # sum of dot and cross products of the centred pairs: the 2-D Kabsch angle in closed form
        sxy = 0.0
        for b in range(e):
            if owner[b] >= 0:
                qx, qy = c_peer[owner[b], 0] - mp[0], c_peer[owner[b], 1] - mp[1]
                rx, ry = c_ego[b, 0] - me[0], c_ego[b, 1] - me[1]
                sxx += qx * rx + qy * ry
                sxy += qx * ry - qy * rx
        yaw = np.arctan2(sxy, sxx)
        c, s = np.cos(yaw), np.sin(yaw)
        tx = me[0] - (c * mp[0] - s * mp[1])
        ty = me[1] - (s * mp[0] + c * mp[1])
    return True, yaw, tx, ty


@dataclass
class BoxPose:
    T: np.ndarray  # 3x3 ego <- peer
    pairs: int  # peer boxes paired with an agreeing ego box within box_gate_m
    score: float  # soft score (box_agreement)


def box_poses(boxes_ego, boxes_peer, cfg: AcquireConfig) -> list[BoxPose]:
    """Up to ``cfg.box_hypotheses`` distinct poses with at least ``cfg.box_min_pairs`` pairs, best score first."""
    ego, peer = BoxSet.of(boxes_ego, cfg.box_max), BoxSet.of(boxes_peer, cfg.box_max)
    if cfg.box_hypotheses == 0 or min(len(ego), len(peer)) < cfg.box_min_pairs:
        return []
    size_ok, tol = same_size(peer, ego, cfg), np.radians(cfg.box_heading_tol_deg)
    gates = np.array([cfg.box_seed_gate_m, cfg.box_gate_m])
    yaw, tx, ty, sup = _seeds(
        peer.centres, peer.headings, ego.centres, ego.headings, size_ok, cfg.box_seed_gate_m**2, tol
    )
    found: list[BoxPose] = []
    found_params = np.empty((cfg.max_refit_attempts, 3))  # se2_params of found's poses
    seen = _PoseSet(cfg)  # the seeds tried and the poses found
    for h in np.argsort(-sup, kind="stable"):
        if sup[h] < cfg.box_min_pairs or seen.tried >= cfg.max_refit_attempts:
            break
        if seen.near(yaw[h], tx[h], ty[h]):
            continue  # a pose already tried or found (each car of one alignment seeds it again)
        seen.add(yaw[h], tx[h], ty[h], tried=True)
        ok, *params = _refit(
            yaw[h],
            tx[h],
            ty[h],
            peer.centres,
            peer.headings,
            ego.centres,
            ego.headings,
            size_ok,
            gates,
            tol,
            cfg.box_min_pairs,
        )
        T = se2(*params)
        pose = se2_params(T)
        if not ok or not pose_is_distinct(found_params[: len(found)], pose, cfg.distinct_m, cfg.distinct_deg):
            continue
        found_params[len(found)] = pose
        found.append(BoxPose(T, *box_agreement(T, peer, ego, cfg, size_ok)))
        seen.add(*pose)
    found = [b for b in found if b.pairs >= cfg.box_min_pairs]
    found.sort(key=lambda b: -b.score)
    return found[: cfg.box_hypotheses]


class _PoseSet:
    """(yaw, tx, ty) of the poses seen so far, in growing arrays: a seed near one of them is not refitted again."""

    def __init__(self, cfg: AcquireConfig):
        self.cfg, self.tried, self.n = cfg, 0, 0
        self.params = np.empty((2 * cfg.max_refit_attempts + 1, 3))

    def add(self, yaw: float, tx: float, ty: float, tried: bool = False) -> None:
        self.params[self.n] = yaw, tx, ty
        self.n += 1
        self.tried += tried

    def near(self, yaw: float, tx: float, ty: float) -> bool:
        return not pose_is_distinct(self.params[: self.n], (yaw, tx, ty), self.cfg.distinct_m, self.cfg.distinct_deg)
