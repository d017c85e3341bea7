"""The two-stage BB-Align pipeline (paper Algorithm 1).

    aligner = Aligner()
    ego = aligner.prepare(make_bev(pts_ego), boxes_ego)     # once per ego frame (cache it)
    peer = aligner.prepare(make_bev(pts_peer), boxes_peer)  # per peer frame
    result = aligner.align(ego, peer)                       # result.T_ego_peer maps peer points into ego

``prepare`` runs lines 6-8 (MIM, keypoints, descriptors) for one car; ``align`` runs lines 9-17.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from threadpoolctl import ThreadpoolController

from .bev import BevImage, make_bev
from .boxes import align_boxes, as_boxes
from .config import AlignConfig, FeatureConfig
from .descriptors import bvft_descriptors, flip_180, keypoint_orientations
from .geometry import se2, se2_params, se3_from_se2
from .keypoints import detect_keypoints
from .loggabor import maximum_index_map
from .matching import match_descriptors, match_with_prior
from .parallel import run_parts
from .ransac import rigid_ransac
from .refine import BevCloud, Refinement, bev_cloud, bev_points, refine_icp
from .result import AlignResult, FailureReason


@dataclass
class PreparedFrame:
    """One car's frame with its engine features computed (reusable against many other frames)."""

    bev: BevImage
    boxes: np.ndarray  # (K, 7) [x, y, z, l, w, h, yaw], sensor frame
    keypoints_rc: np.ndarray  # (K, 2) pixels (row, col)
    keypoints_xy: np.ndarray  # (K, 2) metres in the sensor frame
    descriptors: np.ndarray  # (K, D)
    descriptors_flipped: np.ndarray  # (K, D) the same patches rotated by 180 deg
    orientations: np.ndarray | None = None  # (K,) dominant MIM orientation of each keypoint (1..No, 0: none)
    mim: np.ndarray | None = None  # kept for plots when keep_maps=True
    num_points: int | None = None  # raw cloud size when known
    timings_ms: dict[str, float] = field(default_factory=dict)
    _maps: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)  # (MIM, max amplitude)
    _cloud: BevCloud | None = field(default=None, repr=False)
    _reference: np.ndarray | None = field(default=None, repr=False)

    def reference_descriptors(self, features: FeatureConfig, n_orient: int) -> np.ndarray:
        """What this frame offers when it is the side matched against (the ego frame): for each orientation
        offset in ``features.reference_orientation_offsets`` the descriptors and their 180-degree copies,
        (2 x offsets x K, D); row i describes keypoint i % K. Built on first use (an ego frame pays it once)."""
        if self._reference is None:
            def describe(offset: int) -> list[np.ndarray]:
                if offset == 0:
                    return [self.descriptors, self.descriptors_flipped]
                d = bvft_descriptors(*self._maps, self.keypoints_rc, features, n_orient, orientation_offset=offset,
                                     orientations=self.orientations)
                return [d, flip_180(d, features)]

            self._reference = np.concatenate(sum(run_parts(describe, features.reference_orientation_offsets), []))
        return self._reference

    def cloud(self, min_value: int = 1) -> BevCloud:
        """Lit pixels with normals and their index image (built on first use: an ego frame pays it once)."""
        if self._cloud is None:
            self._cloud = bev_cloud(self.bev, min_value=min_value)
        return self._cloud

    @property
    def lit_pixels(self) -> int:
        return int(np.count_nonzero(self.bev.image))


@lru_cache(maxsize=1)
def _blas_controller() -> ThreadpoolController:
    return ThreadpoolController()


def _single_threaded_blas():
    """The engine's matrix products are small; OpenBLAS worker threads would only spin after each one and steal
    the CPU from the parallel MIM threads and the service's workers (measured: MIM 62 ms instead of 40 ms)."""
    return _blas_controller().limit(limits=1, user_api="blas")


@contextmanager
def _timed(timings: dict[str, float], name: str):
    t0 = time.perf_counter()
    yield
    timings[name] = timings.get(name, 0.0) + (time.perf_counter() - t0) * 1e3


class Aligner:
    """Stateless apart from its configuration; safe to share between threads."""

    def __init__(self, config: AlignConfig | None = None):
        self.config = config or AlignConfig()

    # ---- Algorithm 1, lines 6-8: per car -------------------------------------------------------------
    def prepare(self, frame: BevImage | np.ndarray, boxes=None, *, keep_maps: bool = False) -> PreparedFrame:
        """A BV image (or a raw (N, 3+) cloud, made into one with config.bev) and its boxes -> features."""
        with _single_threaded_blas():
            return self._prepare(frame, boxes, keep_maps)

    def _prepare(self, frame: BevImage | np.ndarray, boxes, keep_maps: bool) -> PreparedFrame:
        cfg = self.config
        timings: dict[str, float] = {}
        num_points = None
        if not isinstance(frame, BevImage):
            pts = np.asarray(frame)
            num_points = int(len(pts))
            with _timed(timings, "bev"):
                frame = make_bev(pts, cfg.bev)
        bev = self._at_resolution(frame)
        with _timed(timings, "mim"):
            mim, amp = maximum_index_map(bev.image, cfg.mim)
        with _timed(timings, "keypoints"):
            rc = detect_keypoints(bev.image, cfg.features)
        with _timed(timings, "descriptors"):
            def describe(part: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                m = keypoint_orientations(mim, amp, part, cfg.features, cfg.mim.n_orient)
                return m, bvft_descriptors(mim, amp, part, cfg.features, cfg.mim.n_orient, orientations=m)

            parts = [p for p in np.array_split(rc, cfg.features.threads) if len(p)] or [rc]
            described = run_parts(describe, parts)
            orientations = np.concatenate([m for m, _ in described])
            desc = np.concatenate([d for _, d in described])
            desc_flip = flip_180(desc, cfg.features)
        return PreparedFrame(
            bev=bev,
            boxes=as_boxes(boxes),
            keypoints_rc=rc,
            keypoints_xy=bev.pixel_to_metre(rc),
            descriptors=desc,
            descriptors_flipped=desc_flip,
            orientations=orientations,
            mim=mim if keep_maps else None,
            num_points=num_points,
            timings_ms=timings,
            _maps=(mim, amp),
        )

    def warm(self, prepared: PreparedFrame) -> PreparedFrame:
        """Build now what a frame needs as the matched-against (ego) side: the reference descriptors and the
        lit-pixel cloud of the refinement. Otherwise the first alignment against it pays for them."""
        with _single_threaded_blas():
            prepared.reference_descriptors(self.config.features, self.config.mim.n_orient)
            if self.config.refine.enabled:
                prepared.cloud(self.config.refine.min_pixel_value)
        return prepared

    def warm_up(self) -> None:
        """Compile the engine's loops and build its per-image-size caches now, on a synthetic image of the configured
        size aligned with itself: the first real frame then runs at full speed (the compiled loops are cached on
        disk after a machine's first run, so this takes well under a second from then on)."""
        b = self.config.bev
        n = max(32, int(round(2 * b.range_m / b.resolution_m)))
        rng = np.random.default_rng(0)
        image = np.zeros((n, n), np.uint8)
        for _ in range(60):
            p0, p1 = rng.integers(0, n, 2), rng.integers(0, n, 2)
            cv2.line(image, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), int(rng.integers(60, 255)), 2)
        frame = self.warm(self.prepare(BevImage(image, b.resolution_m, n * b.resolution_m / 2, b.mode,
                                                b.ground_clearance_m, b.max_height_m)))
        self.align(frame, frame)

    def _at_resolution(self, bev: BevImage) -> BevImage:
        """Descriptors are in pixels: bring a peer image made at another resolution to the configured one."""
        want = self.config.bev.resolution_m
        if abs(bev.resolution_m - want) < 1e-9:
            return bev
        scale = bev.resolution_m / want
        h, w = bev.shape
        size = (max(1, int(round(w * scale))), max(1, int(round(h * scale))))
        interp = cv2.INTER_NEAREST if scale > 1 else cv2.INTER_AREA
        image = cv2.resize(bev.image, size, interpolation=interp)
        return BevImage(image, want, image.shape[0] * want / 2, bev.mode, bev.ground_clearance_m, bev.max_height_m)

    # ---- Algorithm 1, lines 9-17: pair ------------------------------------------------------------------
    def align(self, ego: PreparedFrame, peer: PreparedFrame, *, tz: float = 0.0, roll: float = 0.0,
              pitch: float = 0.0, T_prior: np.ndarray | None = None) -> AlignResult:
        """T_ego_peer from prepared frames. tz, roll, pitch (metres, radians) are Eq. 1's constants.

        ``T_prior`` (3x3 or 4x4 ego <- peer, e.g. from both cars' reported poses) is optional: when given,
        descriptor matches are gated by it (config.prior); without it every yaw and shift is searched."""
        with _single_threaded_blas():
            return self._align(ego, peer, tz, roll, pitch, T_prior)

    def _align(self, ego: PreparedFrame, peer: PreparedFrame, tz: float, roll: float, pitch: float,
               T_prior: np.ndarray | None) -> AlignResult:
        cfg = self.config
        timings: dict[str, float] = {}
        result = AlignResult(success=False, T_ego_peer=np.eye(4), T_bv=np.eye(3), T_box=np.eye(3),
                             timings_ms=timings)

        def finish(reason: FailureReason | None) -> AlignResult:
            T_2d = result.T_box @ result.T_bv
            result.T_ego_peer = se3_from_se2(T_2d, tz=tz, roll=roll, pitch=pitch)
            result.reason = None if reason is None else reason.value
            result.success = reason is None
            result.confidence = self._confidence(result, ambiguity)
            timings["align_total"] = sum(v for k, v in timings.items() if k != "align_total")
            return result

        ambiguity = 1.0
        # Guards: nothing to match.
        for f in (ego, peer):
            if f.num_points is not None and f.num_points < cfg.min_points:
                return finish(FailureReason.too_few_points)
            if f.lit_pixels == 0:
                return finish(FailureReason.empty_image)
            if len(f.keypoints_rc) < 3:
                return finish(FailureReason.no_keypoints)

        # Lines 9-10: match peer descriptors against the ego's (and their 180-degree copies).
        with _timed(timings, "matching"):
            desc_ego = ego.reference_descriptors(cfg.features, cfg.mim.n_orient)
            n_ego = len(ego.descriptors)
            if T_prior is None:
                i_peer, i_ego = match_descriptors(peer.descriptors, desc_ego, mutual=cfg.match.mutual,
                                                  ratio=cfg.match.ratio, threads=cfg.match.threads)
            else:
                yaw, tx, ty = se2_params(T_prior)
                xy_ego = np.tile(ego.keypoints_xy, (len(desc_ego) // n_ego, 1))  # row i is keypoint i % K
                i_peer, i_ego = match_with_prior(
                    peer.descriptors, desc_ego, peer.keypoints_xy, xy_ego,
                    se2(yaw, tx, ty), max_translation=cfg.prior.max_translation_m,
                    max_yaw_rad=np.radians(cfg.prior.max_yaw_deg), top_k=cfg.prior.top_k,
                    threads=cfg.match.threads)
                result.notes.append("matches gated by the prior pose")
            i_ego = i_ego % n_ego
            pts_peer = peer.keypoints_xy[i_peer]
            pts_ego = ego.keypoints_xy[i_ego]
        result.matches_bv = int(len(i_peer))
        if len(i_peer) < 2:
            return finish(FailureReason.too_few_matches)

        # Line 11: T_bv by rigid RANSAC.
        m = cfg.match
        with _timed(timings, "ransac"):
            fit = rigid_ransac(pts_peer, pts_ego, threshold=m.inlier_threshold_m,
                               min_sample_dist=m.min_sample_dist_m, max_iterations=m.max_iterations,
                               min_iterations=m.min_iterations, confidence=m.confidence, seed=m.seed)
        if fit is None:
            return finish(FailureReason.too_few_matches)
        result.T_bv = fit.T_dst_src
        result.inliers_bv = fit.num_inliers
        result.inlier_xy_peer, result.inlier_xy_ego = pts_peer[fit.inliers], pts_ego[fit.inliers]
        ambiguity = fit.ambiguity
        if result.inliers_bv <= cfg.success.min_inliers_bv:
            return finish(FailureReason.too_few_inliers_bv)
        if ambiguity >= cfg.success.max_ambiguity:
            return finish(FailureReason.ambiguous_bv)

        # Not in the paper: dense refinement of T_bv on the lit pixels (bounded; discarded if it wanders).
        refined = False
        if cfg.refine.enabled:
            with _timed(timings, "refine"):
                peer_pts = bev_points(peer.bev, cfg.refine.min_pixel_value, cfg.refine.max_peer_points, seed=m.seed)
                ref = self._refine(ego, peer_pts, result.T_bv)
            result.T_bv, result.refine_fitness, refined = ref.T, ref.fitness, ref.accepted
            if not ref.accepted:
                result.notes.append("BV refinement rejected (correction beyond bounds); stage-1 pose kept")
            if ref.fitness < cfg.success.min_refine_fitness:
                return finish(FailureReason.inconsistent_overlap)

        # Lines 12-15: box alignment on top of T_bv.
        if len(ego.boxes) == 0 or len(peer.boxes) == 0:
            if cfg.success.require_boxes:
                return finish(FailureReason.no_boxes)
            missing = [name for name, f in (("ego", ego), ("peer", peer)) if len(f.boxes) == 0]
            result.notes.append("stage 2 skipped: no boxes from " + " and ".join(missing))
            return finish(None)
        with _timed(timings, "boxes"):
            boxes = align_boxes(ego.boxes, peer.boxes, result.T_bv, cfg.box, seed=m.seed)
        result.box_pairs = boxes.pairs
        result.inliers_box = boxes.inliers
        stage2_failure = (FailureReason.no_box_overlap if boxes.pairs == 0 else
                          FailureReason.too_few_inliers_box if boxes.inliers <= cfg.success.min_inliers_box else None)
        if stage2_failure is not None:
            strong = cfg.success.strong_inliers_bv
            if strong is not None and result.inliers_bv > strong:
                result.notes.append(f"stage 2 could not verify ({stage2_failure.value}); accepted on stage-1 "
                                    f"evidence (inliers_bv > {strong})")
                return finish(None)
            return finish(stage2_failure)
        yaw, tx, ty = se2_params(boxes.T_box)
        if np.hypot(tx, ty) > cfg.box.max_correction_m or abs(np.degrees(yaw)) > cfg.box.max_correction_deg:
            return finish(FailureReason.box_correction_too_large)
        self._apply_box_correction(result, boxes.T_box, ego, peer_pts if refined else None, refined)
        return finish(None)

    def _refine(self, ego: PreparedFrame, peer_pts: np.ndarray, T_init: np.ndarray) -> Refinement:
        rf = self.config.refine
        return refine_icp(ego.cloud(rf.min_pixel_value), peer_pts, T_init, gates=rf.gates_m,
                          iters_per_gate=rf.iters_per_gate, relax=rf.step_relaxation,
                          max_correction_m=rf.max_correction_m,
                          max_correction_deg=rf.max_correction_deg)

    def _apply_box_correction(self, result: AlignResult, T_box: np.ndarray, ego: PreparedFrame,
                              peer_pts: np.ndarray | None, refined: bool) -> None:
        """Stage 2's T_box on top of the (refined) stage-1 pose, per config.box.apply (see BoxConfig)."""
        mode = self.config.box.apply
        if mode == "always" or not refined:
            result.T_box, result.stage2_applied = T_box, True
            return
        yaw, tx, ty = se2_params(T_box)
        box = self.config.box
        if mode == "unrefined" or (np.hypot(tx, ty) <= box.recheck_m and abs(np.degrees(yaw)) <= box.recheck_deg):
            result.notes.append("stage 2 verified the refined stage-1 pose; its correction was not applied")
            return
        # auto: a large, well-supported box correction may mean the refinement settled in a local optimum.
        # Refine again from the box-corrected pose and keep whichever pose the BV images agree with more.
        with _timed(result.timings_ms, "refine"):
            alt = self._refine(ego, peer_pts, T_box @ result.T_bv)
        if alt.accepted and alt.fitness > result.refine_fitness + 0.01:
            result.notes.append(f"stage 2 moved the pose to a better BV overlap ({result.refine_fitness:.2f} -> "
                                f"{alt.fitness:.2f}), refined again")
            result.T_box = alt.T @ np.linalg.inv(result.T_bv)
            result.refine_fitness, result.stage2_applied = alt.fitness, True
        else:
            result.notes.append("stage 2's correction did not improve the BV overlap; refined stage-1 pose kept")

    def _confidence(self, r: AlignResult, ambiguity: float) -> float:
        """Evidence -> [0, 1]. Grows with Inliers_bv and Inliers_box (the paper's Fig. 9: > 100 bv or > 20 box
        inliers put > 90% of pairs under 1 m / 1 deg), shrinks with the RANSAC ambiguity and with a low refinement
        fitness; capped when failed."""
        s = self.config.success
        c_bv = (1.0 - np.exp(-max(0, r.inliers_bv - s.min_inliers_bv) / 40.0)) * (1.0 - min(1.0, ambiguity))
        if self.config.refine.enabled and r.refine_fitness > 0:
            c_bv *= float(np.clip((r.refine_fitness - s.min_refine_fitness) / 0.2, 0.0, 1.0))
        c_box = 1.0 - np.exp(-max(0, r.inliers_box - s.min_inliers_box) / 8.0)
        c = 1.0 - (1.0 - c_bv) * (1.0 - c_box)
        if not r.success:
            cap = 0.5 if r.reason in {FailureReason.no_box_overlap.value, FailureReason.too_few_inliers_box.value,
                                      FailureReason.no_boxes.value} else 0.1
            c = min(c, cap)
        return float(np.clip(c, 0.0, 1.0))


def align_clouds(pts_ego: np.ndarray, pts_peer: np.ndarray, boxes_ego=None, boxes_peer=None,
                 config: AlignConfig | None = None) -> AlignResult:
    """One call: two clouds (sensor frames) and optional boxes -> AlignResult with T_ego_peer."""
    aligner = Aligner(config)
    return aligner.align(aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, boxes_peer))
