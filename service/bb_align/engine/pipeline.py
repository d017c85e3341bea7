"""The two-stage BB-Align pipeline (paper Algorithm 1).

    aligner = Aligner()
    ego = aligner.prepare(make_bev(pts_ego), boxes_ego)     # once per ego frame (cache it)
    peer = aligner.prepare(make_bev(pts_peer), boxes_peer)  # per peer frame
    result = aligner.align(ego, peer)                       # result.T_ego_peer maps peer points into ego

``prepare`` runs lines 6-8 (MIM, keypoints, descriptors) for one car; ``align`` runs lines 9-17. Each step is an
object built once from its config section; the verdict (success rule, failure reasons, confidence) is
``bb_align.engine.verdict``.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from threadpoolctl import ThreadpoolController

from .acquisition import Acquirer, PriorWindow, SearchMemo
from .bev import BevImage, make_bev
from .boxes import BoxStage, as_boxes, box_measurement
from .config import AlignConfig
from .covariance import fuse_poses, left_covariance, motion_covariance, params_covariance, pose_uncertainty
from .descriptors import bvft_descriptors, flip_180, keypoint_orientations
from .frame import PreparedFrame
from .geometry import ground_se2, se2_params
from .keypoints import detect_keypoints
from .landscape import Fields, GaussianPrior, Landscape, landscape, mahalanobis_d2, with_refinement, with_rivals
from .loggabor import maximum_index_map
from .matching import Matcher
from .parallel import run_parts
from .ransac import RigidRansac
from .refine import Refiner
from .result import AlignResult
from .verdict import FailureReason, Verdict

# box.apply "auto": a box correction beyond RECHECK_M or RECHECK_DEG is refined again on the images, and kept when
# its overlap fitness beats the refined stage-1 pose's by more than RECHECK_MIN_GAIN.
RECHECK_M, RECHECK_DEG, RECHECK_MIN_GAIN = 0.5, 0.5, 0.01
# box.fuse: at least FUSE_MIN_PAIRS box pairs (two fix the yaw), fused only when the two measurements agree within
# FUSE_CHI2 (squared Mahalanobis distance, chi2(3) 99 %).
FUSE_MIN_PAIRS, FUSE_CHI2 = 2, 11.345


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


@dataclass
class _Pair:
    """One alignment's working state: the two frames, the result being built, the refinement's peer points."""

    ego: PreparedFrame
    peer: PreparedFrame
    result: AlignResult
    peer_sample: tuple[np.ndarray, np.ndarray] | None = None  # the peer's lit pixels sampled for the refinement,
    # with their normals facing the peer's sensor (Refiner.sample)
    refined: bool = False  # the refinement ran and its correction was accepted
    multi: bool = False  # stage 1 ran the multi-hypothesis acquisition
    window: PriorWindow | None = None  # the multi path searched inside a prior's window only
    memo: SearchMemo | None = None  # what a second search of the same two frames reuses (see _within_prior)


class Aligner:
    """Stateless apart from its configuration and the step objects built from it; safe to share between threads."""

    def __init__(self, config: AlignConfig | None = None):
        self.config = cfg = config or AlignConfig()
        self.matcher = Matcher(cfg.match, cfg.prior, cfg.features, cfg.mim.n_orient)
        self.ransac = RigidRansac(cfg.ransac, cfg.seed)
        self.refiner = Refiner(cfg.refine, cfg.seed)
        self.box_stage = BoxStage(cfg.box, cfg.seed)
        self.verdict = Verdict.of(cfg)
        self.acquirer = Acquirer(cfg, self.verdict) if cfg.acquire.mode == "multi" else None

    # ---- Algorithm 1, lines 6-8: per car -------------------------------------------------------------
    def prepare(
        self, frame: BevImage | np.ndarray, boxes=None, *, keep_maps: bool = False, features: bool = True
    ) -> PreparedFrame:
        """A BV image (or a raw (N, 3+) cloud, made into one with config.bev) and its boxes -> features.

        ``features=False``: the image only, for tracking (the dense refinement needs no MIM, keypoints or
        descriptors); they are computed on first need (``PreparedFrame.ensure_features``, done by ``align``)."""
        with _single_threaded_blas():
            timings: dict[str, float] = {}
            num_points = None
            if not isinstance(frame, BevImage):
                pts = np.asarray(frame)
                num_points = int(len(pts))
                with _timed(timings, "bev"):
                    frame = make_bev(pts, self.config.bev)
            prepared = PreparedFrame(
                bev=self._at_resolution(frame), boxes=as_boxes(boxes), num_points=num_points, timings_ms=timings
            )
            prepared._features = lambda bev: self._features(bev, keep_maps, timings)
            return prepared.ensure_features() if features else prepared

    def _features(self, bev: BevImage, keep_maps: bool, timings: dict[str, float]) -> dict:
        cfg = self.config
        with _single_threaded_blas():
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
                desc = np.concatenate([d for _, d in described])
        return {
            "keypoints_rc": rc,
            "keypoints_xy": bev.pixel_to_metre(rc),
            "descriptors": desc,
            "descriptors_flipped": flip_180(desc, cfg.features),
            "orientations": np.concatenate([m for m, _ in described]),
            "mim": mim if keep_maps else None,
            "_maps": (mim, amp),
        }

    def warm(self, prepared: PreparedFrame) -> PreparedFrame:
        """Build now what a frame needs as the matched-against (ego) side: the reference descriptors and the
        lit-pixel cloud of the refinement. Otherwise the first alignment against it pays for them."""
        with _single_threaded_blas():
            prepared.ensure_features().reference_descriptors(self.config.features, self.config.mim.n_orient)
            if self.config.refine.enabled:
                prepared.cloud(self.config.refine)
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
        frame = self.warm(
            self.prepare(
                BevImage(image, b.resolution_m, n * b.resolution_m / 2, b.mode, b.ground_clearance_m, b.max_height_m)
            )
        )
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
    def align(
        self,
        ego: PreparedFrame,
        peer: PreparedFrame,
        *,
        tz: float = 0.0,
        roll: float = 0.0,
        pitch: float = 0.0,
        T_prior: np.ndarray | None = None,
    ) -> AlignResult:
        """T_ego_peer from prepared frames. tz, roll, pitch (metres, radians) are Eq. 1's constants.

        ``T_prior`` (3x3 or 4x4 ego <- peer, e.g. from both cars' reported poses) is optional. Multi mode: the pose
        must lie inside its window (config.prior), which is searched alone when the search everywhere fails
        (``_within_prior``); paper mode: the descriptor matches are gated by it. Without it every yaw and shift is
        searched."""
        with _single_threaded_blas():
            ego.ensure_features(), peer.ensure_features()
            if self.acquirer is None or T_prior is None:
                pair, reason = self._solve(ego, peer, T_prior)  # paper mode gates its matches by the prior
            else:
                pair, reason = self._within_prior(ego, peer, self._window(T_prior))
            return self.verdict.finish(pair.result, reason, tz=tz, roll=roll, pitch=pitch)  # lines 15-17

    def align_stream(self, frames: list, T_prior: np.ndarray | None = None) -> AlignResult:
        """T_ego_peer at the last of ``frames`` (``engine.stream_acquire.StreamFrame``: both cars' prepared frames,
        odometry poses and stamps, e.g. a second of a 10 Hz stream), from every frame together: a pose must
        explain every frame, an alias that does not persist loses its weight, the covariance is what the frames
        pin down together (engine.stream_acquire): a first answer where one frame alone cannot give one.
        ``T_prior``: a reported T_ego_peer at the last frame (4x4 or 3x3), as ``align``'s: the search inside its
        window, the rivals weighed by it."""
        from .stream_acquire import StreamAcquirer  # it builds on this class's steps

        return StreamAcquirer(self)(frames, T_prior)

    def _solve(
        self,
        ego: PreparedFrame,
        peer: PreparedFrame,
        T_prior: np.ndarray | None = None,
        window: PriorWindow | None = None,
        memo: SearchMemo | None = None,
    ) -> tuple[_Pair, FailureReason | None]:
        result = AlignResult(success=False, T_ego_peer=np.eye(4), T_bv=np.eye(3), T_box=np.eye(3))
        pair = _Pair(ego, peer, result, window=window, memo=memo)
        reason = (
            self.verdict.inputs(ego, peer)
            or self._stage1(pair, T_prior)  # lines 9-11: matches, P_src / P_dest, T_bv, Inliers_bv; refined
            or self._judge(pair)  # not in the paper: the pose landscape's peak and covariance (never fails)
            or self._stage2(pair)  # lines 12-15: boxes under T_bv, corner pairs, T_box, Inliers_box; fused
            or self._sweep_motion(pair)  # not in the paper: what the sweeps' self-motion may leave (never fails)
            or self._uncertain(pair)  # not in the paper: a degenerate final pose is refused
        )
        return pair, reason

    def _window(self, T_prior: np.ndarray) -> PriorWindow:
        p = self.config.prior
        return PriorWindow(ground_se2(np.asarray(T_prior, dtype=float)), p.max_translation_m, p.max_yaw_deg)

    def _within_prior(
        self, ego: PreparedFrame, peer: PreparedFrame, window: PriorWindow
    ) -> tuple[_Pair, FailureReason | None]:
        """Multi mode with a prior pose (not in the paper). First the search everywhere, as without a prior: its pose
        stands when it lies inside the prior's window, and is refused when it lies outside (the images and the
        report disagree: an alias, or a wrong or lying report). If it failed, the search again inside the window
        alone. There fewer rivals stand against the best pose, so the margin says less; the pose must then also be
        precise: 1-sigma within prior.max_sigma_m (docs/acquisition.md). The second search reuses
        the first's descriptor candidates, box poses and (unmasked) votes: only the window is new."""
        memo = SearchMemo()
        pair, reason = self._solve(ego, peer, memo=memo)
        r = pair.result
        if reason is None:
            return pair, self.verdict.within_prior(r, window.holds(r.T_box @ r.T_bv))
        if self.verdict.inputs(ego, peer) is not None:  # the inputs were refused: a window does not change that
            return pair, reason
        bounded, bounded_reason = self._solve(ego, peer, window=window, memo=memo)
        b = bounded.result
        b.notes.insert(0, f"searched everywhere first: {reason.value}; then inside the prior's window")
        for name, ms in r.timings_ms.items():
            b.timings_ms[name] = b.timings_ms.get(name, 0.0) + ms
        return bounded, bounded_reason

    # ---- tracking (not in the paper): one measurement from a predicted pose ------------------------------
    def measure(self, ego: PreparedFrame, peer: PreparedFrame, T_pred: np.ndarray) -> AlignResult:
        """The dense refinement started at a predicted T_ego_peer (3x3 or 4x4) and the refined pose's covariance:
        what a tracker fuses (bb_align.engine.follow). Needs no MIM, keypoints or descriptors. ``success``: the
        refinement stayed within its bounds on enough overlap (track.min_fitness); whether the pose agrees with the
        prediction is the tracker's judgement. ``T_ego_peer`` is the ground-plane pose lifted with no tz, roll or
        pitch (the follower sets them)."""
        cfg = self.config
        T_pred = ground_se2(np.asarray(T_pred, dtype=float))
        r = AlignResult(success=False, T_ego_peer=np.eye(4), T_bv=T_pred, T_box=np.eye(3))
        with _single_threaded_blas():
            reason = self.verdict.images(ego, peer)
            if reason is None:
                with _timed(r.timings_ms, "refine"):
                    sample = peer.cached(("refine_sample", self.config.seed), lambda: self.refiner.sample(peer.bev))
                    ego_cloud = ego.cloud(cfg.refine)
                    ref = self.refiner.refine(ego_cloud, sample, T_pred)
                r.T_bv, r.refine_fitness = ref.T, ref.fitness
                reason = self.verdict.measured(ref.accepted, ref.fitness, cfg.track.min_fitness)
            if reason is None and cfg.covariance.enabled:
                with _timed(r.timings_ms, "covariance"):
                    r.covariance = pose_uncertainty(
                        ego_cloud, sample, r.T_bv, cfg.refine.gates_m[-1], cfg.covariance, cfg.refine.facing_min_cos
                    )
            r.notes.append("tracking measurement: refined from the predicted pose")
            return self.verdict.finish(r, reason, tz=0.0, roll=0.0, pitch=0.0)

    def _stage1(self, pair: _Pair, T_prior: np.ndarray | None) -> FailureReason | None:
        """Lines 9-11 and the dense refinement. In multi mode: many pose hypotheses from the top-k descriptor
        candidates (inside ``pair.window`` when set), each verified densely (engine.acquire, not in the paper); in
        paper mode the nearest-neighbour (or prior-gated) matches and one RANSAC fit, then refined."""
        if self.acquirer is not None:
            r = pair.result
            reason, pair.peer_sample = self.acquirer(
                pair.ego, pair.peer, r, lambda name: _timed(r.timings_ms, name), window=pair.window, memo=pair.memo
            )
            pair.multi = pair.refined = True
            return reason
        return self._match_and_fit(pair, T_prior) or self._refine(pair)

    def _match_and_fit(self, pair: _Pair, T_prior: np.ndarray | None) -> FailureReason | None:
        r, t = pair.result, pair.result.timings_ms
        with _timed(t, "matching"):
            pts_peer, pts_ego = self.matcher(pair.ego, pair.peer, T_prior)
        if T_prior is not None:
            r.notes.append("matches gated by the prior pose")
        r.matches_bv = len(pts_peer)
        with _timed(t, "ransac"):
            fit = self.ransac.fit(pts_peer, pts_ego) if len(pts_peer) >= 2 else None
        if fit is None:
            return self.verdict.candidates(0)
        r.T_bv, r.inliers_bv, r.ambiguity_bv = fit.T_dst_src, fit.num_inliers, fit.ambiguity
        r.inlier_xy_peer, r.inlier_xy_ego = pts_peer[fit.inliers], pts_ego[fit.inliers]
        return self.verdict.stage1(r)

    def _judge(self, pair: _Pair) -> None:
        """The refined stage-1 pose judged on its landscape (engine.landscape): it stands when the grid agrees within
        1 sigma, else the grid's answer is taken; the covariance is the grid's distribution, widened by the refined
        pose when the grid rules it out and, inside a prior's window (where they replace the margin) or when
        better-scoring poses gave way to the free space, by the other poses the search kept. Without the landscape:
        the refinement's covariance."""
        lc = self.config.landscape
        if not (lc.enabled and pair.multi and self.config.covariance.enabled) or pair.peer_sample is None:
            return self._covariance(pair)
        r = pair.result
        with _timed(r.timings_ms, "landscape"):
            main, fields, pts = self._landscape_about(pair.ego, pair.peer_sample, r.T_bv)
            r.T_bv, r.covariance = main.T, main.covariance
            if main.at_edge:
                r.notes.append("the pose landscape has no bounded peak within its window (a corridor)")
            if r.acquisition is not None and (pair.window is not None or r.acquisition.gave_way):
                pc = self.config.prior
                prior = None if pair.window is None else GaussianPrior(pair.window.T, pc.sigma_m, pc.sigma_deg)
                rivals = r.acquisition.rivals()
                ego_cloud = pair.ego.cloud(self.config.refine)
                r.covariance, weights = with_rivals(main, ego_cloud, fields, pts, rivals, lc, prior)
                if weights and max(weights) > 1e-3:
                    r.notes.append(f"the rivals weigh up to {max(weights):.3f} of the answer")
        return None

    def _landscape_about(self, ego: PreparedFrame, peer_sample, T_refined: np.ndarray, lc=None):
        """The landscape around a refined pose, weighed against the refinement (``with_refinement``): (the landscape
        with the answer and covariance, the ego's fields, the peer points scored). ``lc``: another window."""
        lc = lc or self.config.landscape
        ego_cloud, fields = ego.cloud(self.config.refine), self._fields(ego)
        pts = peer_sample[0][: lc.max_points]
        main = landscape(ego_cloud, fields, pts, T_refined, lc)
        if lc.refinement_d2 is not None and not main.at_edge:
            if mahalanobis_d2(main, T_refined) > lc.refinement_d2:
                # A local search started elsewhere may have stopped in another basin: ask the refinement again
                # from the landscape's answer before calling the two estimators in disagreement.
                again = self.refiner.refine(ego_cloud, peer_sample, main.T)
                if again.accepted:
                    T_refined = again.T
            main.T, main.covariance = with_refinement(main, T_refined, lc.refinement_d2)
        return main, fields, pts

    def _fields(self, ego: PreparedFrame) -> Fields:
        """The ego image's likelihood fields for the landscape, built once per ego frame. Keyed by every setting
        they depend on: a frame may be judged by aligners of other configs."""
        lc = self.config.landscape
        key = ("landscape_fields", lc.sigma_m, lc.wide_sigma_m, lc.step_m)
        return ego.cached(key, lambda: Fields.of(ego.cloud(self.config.refine), lc))

    def ready_to_track(self, ego: PreparedFrame) -> PreparedFrame:
        """The ego-side work every tracked peer frame against ``ego`` uses, done once when the ego frame arrives:
        the refinement's cloud and the landscape's fields (no MIM or descriptors: an acquisition builds them)."""
        with _single_threaded_blas():
            self._fields(ego)
        return ego

    def judge(
        self, ego: PreparedFrame, peer: PreparedFrame, T_refined: np.ndarray, half_width_m: float | None = None
    ) -> Landscape:
        """A refined T_ego_peer (3x3, e.g. ``measure``'s) judged on its pose landscape as an acquisition's answer
        is: the landscape's answer and covariance (of its parameters; unbounded, ``at_edge``, in a corridor). What a
        tracker takes as a frame's own evidence: the refinement's curvature is over-confident at range.
        ``half_width_m``: the window's reach in x and y (default ``landscape.half_width_m``)."""
        sample = peer.cached(("refine_sample", self.config.seed), lambda: self.refiner.sample(peer.bev))
        lc = self.config.landscape
        if half_width_m is not None and half_width_m != lc.half_width_m:
            lc = lc.model_copy(update={"half_width_m": float(half_width_m)})
        with _single_threaded_blas():
            return self._landscape_about(ego, sample, ground_se2(np.asarray(T_refined, dtype=float)), lc)[0]

    def _covariance(self, pair: _Pair) -> None:
        """The covariance of the current pose (T_box @ T_bv) from the refinement's normal equations."""
        if not self.config.covariance.enabled or pair.peer_sample is None:
            return None
        r = pair.result
        with _timed(r.timings_ms, "covariance"):
            r.covariance = pose_uncertainty(
                pair.ego.cloud(self.config.refine),
                pair.peer_sample,
                r.T_box @ r.T_bv,
                self.config.refine.gates_m[-1],
                self.config.covariance,
                self.config.refine.facing_min_cos,
            )
        return None

    def _sweep_motion(self, pair: _Pair) -> None:
        """The final pose's covariance widened by what each car's travel during a sweep it did not de-skew may move it
        (``covariance.sweep_travel_m``; engine.covariance.motion_covariance): a shear the images cannot reveal."""
        r, cc = pair.result, self.config.covariance
        if r.covariance is None or pair.peer_sample is None or cc.sweep_travel_m <= 0:
            return None
        with _timed(r.timings_ms, "covariance"):
            gate, min_cos = self.config.refine.gates_m[-1], self.config.refine.facing_min_cos
            extra = motion_covariance(
                pair.ego.cloud(self.config.refine), pair.peer_sample, r.T_box @ r.T_bv, gate, cc.sweep_travel_m, min_cos
            )
            r.covariance = np.asarray(r.covariance, dtype=float) + extra
        return None

    def _uncertain(self, pair: _Pair) -> FailureReason | None:
        if pair.result.covariance is None:
            return None
        bound = None  # inside a prior's window the landscape counts the rivals; else the margin did
        if pair.window is not None and not (self.config.landscape.enabled and pair.multi):
            bound = self.config.prior.max_sigma_m
        return self.verdict.uncertain(pair.result, max_sigma_m=bound)

    def _refine(self, pair: _Pair) -> FailureReason | None:
        """Dense point-to-line ICP of T_bv on the lit pixels; bounded (a correction that wanders is discarded)."""
        if not self.refiner.enabled:
            return None
        r = pair.result
        with _timed(r.timings_ms, "refine"):
            pair.peer_sample = self.refiner.sample(pair.peer.bev)
            ref = self.refiner.refine(pair.ego.cloud(self.config.refine), pair.peer_sample, r.T_bv)
        r.T_bv, r.refine_fitness, pair.refined = ref.T, ref.fitness, ref.accepted
        if not ref.accepted:
            r.notes.append("BV refinement rejected (correction beyond bounds); stage-1 pose kept")
        return self.verdict.refined(r)

    def _stage2(self, pair: _Pair) -> FailureReason | None:
        r = pair.result
        missing = [name for name, f in (("ego", pair.ego), ("peer", pair.peer)) if len(f.boxes) == 0]
        if missing:
            return self.verdict.without_boxes(r, missing)
        with _timed(r.timings_ms, "boxes"):
            boxes = self.box_stage.align(pair.ego.boxes, pair.peer.boxes, r.T_bv)
        r.box_pairs, r.inliers_box = boxes.pairs, boxes.inliers
        evidence = None  # the multi path's dense evidence, when found by the search everywhere
        if pair.multi and pair.window is None and r.acquisition is not None and r.acquisition.best is not None:
            evidence = r.acquisition.evidence
        reason = self.verdict.stage2(r, boxes.T_box, densely_verified=pair.multi, evidence=evidence)
        if reason is None and self.verdict.boxes_verified(r):
            self._apply_box_correction(pair, boxes.T_box)
            if r.stage2_applied:  # the pose moved: its uncertainty is the final pose's
                self._covariance(pair)
            reason = self._fuse_boxes(pair)
        return reason

    def _fuse_boxes(self, pair: _Pair) -> FailureReason | None:
        """Not in the paper: the boxes both cars detected as a second, independent measurement of the final pose,
        fused with the refined one by information (box.fuse). The refinement pins a far pair across the street but
        hardly along it; the cars' positions pin it along. When the two disagree the pose is refused
        (box.fuse_disagreement_fails), or the boxes are left out."""
        r, box = pair.result, self.config.box
        if not box.fuse or r.covariance is None:
            return None
        T = r.T_box @ r.T_bv
        with _timed(r.timings_ms, "boxes"):
            meas = box_measurement(
                pair.ego.boxes,
                pair.peer.boxes,
                T,
                box.fuse_sigma_m,
                pair_gate_m=box.pair_gate_m,
                min_pairs=FUSE_MIN_PAIRS,
                min_inliers=self.config.success.min_inliers_box + 1,
                cfg=box,
                seed=self.config.seed,
            )
            fused = None if meas is None else fuse_poses(T, left_covariance(r.covariance, T), *meas, FUSE_CHI2)
        if meas is None:
            r.notes.append("box measurement not formed")
            return None
        if fused is None:
            return self.verdict.boxes_disagree(r, refuse=box.fuse_disagreement_fails)
        T_fused, C_fused = fused
        r.T_box = T_fused @ np.linalg.inv(r.T_bv)
        r.covariance = params_covariance(C_fused, T_fused)
        r.notes.append("box measurement fused with the refined pose")
        return None

    def _apply_box_correction(self, pair: _Pair, T_box: np.ndarray) -> None:
        """Stage 2's T_box on top of the (refined) stage-1 pose, per config.box.apply (see BoxConfig)."""
        r, box = pair.result, self.config.box
        if box.apply == "always" or not pair.refined:
            r.T_box, r.stage2_applied = T_box, True
            return
        yaw, tx, ty = se2_params(T_box)
        if np.hypot(tx, ty) <= RECHECK_M and abs(np.degrees(yaw)) <= RECHECK_DEG:
            r.notes.append("stage 2 verified the refined stage-1 pose; its correction was not applied")
            return
        # auto: a large, well-supported box correction may mean the refinement settled in a local optimum.
        # Refine again from the box-corrected pose and keep whichever pose the BV images agree with more.
        with _timed(r.timings_ms, "refine"):
            alt = self.refiner.refine(pair.ego.cloud(self.config.refine), pair.peer_sample, T_box @ r.T_bv)
        if alt.accepted and alt.fitness > r.refine_fitness + RECHECK_MIN_GAIN:
            r.notes.append(
                f"stage 2 moved the pose to a better BV overlap ({r.refine_fitness:.2f} -> "
                f"{alt.fitness:.2f}), refined again"
            )
            r.T_box = alt.T @ np.linalg.inv(r.T_bv)
            r.refine_fitness, r.stage2_applied = alt.fitness, True
        else:
            r.notes.append("stage 2's correction did not improve the BV overlap; refined stage-1 pose kept")


def align_clouds(
    pts_ego: np.ndarray, pts_peer: np.ndarray, boxes_ego=None, boxes_peer=None, config: AlignConfig | None = None
) -> AlignResult:
    """One call: two clouds (sensor frames) and optional boxes -> AlignResult with T_ego_peer."""
    aligner = Aligner(config)
    return aligner.align(aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, boxes_peer))
