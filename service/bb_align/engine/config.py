"""The engine's settings (pydantic models), one section per step of the pipeline.

``USER_FACING`` lists the few a user tunes (image range and resolution, the acquisition mode, the prior's
tolerances, the success rule, the pose's uncertainty bounds, tracking, threads, seed): ``bb-align config --dump``
prints those, ``--dump --advanced`` every setting. The rest are calibrated together (docs/acquisition.md explains
each check and its threshold): change them only to re-run that calibration. Fixed numbers that are not settings
live as constants beside the code that uses them (``RETIRED`` lists the ones that used to be settings).
Each step of the pipeline is built once from its section (``Aligner.__init__``). The service's own settings (ports,
Zenoh, limits) live in ``bb_align.server.settings`` and embed an :class:`AlignConfig` (environment:
``BBALIGN_ALIGN__<SECTION>__<NAME>``); ``bb-align align --config FILE`` loads a saved one.
"""

from __future__ import annotations

import difflib
import json
import typing
from collections.abc import Mapping
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class BevConfig(_Frozen):
    """Bird's-eye-view height image (paper Eq. 4)."""

    range_m: float = Field(
        100.0,
        gt=0,
        le=250,
        description="half width R of the square image, metres (100 at 0.4 m: 500 x 500 px); pairs farther apart "
        "than about R share too little of their images; the MIM's cost grows with R squared",
    )
    resolution_m: float = Field(0.4, gt=0.01, le=5, description="cell size c, metres per pixel")
    mode: Literal["max_height", "slices"] = Field(
        "max_height", description="max_height: paper's max z per cell; slices: occupied z-slices (reference)"
    )
    ground_clearance_m: float = Field(0.3, ge=0, description="heights below this above the local ground map to 0")
    max_height_m: float = Field(12.0, gt=0, description="heights above the ground are clipped here")
    slice_m: float = Field(0.2, gt=0, description="slice thickness for mode='slices'")


class MimConfig(_Frozen):
    """Log-Gabor bank and Maximum Index Map (Eqs. 5-10)."""

    n_orient: int = Field(12, ge=4, le=36)
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

    max_keypoints: int = Field(400, ge=10, le=5000, description="strongest FAST responses kept per image")
    patch_px: int = Field(96, ge=24, description="descriptor window J")
    grid: int = Field(6, ge=2, description="cells per side l")
    merge_bins: bool = Field(True, description="True: 216-D (bins merged in pairs); False: 432-D")
    window_stride: int = Field(1, ge=1, le=4, description="sample every n-th pixel each way of the J x J window")
    threads: int = Field(2, ge=1, le=16, description="keypoint groups described in parallel (same result)")
    orientation_stride: int = Field(
        2,
        ge=1,
        le=4,
        description="sample every n-th pixel each way of the dominant-orientation disc (2: a quarter of the "
        "work, the same accuracy)",
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


class PriorConfig(_Frozen):
    """Optional prior pose (e.g. from the cars' reported GPS poses). In multi mode the pose must lie inside its
    window; when the search everywhere fails, the window is searched alone (only poses inside it hypothesised,
    verified and counted as rivals; the prior pose itself verified as one more), and a pose found there must be
    precise (max_sigma_m). In paper mode it gates the descriptor matches. Without a prior the engine searches every
    yaw and shift (the paper's setting)."""

    max_translation_m: float = Field(
        10.0, gt=0, description="how far the true pose may be from the prior, metres (x and y)"
    )
    sigma_m: float = Field(
        2.0,
        gt=0,
        description="the prior's own 1-sigma in x and y, metres (GNSS-grade: the field's sigma_t = 2 m): its "
        "density weighs each rival of the answer inside the prior's window",
    )
    sigma_deg: float = Field(2.0, gt=0, description="the prior's 1-sigma in yaw, degrees")
    max_yaw_deg: float = Field(10.0, gt=0, le=180, description="how far its yaw may be from the prior's, degrees")
    top_k: int = Field(4, ge=1, le=32, description="paper mode: descriptor candidates per peer keypoint gated")
    verify_prior_pose: bool = Field(True, description="multi mode: the prior pose is also verified as a hypothesis")
    max_sigma_m: float = Field(
        0.3,
        gt=0,
        description="multi mode, metres: a pose found inside the window alone is refused when its 1-sigma along its "
        "worst translation direction exceeds this (fewer rivals there, so the pose must be precise)",
    )


class RefineConfig(_Frozen):
    """Dense point-to-line ICP on the lit BV pixels after stage 1 (not in the paper; see bb_align.engine.refine)."""

    enabled: bool = True
    gates_m: tuple[float, ...] = Field((2.0, 1.0, 0.5, 0.4), description="correspondence gates, coarse to fine")
    iters_per_gate: int = Field(3, ge=1, le=50)
    min_pixel_value: int = Field(1, ge=1, le=255, description="pixels at or above this value take part")
    max_peer_points: int = Field(2000, ge=100, description="seeded random subset of the peer's lit pixels")
    max_correction_m: float = Field(2.0, gt=0, description="a refinement moving the pose farther (metres) is discarded")
    max_correction_deg: float = Field(3.0, gt=0, description="... or turning it more (degrees)")
    facing_min_cos: float = Field(
        0.5,
        ge=-1,
        le=1,
        description="a peer pixel pairs with an ego pixel only if their normals, each turned towards its own "
        "sensor, agree this well (cosine): two faces of one object between the cars are not one surface; -1: off",
    )
    min_points: int = Field(10, ge=3, description="fewer ego pixels, peer points or matches: no refinement")


class BoxConfig(_Frozen):
    """Stage 2: box-corner alignment."""

    apply: Literal["always", "auto"] = Field(
        "auto",
        description="always: T_2D = T_box @ T_bv (the paper). auto: stage 2 estimates T_box and counts Inliers_box "
        "for the success rule, but applies its correction only when the dense BV refinement did not run or was "
        "rejected (box corners from a noisy detector are less precise than the refined images), or when a correction "
        "over 0.5 m / 0.5 deg, refined again on the BV images, makes them agree better (a refinement stuck in a "
        "local optimum)",
    )
    pair_gate_m: float = Field(3.0, gt=0, description="peer/ego box centres closer than this may pair")
    ransac: RansacConfig = RansacConfig(
        inlier_threshold_m=0.8, min_sample_dist_m=1.0, max_iterations=500, min_iterations=256
    )
    max_correction_m: float = Field(4.0, gt=0, description="stage 2 may move stage 1 by at most this, metres")
    max_correction_deg: float = Field(6.0, gt=0, description="... and turn it by at most this, degrees")
    fuse: bool = Field(
        True,
        description="after stage 2 verified the pose, fuse the paired boxes as a second measurement "
        "of it, by information with the refined pose's covariance (not in the paper)",
    )
    fuse_sigma_m: float = Field(
        1.3, gt=0, description="1-sigma of one paired box centre, metres (as the tracker's track.box_sigma_m)"
    )
    fuse_disagreement_fails: bool = Field(
        True,
        description="when the boxes' measurement and the refined pose disagree (chi2(3) 99 %) the alignment fails "
        "(box_correction_too_large) instead of keeping the refined pose: two independent measurements contradict each "
        "other",
    )


class SuccessRule(_Frozen):
    """Paper rule: Inliers_bv > 25 and Inliers_box > 6."""

    min_inliers_bv: int = Field(25, ge=0, description="success needs inliers_bv > this")
    min_inliers_box: int = Field(6, ge=0, description="success needs inliers_box > this (when boxes are given)")
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
        "within the finest gate of an ego pixel (catches keypoint aliases along repetitive streets; paper mode)",
    )


class AcquireConfig(_Frozen):
    """Stage-1 acquisition (bb_align.engine.acquire). paper: one RANSAC fit on nearest-neighbour matches (the
    paper's Algorithm 1). multi: top-k descriptor candidates, distinct pose hypotheses by pairwise voting, each
    verified by the dense refinement, chosen with a margin over the runner-up."""

    mode: Literal["paper", "multi"] = Field(
        "multi",
        description="paper: one RANSAC fit on nearest-neighbour descriptor matches (the paper's Algorithm 1); multi: "
        "many pose hypotheses, each verified densely (engine.acquisition), for pairs up to about bev.range_m apart",
    )
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
    peaks: int = Field(200, ge=1, le=5000, description="strongest accumulator cells examined (before deduplication)")
    max_refit_attempts: int = Field(
        40,
        ge=1,
        le=1000,
        description="accumulator peaks refitted at most (bounds the time when many peaks collapse onto the same poses)",
    )
    max_hypotheses: int = Field(32, ge=1, le=64, description="distinct hypotheses verified densely")
    distinct_m: float = Field(2.0, gt=0, description="hypotheses closer than this and distinct_deg are one")
    distinct_deg: float = Field(2.0, gt=0, description="see distinct_m")
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
        description="... and this many times as many",
    )
    merge_checks: int = Field(2, ge=0, le=8, description="such rivals refined at most per frame (0: off)")
    finalists: int = Field(2, ge=1, le=64, description="best coarse hypotheses refined fully (refine config)")
    covisible_m: float = Field(
        2.0,
        gt=0,
        description="a peer pixel is co-visible when it lands within this of an "
        "ego lit pixel; relative fitness = fitness / co-visible fraction",
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
        "the runner-up and explain the structure the two images can share",
    )
    min_relative_fitness: float = Field(
        0.0,
        ge=0,
        le=1,
        description="success needs relative fitness >= this (replaces success.min_refine_fitness in multi mode)",
    )
    min_fitness: float = Field(0.0, ge=0, le=1, description="absolute dense-overlap floor in multi mode")
    near_m: float = Field(
        10.0,
        ge=0,
        description="two LiDARs closer than this (m) see nearly one scene: a pose placing the peer this near must "
        "reach near_min_fitness (0: off)",
    )
    near_min_fitness: float = Field(
        0.4,
        ge=0,
        le=1,
        description="the dense overlap a pose within near_m needs. Right poses within 10 m: 0.50-0.93 (real scans "
        "0.66-0.93); two far places' near fields laid over each other: 0.20-0.33 (docs/acquisition.md)",
    )
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
        "never waived (a pose with no box pairing has no support beside the images); a box correction beyond "
        "box.max_correction_* still fails. 1.0 = first_pass_evidence. None: stage 2 always vetoes",
    )


class CovarianceConfig(_Frozen):
    """3x3 covariance of (yaw rad, tx m, ty m) from the refinement's point-to-line normal equations (see
    bb_align.engine.covariance)."""

    enabled: bool = True
    inflation: float = Field(
        450.0,
        gt=0,
        description="variance factor for correlated neighbouring pixels and model error (calibrated so the true "
        "pose lies within the covariance's chi2(3) 99 % bound for almost every correct pair)",
    )
    min_residual_sigma_m: float = Field(
        0.1,
        gt=0,
        description="floor of the point-to-line residual sigma (pixel "
        "centres are quantised: 0.4 m / sqrt(12) = 0.12 m for a uniform offset)",
    )
    sweep_travel_m: float = Field(
        0.0,
        ge=0,
        le=10,
        description="1-sigma of how far each car travelled during a sweep its sender did not de-skew, metres (e.g. "
        "1.0: 10 m/s x 0.1 s): the shear this leaves in each image biases the pose without widening the landscape, "
        "so its effect at the answer is added to the covariance (engine.covariance.motion_covariance). 0 (the "
        "default): the senders de-skew (bb_align_client.deskew_sweep, encode_frame(velocity=...))",
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
    follow_peak: bool = Field(
        True,
        description="when the peak lies near the window's edge off its centre in x / y, move the window's translation "
        "onto it once (a refinement that stopped a few metres off along a street puts the peak, not a corridor, at "
        "the edge); the answer must still lie inside the first window",
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
        description="an acquired pose whose conflict (a share of tall structure, 0-1) exceeds this is refused "
        "(free_space_conflict); 1: never. Right poses stay under about 0.07, aliases that won the margin once their "
        "rivals were ruled out lie above",
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
        "distinct one with some overlap lies within gave_way_max_conflict: the free space prefers that one (right "
        "poses lie under it, overlays of two cars' near fields on real streets at 0.05-0.15). None: off",
    )
    gave_way_max_conflict: float = Field(
        0.03,
        ge=0,
        le=1,
        description="a pose chosen because better-scoring ones were ruled out must itself be this clear of the free "
        "space (else free_space_conflict)",
    )


class AnswerRule(_Frozen):
    """What ``success`` promises, for every answer (a single shot, a tracked frame; the CLI, the service,
    ``recover``): the truth lies within ``max_error_m`` (the peer's position) and ``max_error_deg`` (its yaw) of it
    with at least ``confidence``, by the answer's own covariance (a lower bound on that probability:
    engine.covariance.probability_within)."""

    max_error_m: float = Field(1.0, gt=0, description="the user's bound on a successful answer's position error, m")
    max_error_deg: float = Field(1.0, gt=0, description="... and on its yaw error, degrees")
    confidence: float = Field(
        0.95,
        gt=0,
        lt=1,
        description="an answer is successful only when its covariance puts the truth within max_error_m / _deg with "
        "at least this probability (README, What success promises)",
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
        "gate",
        description="what a reported-pose prior (GNSS) does to a track's acquisitions. gate: the acquisition searches "
        "inside the prior's window and its rivals are weighed by the prior, as Aligner.align(T_prior=...) does; "
        "check: it searches every pose and its answer is refused when it lies farther from the prior than "
        "prior.max_translation_m / max_yaw_deg",
    )
    measurement_inflation: float = Field(
        16.0,
        gt=0,
        description="the tracking measurement's covariance is multiplied by this before the filter fuses it (the "
        "filter only predicts): successive refinements of nearly the same view share their errors, so they are not "
        "independent evidence (16: calibrated on swept sequences, docs/history.md)",
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
    max_odometry_accel_m_s2: float | None = Field(
        10.0,
        gt=0,
        description="an odometry step off the car's recent motion (speed and yaw rate continued) by more than this "
        "acceleration allows (plus odometry_step_noise_m) is a jump: about 1 g, what a road car's tyres give at most "
        "(engine.odometry; real 10 Hz poses stay under half the bound, docs/tracking.md). None: no such check (a "
        "replay that turns its cars round in one frame)",
    )
    max_odometry_yaw_accel_deg_s2: float = Field(
        120.0, gt=0, description="likewise for the change of its yaw rate, deg/s^2"
    )
    odometry_step_noise_m: float = Field(
        0.25, ge=0, description="what an odometry step may be off its motion without any acceleration, metres"
    )
    odometry_step_noise_deg: float = Field(1.0, ge=0, description="... and degrees")
    max_unchecked_jump_m: float = Field(
        5.0,
        gt=0,
        description="after a gap so long that the odometry check could take a relocalisation larger than this for "
        "motion (at 10 Hz: about 0.9 s without a frame), the track is confirmed by the full method before it answers "
        "(dropped when that fails or disagrees). Each confirmation is an acquisition: 1.6 m (what a refinement "
        "reaches back, ~0.5 s gaps) cost the 8-peer soak 87 % of its answers; relocalisations of 1.6-5 m hidden in "
        "0.5-0.9 s gaps are not covered (docs/tracking.md, Odometry jumps)",
    )
    max_gap_s: float = Field(5.0, gt=0, description="a peer silent longer than this loses its track")
    support_ratio: float = Field(
        0.5,
        gt=0,
        le=1,
        description="a tracked frame's refinement validates an answer only when its fitness is at least this share "
        "of the track's recent valid evidence: a refinement caught in a local minimum near a wrong prediction (an "
        "odometry jump) finds a fraction of the overlap the right pose found",
    )
    landscape: bool = Field(
        True,
        description="a tracked frame's own evidence is the pose landscape around its refinement (as an acquisition's "
        "answer is judged; its covariance covers its error at range, the refinement's curvature does not)",
    )
    landscape_sigmas: float = Field(
        4.0,
        gt=0,
        description="a tracked frame's landscape reaches this many of the refinement's own worst-direction sigmas "
        "each way in x and y (the refinement's is the wider at range), at most landscape.half_width_m",
    )
    landscape_min_half_width_m: float = Field(
        1.6, gt=0, description="... and at least this far, metres (a near frame's landscape costs half the full one)"
    )
    evidence_window_s: float = Field(
        5.0,
        gt=0,
        le=10,
        description="with odometry, the frames of the last this many seconds whose own measurements agree are fused "
        "into the stream's evidence (engine.evidence), the answer of a tracked frame; an older frame's covariance "
        "grows by the odometry's drift since",
    )
    evidence_max_frames: int = Field(50, ge=1, le=100, description="... and at most this many frames")
    evidence_correlation: float = Field(
        0.6,
        ge=0,
        le=1,
        description="what two frames' errors share in the stream's evidence while both cars stay within "
        "evidence_same_place_m (the same buildings, the same aliasing): the mean product of their errors in units "
        "of their own covariances; n such frames count as n / (1 + rho (n - 1)) independent ones. 0.6: the largest "
        "measured on the real runs (all within 9 m) and the simulated sweeps of seed 101, rounded up (real KITTI 00 "
        "run 73-80 m: 0.52 in yaw); checked on the held-out sweeps (benchmarks/evidence_correlation.py, "
        "docs/tracking.md)",
    )
    evidence_correlation_far: float | None = Field(
        0.4,
        ge=0,
        le=1,
        description="... what they share once the cars have moved on and the images see other structure: the "
        "shared part decays from evidence_correlation to this over evidence_decorrelation_m beyond "
        "evidence_same_place_m (None: evidence_correlation wherever the cars go). 0.4: the largest product of a "
        "sequence's frames 20 m or more apart on seed 101, 0.32, rounded up (held out: 0.15); the real runs never "
        "move that far",
    )
    evidence_same_place_m: float = Field(
        10.0,
        ge=0,
        description="frames taken while both cars stay within this of where they were share evidence_correlation "
        "(metres, the larger of the two cars' moves by their odometry; the real runs, 0-9 m, lie within it)",
    )
    evidence_decorrelation_m: float = Field(
        10.0, gt=0, description="... beyond it, the shared part decays over this many metres"
    )
    evidence_agreement: float = Field(
        0.1,
        gt=0,
        le=1,
        description="two frames of the stream's evidence must agree within this share of their covariances (plus "
        "the odometry's drift between them), judged at gate_chi2: what they share cancels in their difference. "
        "Tight, as a window cut short only costs evidence: a peer whose odometry drifts 0.3 m a frame keeps two or "
        "three frames",
    )
    stream_coast_s: float = Field(
        1.0,
        ge=0,
        le=5,
        description="with odometry, a frame with no evidence of its own (its refinement failed or diverged, or "
        "a busy service did not measure it: its unmeasured_after_s) is answered from the stream's evidence when "
        "its newest frame is at most this old (seconds): their fusion carried to this frame by both cars' "
        "odometry, its covariance grown by their drift since, valid only when that keeps the answer rule's promise "
        "(source 'stream'; 0: never, the frame is refused). 1 s: ten frames at 10 Hz, chosen before measuring; "
        "checked on the swept sequences and crossings, 0 wrong (docs/tracking.md)",
    )
    reacquire_s: float = Field(
        1.0,
        ge=0,
        description="a track that max_rejects frames in a row did not confirm on their own evidence runs a full "
        "acquisition, at most this often",
    )


class StreamConfig(_Frozen):
    """Acquisition over a second of stream (bb_align.engine.stream_acquire): several frames of each car with their
    odometry, a pose must explain every frame."""

    first_answer: bool = Field(
        True,
        description="a tracker with no track whose frame alone gives no answer tries its recent frames together "
        "(with odometry)",
    )
    frames: int = Field(10, ge=2, le=50, description="... its last this many frames")
    window_s: float = Field(1.0, gt=0, le=10, description="... within this many seconds")
    min_frames: int = Field(5, ge=2, le=50, description="... at least this many of them")
    every_s: float = Field(
        1.0, ge=0, description="... at most this often (seconds): it costs about a second on one core at range"
    )

    search_frames: int = Field(
        3, ge=1, le=20, description="the full search runs on this many of the frames (the last, then spread)"
    )
    max_hypotheses: int = Field(
        6, ge=1, le=50, description="at most this many of the poses the searches verified are explained by every frame"
    )
    min_bounded_share: float = Field(
        0.5,
        gt=0,
        le=1,
        description="a hypothesis is an answer only when at least this share of the frames bound it (their pose "
        "landscape has a peak) and agree on it (as the stream's evidence keeps frames)",
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
    acquire: AcquireConfig = AcquireConfig()
    covariance: CovarianceConfig = CovarianceConfig()
    stream: StreamConfig = StreamConfig()
    free_space: FreeSpaceConfig = FreeSpaceConfig()
    landscape: LandscapeConfig = LandscapeConfig()
    track: TrackConfig = TrackConfig()
    answer: AnswerRule = AnswerRule()
    min_points: int = Field(1000, ge=0, description="a cloud with fewer points is refused (too_few_points)")
    min_keypoints: int = Field(3, ge=2, description="a frame with fewer keypoints is refused (no_keypoints)")
    seed: int = Field(0, description="seeds every random choice (RANSAC samples, refinement subsets)")

    @model_validator(mode="before")
    @classmethod
    def _without_retired(cls, data):
        return without_retired(data)

    def dump(self, advanced: bool = False) -> dict:
        """The settings as a JSON-able dict: the ``USER_FACING`` ones (``advanced``: all of them)."""
        data = self.model_dump(mode="json")
        if advanced:
            return data
        out: dict = {}
        for path in USER_FACING:
            *sections, name = path.split(".")
            src, dst = data, out
            for sec in sections:
                src, dst = src[sec], dst.setdefault(sec, {})
            dst[name] = src[name]
        return out


# The settings a user tunes; the others are calibrated together (module docstring). Units are in each description.
USER_FACING = (
    "bev.range_m",
    "bev.resolution_m",
    "features.max_keypoints",
    "acquire.mode",
    "acquire.top_k",
    "prior.max_translation_m",
    "prior.max_yaw_deg",
    "prior.sigma_m",
    "prior.sigma_deg",
    "success.min_inliers_bv",
    "success.min_inliers_box",
    "success.require_boxes",
    "track.enabled",
    "answer.max_error_m",
    "answer.max_error_deg",
    "answer.confidence",
    "acquire.threads",
    "mim.threads",
    "features.threads",
    "match.threads",
    "seed",
)

# Former settings, with the value the engine now uses (a constant beside its code, or the only option left). A saved
# config naming one with that value still loads; any other value is refused, naming the setting.
RETIRED: dict[str, object] = {
    "bev.ground_cell_m": 2.0,  # bev.GROUND_CELL_M
    "bev.ground_window_cells": 3,  # bev.GROUND_WINDOW_CELLS
    "mim.n_scales": 4,  # loggabor.N_SCALES (and the bank's shape below)
    "mim.min_wavelength_px": 3.0,
    "mim.mult": 1.6,
    "mim.sigma_on_f": 0.75,
    "mim.lowpass_cutoff": 0.45,
    "mim.lowpass_order": 15,
    "features.fast_threshold": 10,  # keypoints.FAST_THRESHOLD
    "features.reference_orientation_offsets": (0, -1, 1),  # frame.REFERENCE_ORIENTATION_OFFSETS
    "ransac.refits": 3,  # ransac.REFITS
    "ransac.ambiguity_hypotheses": 1024,  # ransac.AMBIGUITY_HYPOTHESES
    "box.ransac.refits": 3,
    "box.ransac.ambiguity_hypotheses": 1024,
    "refine.step_relaxation": 2.0,  # refine.STEP_RELAXATION and the ICP's other constants
    "refine.point_weight": 0.1,
    "refine.huber_fraction": 0.25,
    "refine.normal_neighbours": 8,
    "refine.peer_normal_px": 2,
    "refine.converged_rad": 2e-5,
    "refine.converged_m": 0.002,
    "box.recheck_m": 0.5,  # pipeline.RECHECK_M, RECHECK_DEG, RECHECK_MIN_GAIN, FUSE_MIN_PAIRS, FUSE_CHI2
    "box.recheck_deg": 0.5,
    "box.recheck_min_gain": 0.01,
    "box.fuse_min_pairs": 2,
    "box.fuse_chi2": 11.345,
    "success.strong_inliers_bv": None,  # removed: never used
    "confidence.bv_inlier_scale": 40.0,  # verdict.BV_INLIER_SCALE and the confidence's other constants
    "confidence.box_inlier_scale": 8.0,
    "confidence.fitness_span": 0.2,
    "confidence.cap_stage1_failed": 0.1,
    "confidence.cap_stage2_failed": 0.5,
    "acquire.score": "fitness",  # removed: the dense score is the overlap fitness
    "acquire.vote_yaw_deg": 3.0,  # acquisition.hypotheses.VOTE_YAW_DEG and the vote's other constants
    "acquire.vote_t_m": 3.0,
    "acquire.min_votes": 2.0,
    "acquire.length_tolerance_m": 1.5,
    "acquire.refits": 4,
    "acquire.min_hypothesis_inliers": 6,
    "acquire.coarse_points": 400,  # acquisition.verification.COARSE_POINTS, COARSE_GATES_M, ...
    "acquire.coarse_gates_m": (2.0, 1.0),
    "acquire.coarse_iters_per_gate": 2,
    "acquire.merge_within_m": 4.0,  # acquisition.verification.MERGE_WITHIN_M, MERGE_WITHIN_DEG
    "acquire.merge_within_deg": 4.0,
    "covariance.max_sigma_m": 1.0,  # replaced by the answer rule (answer.max_error_m, max_error_deg, confidence)
    "covariance.max_sigma_deg": 1.0,
    "track.evidence_sigmas": 3.0,  # replaced by the answer rule (answer.*) on the stream's evidence
    "track.evidence_bound_m": 1.0,
    "track.evidence_bound_deg": 1.0,
    "track.answer_sigma_m": 0.3,
    "track.answer_sigma_deg": 0.35,
    "track.answer_own_measurement": True,
}


def _same(given, value) -> bool:
    if isinstance(given, list | tuple) and isinstance(value, tuple):
        return len(given) == len(value) and all(_same(g, v) for g, v in zip(given, value, strict=True))
    return given == value and isinstance(given, bool) == isinstance(value, bool)  # True is not 1.0


def without_retired(data):
    """``data`` (a config as a dict) without the ``RETIRED`` settings it names at their value; a retired setting at
    another value raises ValueError naming it (one line). Sections given as models are left as they are."""
    if not isinstance(data, dict):
        return data
    data = dict(data)
    for path, value in RETIRED.items():
        *sections, name = path.split(".")
        parents, node = [], data
        for sec in sections:
            parents.append((node, sec))
            node = node.get(sec) if isinstance(node, dict) else None
        if not isinstance(node, dict) or name not in node:
            continue
        if not _same(node[name], value):
            raise ValueError(
                f"{path} is no longer a setting (the engine uses {value!r}, a constant); remove it from the config"
            )
        # Copy the dicts on the path (the caller's stay as they were), then drop the setting.
        for parent, sec in parents:
            parent[sec] = dict(parent[sec])
        node = data
        for sec in sections:
            node = node[sec]
        del node[name]
    if data.get("confidence") == {}:  # a section whose settings all retired
        del data["confidence"]
    return data


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


def _field_names_at(model: type[BaseModel], loc: tuple) -> list[str]:
    """The field names of the (sub)model that holds the last element of ``loc`` ([] if the path leaves models)."""
    for part in loc[:-1]:
        field = model.model_fields.get(str(part))
        if field is None:
            return []
        kinds = [field.annotation, *typing.get_args(field.annotation)]
        model = next((k for k in kinds if isinstance(k, type) and issubclass(k, BaseModel)), None)
        if model is None:
            return []
    return list(model.model_fields)


def nearest_setting(model: type[BaseModel], loc: tuple) -> tuple | None:
    """The valid setting nearest in spelling to the unknown one at ``loc`` (same section), e.g. ('bev', 'range_m')
    for ('bev', 'range_mm'); None when nothing is close."""
    close = difflib.get_close_matches(str(loc[-1]), _field_names_at(model, loc), n=1, cutoff=0.6)
    return (*loc[:-1], close[0]) if close else None


def describe_errors(
    error: ValidationError, model: type[BaseModel], env_prefix: str = "", environ: Mapping[str, str] | None = None
) -> str:
    """A pydantic error in one line: each wrong setting with what it must be, an unknown one with the nearest valid
    name ("did you mean"). With ``env_prefix``, a setting that came from ``environ`` is named as its variable
    (``BBALIGN_ALIGN__BEV__RANGE_MM``: nested sections joined by ``__``), its nearest valid one too."""
    env = {k.upper() for k in (environ or {})}
    parts = []
    for err in error.errors():
        loc = tuple(err["loc"])
        if not loc and err["type"] == "value_error":  # a retired setting (RETIRED): the message names it
            parts.append(err["msg"].removeprefix("Value error, "))
            continue
        from_env = bool(env_prefix) and _env_name(env_prefix, loc) in env

        def name(path: tuple, from_env: bool = from_env) -> str:
            return _env_name(env_prefix, path) if from_env else ".".join(str(p) for p in path) or "(top level)"

        if err["type"] == "extra_forbidden" and loc:
            near = nearest_setting(model, loc)
            parts.append(f"{name(loc)}: no such setting" + (f" (did you mean {name(near)}?)" if near else ""))
            continue
        got = "" if err["type"] in ("missing", "json_invalid") else f" (got {err.get('input')!r})"
        parts.append(f"{name(loc)}: {err['msg']}{got}")
    return "; ".join(parts)


def _env_name(prefix: str, loc: tuple) -> str:
    return prefix + "__".join(str(p) for p in loc).upper()
