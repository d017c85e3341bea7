"""Every tunable number of the engine, in one place (pydantic models).

Defaults follow ../shared/reference/ALGORITHM.md (the numbers the paper leaves out) unless a measurement in
docs/ says otherwise. Each step of the pipeline is built once from its section (``Aligner.__init__``). The
service's own settings (ports, Zenoh, limits) live in ``bb_align.server.settings`` and embed an :class:`AlignConfig`;
``bb-align config --dump`` prints these defaults, ``bb-align align --config FILE`` loads a saved one.
"""

from __future__ import annotations

import json
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class BevConfig(_Frozen):
    """Bird's-eye-view height image (paper Eq. 4)."""

    range_m: float = Field(
        100.0,
        gt=0,
        le=250,
        description="half width R of the square image, metres (100: 500 x 500 "
        "px; measured against 80 and 120 on the 200-pair simulated benchmark, docs/acquisition.md: "
        "80 -> 100 raises 40-70 m pairs under 1 m & 1 deg from 20 % to 31 % (paper) and the multi "
        "path's from 48 % to 66 % (gates open); 120 adds nothing over 100 at 2.25x the MIM cost)",
    )
    resolution_m: float = Field(0.4, gt=0.01, le=5, description="cell size c, metres per pixel")
    mode: Literal["max_height", "slices"] = Field(
        "max_height", description="max_height: paper's max z per cell; slices: occupied z-slices (reference)"
    )
    ground_clearance_m: float = Field(0.3, ge=0, description="heights below this above the local ground map to 0")
    max_height_m: float = Field(12.0, gt=0, description="heights above the ground are clipped here")
    slice_m: float = Field(0.2, gt=0, description="slice thickness for mode='slices'")
    ground_cell_m: float = Field(2.0, gt=0, description="cell of the coarse ground-height grid")
    ground_window_cells: int = Field(3, ge=1, description="min-filter window over the coarse ground grid")


class MimConfig(_Frozen):
    """Log-Gabor bank and Maximum Index Map (Eqs. 5-10)."""

    n_scales: int = Field(4, ge=1, le=8)
    n_orient: int = Field(12, ge=4, le=36)
    min_wavelength_px: float = Field(3.0, gt=1)
    mult: float = Field(1.6, gt=1)
    sigma_on_f: float = Field(0.75, gt=0, lt=1)
    lowpass_cutoff: float = Field(0.45, gt=0, le=0.5)
    lowpass_order: int = Field(15, ge=1)
    min_amplitude: float = Field(0.1, ge=0, description="MIM = 0 where max_o A_o <= this (image in 0..255)")
    fft_margin_px: int = Field(
        16,
        ge=0,
        description="zero margin around the image before the FFT (no wrap-around; "
        "16 px: 432 x 432 transforms for 400 px images, 99.5% the same MIM as 24 px)",
    )
    coarse_scales: int = Field(
        4,
        ge=0,
        le=8,
        description="the coarsest scales whose response is computed on a grid decimated by coarse_stride (their "
        "band fits it) and interpolated back: fewer, smaller inverse DFTs",
    )
    coarse_stride: int = Field(2, ge=2, le=8, description="decimation of the coarse scales' grid, each way")
    threads: int = Field(2, ge=1, le=12, description="orientation groups computed in parallel (same result)")
    filter_cache_mb: float = Field(
        256.0,
        ge=0,
        description="the per-shape filter banks kept, bounded in MB (least recently used shapes go first); a "
        "400 px image's boxed bank is about 30 MB",
    )


class FeatureConfig(_Frozen):
    """FAST keypoints and BVFT descriptors."""

    fast_threshold: int = Field(10, ge=1, le=255)
    max_keypoints: int = Field(400, ge=10, le=5000, description="strongest FAST responses kept")
    patch_px: int = Field(96, ge=24, description="descriptor window J")
    grid: int = Field(6, ge=2, description="cells per side l")
    merge_bins: bool = Field(True, description="True: 216-D (bins merged in pairs); False: 432-D")
    reference_orientation_offsets: tuple[int, ...] = Field(
        (0, -1, 1),
        description="the matched-against (ego) side also describes each keypoint as if its dominant "
        "orientation were these neighbouring bins: a peer whose orientation estimate is one bin off still finds "
        "its match (measured: +35% correct matches at 40-70 m; docs/engine.md)",
    )
    window_stride: int = Field(1, ge=1, le=4, description="sample every n-th pixel each way of the J x J window")
    threads: int = Field(2, ge=1, le=16, description="keypoint groups described in parallel (same result)")
    orientation_stride: int = Field(
        2,
        ge=1,
        le=4,
        description="sample every n-th pixel each way of the dominant-orientation disc (2: a "
        "quarter of the work, same accuracy on the simulated pairs; docs/engine.md)",
    )


class MatchConfig(_Frozen):
    """Descriptor matching (stage 1, Algorithm 1 lines 9-10)."""

    mutual: bool = Field(False, description="keep only mutual nearest neighbours")
    ratio: float = Field(1.0, gt=0, le=1, description="Lowe ratio test; 1.0 disables it")
    threads: int = Field(2, ge=1, le=16, description="blocks of query descriptors matched in parallel (same result)")


class RansacConfig(_Frozen):
    """Rigid 2-D RANSAC (seeded, adaptive, vectorised; Kabsch refit). Stage 1 fits keypoint matches with
    ``AlignConfig.ransac``; stage 2 fits box corners with ``BoxConfig.ransac``."""

    inlier_threshold_m: float = Field(2.0, gt=0, description="a match is an inlier when mapped this close")
    min_sample_dist_m: float = Field(3.0, ge=0, description="the two points of a sample must be this far apart")
    max_iterations: int = Field(5000, ge=10)
    min_iterations: int = Field(200, ge=1, description="hypotheses scored at least, whatever the adaptive count")
    confidence: float = Field(0.9999, gt=0, lt=1, description="adaptive stop: P(an all-inlier sample was drawn)")
    batch: int = Field(256, ge=1, description="samples scored together (vectorised)")
    refits: int = Field(3, ge=0, description="Kabsch refits on the inliers after the best hypothesis")
    ambiguity_hypotheses: int = Field(
        1024, ge=1, description="best-scoring hypotheses searched for a distinct runner-up (RansacResult.ambiguity)"
    )


class PriorConfig(_Frozen):
    """Optional prior pose (e.g. from the cars' reported GPS poses). In multi mode the pose must lie inside its
    window; when the search everywhere fails, the window is searched alone (only poses inside it hypothesised,
    verified and counted as rivals; the prior pose itself verified as one more), and a pose found there must be
    precise (max_sigma_m). In paper mode it gates the descriptor matches. Without a prior the engine searches every
    yaw and shift (the paper's setting)."""

    max_translation_m: float = Field(10.0, gt=0, description="how far the true pose may be from the prior")
    sigma_m: float = Field(
        2.0,
        gt=0,
        description="the prior's own 1-sigma in x and y, metres (GNSS-grade: the field's sigma_t = 2 m): its "
        "density weighs each rival of the answer inside the prior's window",
    )
    sigma_deg: float = Field(2.0, gt=0, description="the prior's 1-sigma in yaw, degrees")
    max_yaw_deg: float = Field(10.0, gt=0, le=180)
    top_k: int = Field(4, ge=1, le=32, description="paper mode: descriptor candidates per peer keypoint gated")
    verify_prior_pose: bool = Field(True, description="multi mode: the prior pose is also verified as a hypothesis")
    max_sigma_m: float = Field(
        0.3,
        gt=0,
        description="multi mode: a pose found inside the window alone is refused when its 1-sigma along its worst "
        "translation direction exceeds this (fewer rivals there, so the pose must be precise): the largest value "
        "with no wrong success on seeds 2024 and 777, checked on 4242, 9001, 31337 and 55555 (docs/acquisition.md, "
        "Session 10)",
    )


class RefineConfig(_Frozen):
    """Dense point-to-line ICP on the lit BV pixels after stage 1 (not in the paper; see bb_align.engine.refine)."""

    enabled: bool = True
    gates_m: tuple[float, ...] = Field((2.0, 1.0, 0.5, 0.4), description="correspondence gates, coarse to fine")
    iters_per_gate: int = Field(3, ge=1, le=50)
    step_relaxation: float = Field(
        2.0, ge=1.0, le=3.0, description="a Gauss-Newton step continuing the previous one is lengthened so"
    )
    min_pixel_value: int = Field(1, ge=1, le=255, description="pixels at or above this value take part")
    max_peer_points: int = Field(2000, ge=100, description="seeded random subset of the peer's lit pixels")
    max_correction_m: float = Field(2.0, gt=0)
    max_correction_deg: float = Field(3.0, gt=0)
    point_weight: float = Field(
        0.1,
        ge=0,
        description="weight of the point-to-point terms beside the point-to-line ones: pins the motion along a line",
    )
    huber_fraction: float = Field(
        0.25, gt=0, description="Huber threshold of the point-to-line residual, as a fraction of the current gate"
    )
    normal_neighbours: int = Field(8, ge=3, le=64, description="ego pixels in each pixel's PCA normal")
    facing_min_cos: float = Field(
        0.5,
        ge=-1,
        le=1,
        description="a peer pixel pairs with an ego pixel only if their normals, each turned towards its own "
        "sensor, agree this well (cosine): two faces of one object between the cars are not one surface; -1: off "
        "(refined from the truth at 85-100 m, within 1 m & 1 deg: 54 % off, 83 % at 0.5; benchmarks/facing_study.py)",
    )
    peer_normal_px: int = Field(2, ge=1, le=6, description="half window (pixels) of the peer pixels' PCA normals")
    min_points: int = Field(10, ge=3, description="fewer ego pixels, peer points or matches: no refinement")
    converged_rad: float = Field(2e-5, gt=0, description="a step under this yaw and converged_m ends a gate")
    converged_m: float = Field(0.002, gt=0)


class BoxConfig(_Frozen):
    """Stage 2: box-corner alignment."""

    apply: Literal["always", "unrefined", "auto"] = Field(
        "auto",
        description="always: T_2D = T_box @ T_bv (the paper). unrefined: stage 2 estimates T_box and counts "
        "Inliers_box for the success rule, but applies its correction only when the dense BV refinement did not "
        "run or was rejected (box corners from a noisy detector are less precise than the refined images). auto: "
        "as unrefined, but a box correction over recheck_m / recheck_deg is refined again on the BV images and "
        "kept when the images agree with it better (a refinement stuck in a local optimum); docs/engine.md",
    )
    recheck_m: float = Field(0.5, ge=0, description="auto: box corrections beyond this are re-refined and compared")
    recheck_deg: float = Field(0.5, ge=0, description="auto: likewise for the yaw correction")
    recheck_min_gain: float = Field(
        0.01,
        ge=0,
        description="auto: the re-refined box-corrected pose is kept when "
        "its overlap fitness beats the refined stage-1 pose's by more than this",
    )
    pair_gate_m: float = Field(3.0, gt=0, description="peer/ego box centres closer than this may pair")
    ransac: RansacConfig = RansacConfig(
        inlier_threshold_m=0.8, min_sample_dist_m=1.0, max_iterations=500, min_iterations=256
    )
    max_correction_m: float = Field(4.0, gt=0, description="stage 2 may move stage 1 by at most this")
    max_correction_deg: float = Field(6.0, gt=0)
    fuse: bool = Field(
        True,
        description="after stage 2 verified the pose, fuse the paired boxes as a second measurement "
        "of it, by information with the refined pose's covariance (not in the paper; docs/acquisition.md)",
    )
    fuse_sigma_m: float = Field(
        1.3, gt=0, description="1-sigma of one paired box centre (the tracker's track.box_sigma_m, docs/tracking.md)"
    )
    fuse_min_pairs: int = Field(2, ge=2, description="box pairs needed for the fused measurement (two fix the yaw)")
    fuse_chi2: float = Field(
        11.345, gt=0, description="fused only when the two measurements agree (squared Mahalanobis, chi2(3) 99 %)"
    )
    fuse_disagreement_fails: bool = Field(
        True,
        description="when the boxes' measurement and the refined pose disagree (beyond fuse_chi2) the alignment fails "
        "(box_correction_too_large) instead of keeping the refined pose: two independent measurements contradict each "
        "other (measured: every such success on four simulated seeds was wrong, 1.7-1.8 m off at 77-78 m)",
    )


class SuccessRule(_Frozen):
    """Paper rule: Inliers_bv > 25 and Inliers_box > 6."""

    min_inliers_bv: int = Field(25, ge=0, description="success needs inliers_bv > this")
    min_inliers_box: int = Field(6, ge=0, description="success needs inliers_box > this (when boxes are given)")
    strong_inliers_bv: int | None = Field(
        None,
        ge=0,
        description="if set, a pair whose stage 2 cannot verify it (no box overlap, too few box "
        "inliers) still succeeds when inliers_bv exceeds this (the paper's Fig. 9: > 100 puts > 90% of pairs "
        "under 1 m / 1 deg); None keeps the paper's rule",
    )
    require_boxes: bool = Field(
        False, description="True: a pair without boxes fails; False: stage 1 alone decides (said in the reason)"
    )
    max_ambiguity: float = Field(
        0.8, gt=0, le=1, description="fail when a distinct runner-up pose has this fraction of the best inliers"
    )
    min_refine_fitness: float = Field(
        0.2,
        ge=0,
        le=1,
        description="fail when, after the dense refinement, fewer than this fraction of the peer's lit BV pixels lie "
        "within the finest gate of an ego pixel (catches keypoint aliases along repetitive streets; measured: "
        "correct sim pairs >= 0.19, wrong ones <= 0.17, real KITTI 16 m pair 0.51)",
    )


class ConfidenceConfig(_Frozen):
    """Evidence -> confidence in [0, 1] (bb_align.engine.verdict): each stage's share saturates exponentially in its
    inliers above the success rule's minimum; the paper's Fig. 9 puts > 90 % of pairs under 1 m / 1 deg beyond
    100 BV or 20 box inliers."""

    bv_inlier_scale: float = Field(
        40.0, gt=0, description="BV inliers above the minimum giving 63 % of stage 1's share"
    )
    box_inlier_scale: float = Field(8.0, gt=0, description="likewise for box inliers")
    fitness_span: float = Field(
        0.2,
        gt=0,
        description="stage 1's share grows linearly over this much refinement fitness above success.min_refine_fitness",
    )
    cap_stage1_failed: float = Field(0.1, ge=0, le=1, description="most confidence a failure before stage 2 gets")
    cap_stage2_failed: float = Field(0.5, ge=0, le=1, description="most confidence when only stage 2 failed")


class AcquireConfig(_Frozen):
    """Stage-1 acquisition (bb_align.engine.acquire). paper: one RANSAC fit on nearest-neighbour matches (the
    paper's Algorithm 1). multi: top-k descriptor candidates, distinct pose hypotheses by pairwise voting, each
    verified by the dense refinement, chosen with a margin over the runner-up."""

    mode: Literal["paper", "multi"] = Field("multi", description="paper: single hypothesis; multi: see above")
    top_k: int = Field(12, ge=1, le=32, description="nearest distinct ego keypoints kept per peer descriptor")
    threads: int = Field(
        2, ge=1, le=16, description="the pose vote and the dense verification run on this many threads (same result)"
    )
    first_k: int = Field(3, ge=0, le=32, description="cheap first pass on the first_k nearest candidates only; 0: off")
    first_pass_evidence: float = Field(
        1.0,
        ge=0,
        description="the first pass decides only when margin x relative fitness reaches this (1.5x "
        "min_evidence; wrong poses on the simulated benchmark stay below 0.7); else the full top_k search runs",
    )
    min_sample_dist_m: float = Field(3.0, ge=0, description="candidate pairs shorter than this do not vote")
    length_tolerance_m: float = Field(1.5, gt=0, description="a pair votes only if its two lengths differ less")
    vote_yaw_deg: float = Field(3.0, gt=0, le=30, description="yaw cell of the pose accumulator")
    vote_t_m: float = Field(3.0, gt=0, le=20, description="translation cell of the pose accumulator")
    peaks: int = Field(200, ge=1, le=5000, description="strongest accumulator cells examined (before deduplication)")
    min_votes: float = Field(2.0, ge=0, description="accumulator cells with fewer (soft) votes are not examined")
    max_refit_attempts: int = Field(
        40,
        ge=1,
        le=1000,
        description="accumulator peaks refitted at most (bounds the time when many peaks collapse onto the same poses)",
    )
    refits: int = Field(4, ge=0, le=20, description="Kabsch refits of a peak on its candidate inliers")
    max_hypotheses: int = Field(32, ge=1, le=64, description="distinct hypotheses verified densely")
    distinct_m: float = Field(2.0, gt=0, description="hypotheses closer than this and distinct_deg are one")
    distinct_deg: float = Field(2.0, gt=0, description="see distinct_m")
    min_hypothesis_inliers: int = Field(
        6, ge=2, description="hypotheses with fewer distinct inlier keypoints are not verified"
    )
    box_hypotheses: int = Field(
        8,
        ge=0,
        le=64,
        description="distinct poses proposed by the boxes both cars detected, verified densely beside the "
        "keypoint hypotheses (0: off); at 70-100 m the descriptors rarely agree but the cars do",
    )
    box_min_pairs: int = Field(3, ge=2, description="a box hypothesis needs this many peer boxes on ego boxes")
    box_seed_gate_m: float = Field(
        4.0, gt=0, description="pairing gate of a box seed (its yaw is only the two headings' difference)"
    )
    box_gate_m: float = Field(2.0, gt=0, description="pairing gate after the seed's Kabsch refit")
    box_heading_tol_deg: float = Field(
        20.0,
        gt=0,
        le=90,
        description="two boxes pair only if their headings agree within this, modulo 180 degrees (a detector may "
        "report a car backwards); rows of parked cars otherwise pair many boxes at wrong poses",
    )
    box_size_tol_m: float = Field(
        1.0, gt=0, description="... and their footprints (length, width) differ by less than this"
    )
    box_sigma_m: float = Field(
        0.7,
        gt=0,
        description="box poses are ranked by sum exp(-d^2 / 2 sigma^2) over the pairs (a tight fit of a few cars "
        "beats a loose fit of many); about twice a detector's centre noise at 100 m",
    )
    box_max: int = Field(40, ge=2, le=200, description="boxes per car used, nearest the sensor first (bounds the work)")
    box_weight: float = Field(
        0.015,
        ge=0,
        description="score added per peer box landing on an ego box (within box_gate_m) under a "
        "hypothesis: the cars both detected help rank the poses",
    )
    box_confirm_pairs: int = Field(
        3, ge=0, description="a pose the dense margin cannot settle is accepted when this many boxes pair (0: off)"
    )
    box_confirm_margin: int = Field(2, ge=1, description="... this many more than under any distinct hypothesis ...")
    box_confirm_ratio: float = Field(
        1.5,
        ge=1,
        description="... and this many times as many (calibrated on the simulated seeds 2024 and 777: no "
        "wrong success; benchmarks/acquisition_range.py, docs/acquisition.md)",
    )
    merge_within_m: float = Field(
        4.0,
        gt=0,
        description="a rival this close to the best (and merge_within_deg) is refined fully: it may be the same pose",
    )
    merge_within_deg: float = Field(4.0, gt=0, description="see merge_within_m")
    merge_checks: int = Field(2, ge=0, le=8, description="such rivals refined at most per frame (0: off)")
    coarse_points: int = Field(400, ge=50, description="peer pixels of the coarse verification refinement")
    coarse_gates_m: tuple[float, ...] = Field((2.0, 1.0), description="gates of the coarse verification")
    coarse_iters_per_gate: int = Field(2, ge=1, le=20)
    finalists: int = Field(2, ge=1, le=64, description="best coarse hypotheses refined fully (refine config)")
    covisible_m: float = Field(
        2.0,
        gt=0,
        description="a peer pixel is co-visible when it lands within this of an "
        "ego lit pixel; relative fitness = fitness / co-visible fraction",
    )
    score: Literal["fitness", "relative", "blend"] = Field(
        "fitness", description="ranks hypotheses: dense overlap, relative fitness, or relative x sqrt(fitness)"
    )
    min_margin: float = Field(1.1, ge=1, description="the best score must exceed the runner-up's by this factor")
    runner_up_floor: float = Field(
        0.05,
        ge=0.001,
        le=1,
        description="the runner-up's score is taken as at least "
        "this (a wrong pose's dense overlap on the simulated pairs: 0.05-0.3), also when "
        "there is no runner-up: a lone weak hypothesis has no margin",
    )
    min_evidence: float = Field(
        0.65,
        ge=0,
        description="success needs margin x relative fitness >= this: a pose must both stand out from "
        "the runner-up and explain the structure the two images can share (calibrated on the 200-pair simulated "
        "benchmark, seed 2024: no wrong success; benchmarks/acquisition_range.py)",
    )
    min_relative_fitness: float = Field(
        0.0,
        ge=0,
        le=1,
        description="success needs relative fitness >= this (replaces success.min_refine_fitness in multi mode)",
    )
    min_fitness: float = Field(0.0, ge=0, le=1, description="absolute dense-overlap floor in multi mode")
    stage2_required: bool = Field(
        True,
        description="multi mode: False lets a densely verified pose succeed when "
        "stage 2 cannot verify it (no common boxes at long range); a box correction beyond "
        "box.max_correction_* still fails",
    )
    stage2_waiver_evidence: float | None = Field(
        1.0,
        ge=0,
        description="multi mode, the search everywhere (not inside a prior's window, whose fewer rivals inflate the "
        "margin): a pose whose dense evidence (margin x relative fitness) reaches this succeeds when some boxes "
        "pair under it but too few of their corners agree for stage 2 (too_few_inliers_box); no_box_overlap is "
        "never waived (two wrong successes, one 42 m off, on seeds 9001 and 55555: docs/acquisition.md, Sessions "
        "11-12); a box correction beyond box.max_correction_* still fails. 1.0 = first_pass_evidence. "
        "None: stage 2 always vetoes",
    )


class CovarianceConfig(_Frozen):
    """3x3 covariance of (yaw rad, tx m, ty m) from the refinement's point-to-line normal equations (see
    bb_align.engine.covariance)."""

    enabled: bool = True
    inflation: float = Field(
        450.0,
        gt=0,
        description="variance factor for correlated neighbouring pixels and model "
        "error, calibrated on seeded simulated pairs (benchmarks/acquisition_range.py)",
    )
    max_sigma_m: float = Field(
        1.0,
        gt=0,
        description="refuse a pose whose 1-sigma translation along its worst "
        "direction exceeds this (degenerate scene, e.g. a straight corridor)",
    )
    max_sigma_deg: float = Field(1.0, gt=0, description="refuse a pose whose 1-sigma yaw exceeds this")
    min_residual_sigma_m: float = Field(
        0.1,
        gt=0,
        description="floor of the point-to-line residual sigma (pixel "
        "centres are quantised: 0.4 m / sqrt(12) = 0.12 m for a uniform offset)",
    )


class LandscapeConfig(_Frozen):
    """The pose landscape around an answer (bb_align.engine.landscape): a grid of poses scored by the likelihood
    field of the ego image; its peak is the answer and its spread the answer's uncertainty."""

    enabled: bool = Field(True, description="judge the answer on the landscape (False: the refinement's curvature)")
    half_width_m: float = Field(3.2, gt=0, le=20, description="the grid reaches this far each way in x and y, metres")
    half_yaw_deg: float = Field(1.5, gt=0, le=20, description="... and this far in yaw, degrees")
    step_m: float = Field(0.2, gt=0, description="grid step in x and y, metres (half a 0.4 m pixel)")
    step_deg: float = Field(0.1, gt=0, description="grid step in yaw, degrees")
    fine_cells: int = Field(
        5, ge=1, le=20, description="the fine grid reaches this many steps each way of the coarse peak"
    )
    sigma_m: float = Field(0.4, gt=0, description="width of the ego image's likelihood field, metres")
    wide_sigma_m: float = Field(
        2.0,
        gt=0,
        description="the score is the narrow field's sum over this wide field's, at the peer's pixels: how well the "
        "structure near ego structure lies on it, not how much lands near it (a pose moved along a street towards "
        "the denser near field would otherwise gain)",
    )
    max_points: int = Field(1000, ge=50, description="peer pixels scored (seeded subset of the refinement's sample)")
    effective_points: float = Field(
        100.0,
        gt=0,
        description="how many independent measurements the peer's pixels are worth: p(T) ~ exp(effective_points x "
        "(S(T) - S_max)). 100: the true pose within the chi2(3) 99 % bound for 98.5 % of the simulated pairs at "
        "40-100 m (seed 2024); checked on the real KITTI 00 pairs at 73-80 m: 100 % (docs/real_pairs.md)",
    )
    refinement_d2: float | None = Field(
        11.345,
        gt=0,
        description="when the refined pose lies beyond this squared Mahalanobis distance of the landscape's answer "
        "(chi2(3) 99 %), the two disagree and both count as modes of equal weight (None: the landscape alone)",
    )
    max_edge_mass: float = Field(
        0.05, gt=0, le=1, description="more probability than this on the grid's faces: no bounded peak (a corridor)"
    )


class FreeSpaceConfig(_Frozen):
    """The free-space check of an acquired pose (bb_align.engine.freespace): the share of one car's tall structure
    that lands, under the pose, where the other car's LiDAR saw through (both directions; the larger counts)."""

    enabled: bool = Field(True, description="compute the conflict of the acquired poses (multi mode)")
    bin_deg: float = Field(0.5, gt=0, le=10, description="azimuth bin of the first-hit ranges")
    spread_bins: int = Field(
        1,
        ge=0,
        le=10,
        description="a pixel is free only if nearer than the first hit of its bin and of this many bins either side",
    )
    min_range_m: float = Field(
        3.0, ge=0, description="lit pixels nearer than this (the car itself) do not stop the beams"
    )
    margin_m: float = Field(2.0, ge=0, description="free space ends this far before the first hit")
    open_m: float = Field(
        0.0,
        ge=0,
        description="an azimuth with no hit is free up to this range (0: unknown; no return may mean blocked)",
    )
    tall_m: float = Field(1.5, ge=0, description="only structure at least this tall above the ground is checked")
    max_points: int = Field(3000, ge=10, le=100000, description="tall pixels sampled per frame (seeded)")
    max_conflict: float = Field(
        0.10,
        ge=0,
        le=1,
        description="an acquired pose whose conflict exceeds this is refused (free_space_conflict); 1: never. Right "
        "poses on thirteen simulated seeds: at most 0.067 (99 % under 0.045); the aliases that won the margin once "
        "their rivals were ruled out: 0.074-0.146 (docs/acquisition.md)",
    )
    rival_conflict: float = Field(
        0.15,
        ge=0,
        le=1,
        description="a hypothesis whose conflict exceeds this is no rival of the best (neither in the margin nor in "
        "the boxes' confirmation): the two LiDARs' free space rules it out. 1: every distinct hypothesis is a rival. "
        "Gross aliases: median 0.20",
    )
    ruled_out_first: bool = Field(
        True,
        description="a best hypothesis above rival_conflict gives way: the hypotheses the free space rules out are "
        "dropped and the best of the others is refined fully and judged (False: the ruled-out best is refused). At "
        "70-100 m an alias laying both cars' near fields over each other often outscores the truth",
    )
    alias_conflict: float | None = Field(
        0.045,
        ge=0,
        le=1,
        description="a best hypothesis above this conflict is ruled out as an alias (as above rival_conflict) when a "
        "distinct one with some overlap lies within gave_way_max_conflict: the free space prefers that one. Right "
        "poses: 99 % of the simulated ones under 0.045, the real ones at most 0.03; the overlays of two cars' near "
        "fields on real streets 0.05-0.15. None: off",
    )
    gave_way_max_conflict: float = Field(
        0.03,
        ge=0,
        le=1,
        description="a pose chosen because better-scoring ones were ruled out must itself be this clear of the free "
        "space (else free_space_conflict). Measured on 22 simulated sets: right such poses at most 0.008, a gross "
        "alias 0.064",
    )


class TrackConfig(_Frozen):
    """Following a peer through time (bb_align.engine.tracker): process noise, gates, when to acquire again."""

    enabled: bool = Field(
        True, description="the service follows each peer (acquire once, then refine from the prediction)"
    )
    min_fitness: float = Field(
        0.05,
        ge=0,
        le=1,
        description="a tracking measurement whose refined overlap fitness is below this is no measurement (far "
        "pairs share little: the Mahalanobis gate, not a fixed overlap, judges the rest)",
    )

    odometry_drift_m_per_s: float = Field(
        0.15,
        gt=0,
        description="with odometry: how fast the two cars' odometry "
        "offset may drift, 1 sigma of a random walk per sqrt(s), metres",
    )
    odometry_drift_deg_per_s: float = Field(0.05, gt=0, description="likewise for its yaw, degrees")
    relative_accel_m_per_s2: float = Field(
        1.5,
        gt=0,
        description="without odometry: the relative pose's constant-velocity model, white acceleration noise, 1 sigma",
    )
    relative_accel_deg_per_s2: float = Field(3.0, gt=0, description="likewise for the relative yaw")
    initial_relative_speed_m_per_s: float = Field(
        10.0, gt=0, description="without odometry: 1 sigma of the relative velocity when a track starts"
    )
    initial_relative_yaw_rate_deg_per_s: float = Field(10.0, gt=0)
    gate_chi2: float = Field(
        16.27,
        gt=0,
        description="a measurement whose squared Mahalanobis distance to the "
        "prediction exceeds this is rejected (16.27: chi2, 3 dof, 99.9 %)",
    )
    max_rejects: int = Field(3, ge=1, description="this many rejected measurements in a row: the track is lost")
    max_sigma_m: float = Field(
        1.0,
        gt=0,
        description="a prediction whose worst-direction 1-sigma exceeds this "
        "triggers an acquisition, and is not a valid answer on its own",
    )
    prior: Literal["check", "gate"] = Field(
        "check",
        description="what a reported-pose prior does to a track's acquisitions. check: the acquisition searches "
        "every pose (multi-hypothesis, strongest at range) and its answer is refused when it lies farther from "
        "the prior than prior.max_translation_m / max_yaw_deg (an alias along a street, a lying report); gate: "
        "the prior gates the descriptor matches as in Aligner.align",
    )
    answer_sigma_m: float = Field(
        0.3,
        gt=0,
        description="a tracked answer is valid only while its worst-direction 1-sigma is within this (0.3: with an "
        "honest covariance a valid answer is off by more than 1 m with probability < 0.5 %, exp(-1 / (2 0.3^2)))",
    )
    answer_sigma_deg: float = Field(0.35, gt=0, description="likewise for its yaw 1-sigma, degrees")
    measurement_inflation: float = Field(
        16.0,
        gt=0,
        description="the tracking measurement's covariance is multiplied by this before fusion: successive "
        "refinements of nearly the same view share their errors, so they are not independent evidence (16, with "
        "odometry_drift_m_per_s 0.15 and answer_sigma_m 0.3: calibrated on swept sequences, docs/tracking.md)",
    )
    measurement_inflation_without_odometry: float = Field(
        2.0,
        gt=0,
        description="likewise for the constant-velocity model (no odometry): there the measurements carry the "
        "track alone, so they are trusted more (calibrated offline on the same sequences, docs/tracking.md)",
    )
    crosscheck_s: float = Field(
        5.0, ge=0, description="a full acquisition at least this often as a cross-check (0: never)"
    )
    boxes: bool = Field(
        True,
        description="fuse the boxes both cars detected as a second measurement of each tracked frame: their centres "
        "see along a street, where the refinement is weak at range (docs/tracking.md, Boxes)",
    )
    box_sigma_m: float = Field(
        1.3,
        gt=0,
        description="1 sigma of one paired box's centre in the box measurement (detection noise, corner order, "
        "what the two cars see of the car; calibrated on swept sequences like measurement_inflation)",
    )
    box_pair_gate_m: float = Field(
        2.0, gt=0, description="boxes pair when their centres are this close under the track's prediction"
    )
    box_min_pairs: int = Field(2, ge=2, description="fewer box pairs give no box measurement")
    box_min_inliers: int = Field(6, ge=3, description="corner inliers of the boxes' rigid fit, at least")
    box_agreement_chi2: float = Field(
        11.345,
        gt=0,
        description="a box measurement farther than this (squared Mahalanobis) from the frame's refinement is left "
        "out (mis-paired boxes): 11.345 = chi2, 3 dof, 99 %",
    )
    max_odometry_speed_m_s: float = Field(
        70.0, gt=0, description="an odometry step faster than this is a jump (relocalisation, reset): track lost"
    )
    max_odometry_yaw_rate_deg_s: float = Field(90.0, gt=0, description="likewise for its yaw rate")
    max_gap_s: float = Field(5.0, gt=0, description="a peer silent longer than this loses its track")
    support_ratio: float = Field(
        0.5,
        gt=0,
        le=1,
        description="a tracked frame's refinement validates an answer only when its fitness is at least this share "
        "of the track's recent valid evidence: a refinement caught in a local minimum near a wrong prediction (an "
        "odometry jump) finds a fraction of the overlap the right pose found",
    )
    evidence_sigmas: float = Field(
        3.0,
        gt=0,
        description="a tracked answer is valid only when this frame's own measurement, trusted to this many of its "
        "own sigmas, puts the truth within evidence_bound_m / _deg of the answer: the answer's distance from the "
        "measurement plus this many sigmas (worst direction of the peer's position; yaw)",
    )
    answer_own_measurement: bool = Field(
        True,
        description="with odometry, when the fused pose is not bounded by this frame's measurement but the "
        "measurement itself is (by the same rules), the answer is the measurement with its own covariance",
    )
    evidence_bound_m: float = Field(1.0, gt=0, description="see evidence_sigmas: the bound on position, metres")
    evidence_bound_deg: float = Field(1.0, gt=0, description="see evidence_sigmas: the bound on yaw, degrees")
    reacquire_s: float = Field(
        1.0,
        ge=0,
        description="a track that max_rejects frames in a row did not confirm on their own evidence runs a full "
        "acquisition, at most this often",
    )


class AlignConfig(_Frozen):
    bev: BevConfig = BevConfig()
    mim: MimConfig = MimConfig()
    features: FeatureConfig = FeatureConfig()
    match: MatchConfig = MatchConfig()
    ransac: RansacConfig = RansacConfig()
    prior: PriorConfig = PriorConfig()
    refine: RefineConfig = RefineConfig()
    box: BoxConfig = BoxConfig()
    success: SuccessRule = SuccessRule()
    confidence: ConfidenceConfig = ConfidenceConfig()
    acquire: AcquireConfig = AcquireConfig()
    covariance: CovarianceConfig = CovarianceConfig()
    free_space: FreeSpaceConfig = FreeSpaceConfig()
    landscape: LandscapeConfig = LandscapeConfig()
    track: TrackConfig = TrackConfig()
    min_points: int = Field(1000, ge=0, description="a cloud with fewer points is refused (too_few_points)")
    min_keypoints: int = Field(3, ge=2, description="a frame with fewer keypoints is refused (no_keypoints)")
    seed: int = Field(0, description="seeds every random choice (RANSAC samples, refinement subsets)")


def with_overrides(cfg: AlignConfig, overrides: list[str] | tuple[str, ...]) -> AlignConfig:
    """``cfg`` with ``section.key=JSON`` overrides applied (e.g. ``acquire.top_k=8``, ``mim.coarse_scales=0``), as
    the benchmarks' ``--set`` takes them; validated like any config (a bad name or value raises)."""
    data = cfg.model_dump()
    for o in overrides:
        key, sep, value = o.partition("=")
        section, dot, name = key.partition(".")
        if not (sep and dot) or section not in data or not isinstance(data[section], dict):
            raise ValueError(f"override {o!r}: expected section.key=JSON with a section of AlignConfig")
        data[section][name] = json.loads(value)
    return AlignConfig.model_validate(data)
