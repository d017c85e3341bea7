"""Graph-matching baseline in the style of VIPS (Shi et al., MobiCom 2022): boxes only, no image.

Each car's detections are a graph: nodes are boxes (with size and heading), edges the distances between them.
A candidate correspondence pairs an ego box with a peer box of similar size; two candidates are consistent
when they preserve the edge length and the relative heading (modulo 180 degrees, detectors flip headings).
Spectral matching: the principal eigenvector of the pairwise-consistency matrix scores the candidates, a
greedy one-to-one pass keeps the best, and a rigid fit on the matched centres (dropping residuals over
``inlier_m``) gives T_ego_peer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bb_align.engine.boxes import as_boxes
from bb_align.engine.geometry import kabsch_2d, transform_points_2d, wrap_angle


class GraphMatchConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    size_gate_m: float = Field(1.2, gt=0, description="candidate pairs differ by less than this in l and in w")
    edge_sigma_m: float = Field(0.6, gt=0, description="edge-length consistency scale")
    heading_sigma_deg: float = Field(12.0, gt=0, description="relative-heading consistency scale")
    max_candidates: int = Field(900, ge=10, description="keep at most this many candidates (best node scores)")
    inlier_m: float = Field(1.5, gt=0, description="matched centres farther than this from the fit are dropped")
    min_matches: int = Field(3, ge=2, description="success needs at least this many consistent matches")


@dataclass
class GraphMatchResult:
    success: bool
    T_ego_peer: np.ndarray  # 3x3
    matches: int


def graph_match(boxes_ego, boxes_peer, config: GraphMatchConfig | None = None) -> GraphMatchResult:
    """T_ego_peer (3x3) from the two cars' boxes alone."""
    cfg = config or GraphMatchConfig()
    e, p = as_boxes(boxes_ego), as_boxes(boxes_peer)
    fail = GraphMatchResult(False, np.eye(3), 0)
    if len(e) < 2 or len(p) < 2:
        return fail
    dl = np.abs(e[:, None, 3] - p[None, :, 3])
    dw = np.abs(e[:, None, 4] - p[None, :, 4])
    node = np.exp(-(dl**2 + dw**2) / (2 * 0.5**2))
    ii, aa = np.nonzero((dl < cfg.size_gate_m) & (dw < cfg.size_gate_m))
    if len(ii) > cfg.max_candidates:
        best = np.argsort(-node[ii, aa])[: cfg.max_candidates]
        ii, aa = ii[best], aa[best]
    if len(ii) < 2:
        return fail
    d_e = np.hypot(*(e[:, None, :2] - e[None, :, :2]).transpose(2, 0, 1))
    d_p = np.hypot(*(p[:, None, :2] - p[None, :, :2]).transpose(2, 0, 1))
    edge = d_e[ii][:, ii] - d_p[aa][:, aa]
    rel_e = e[ii, 6][:, None] - e[ii, 6][None, :]
    rel_p = p[aa, 6][:, None] - p[aa, 6][None, :]
    dh = np.abs(wrap_angle(2 * (rel_e - rel_p))) / 2  # modulo 180 degrees
    sigma_h = np.radians(cfg.heading_sigma_deg)
    M = np.exp(-(edge**2) / (2 * cfg.edge_sigma_m**2)) * np.exp(-(dh**2) / (2 * sigma_h**2))
    M[np.abs(edge) > 3 * cfg.edge_sigma_m] = 0.0
    M[(ii[:, None] == ii[None, :]) | (aa[:, None] == aa[None, :])] = 0.0  # one-to-one
    np.fill_diagonal(M, node[ii, aa])
    w, v = np.linalg.eigh(M)
    x = np.abs(v[:, -1])
    used_e, used_p, chosen = set(), set(), []
    for k in np.argsort(-x):
        if x[k] < 0.05 * x.max():
            break
        if ii[k] in used_e or aa[k] in used_p:
            continue
        chosen.append(k)
        used_e.add(ii[k])
        used_p.add(aa[k])
    if len(chosen) < cfg.min_matches:
        return GraphMatchResult(False, np.eye(3), len(chosen))
    src, dst = p[aa[chosen], :2], e[ii[chosen], :2]
    keep = np.ones(len(chosen), dtype=bool)
    T = np.eye(3)
    for _ in range(5):  # refit without the worst-fitting matches
        if keep.sum() < 2:
            break
        T = kabsch_2d(src[keep], dst[keep])
        res = np.linalg.norm(transform_points_2d(T, src) - dst, axis=1)
        new = res < cfg.inlier_m
        if (new == keep).all():
            break
        keep = new
    n = int(keep.sum())
    return GraphMatchResult(n >= cfg.min_matches, T, n)
