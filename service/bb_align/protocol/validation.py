"""The one validator: a decoded Frame against the limits, the receiver's clock and its own image."""

from __future__ import annotations

import numpy as np

from bb_align.engine.bev import image_size_px
from bb_align.engine.config import BevConfig

from .errors import invalid
from .limits import REPLAY_HINT, Limits, limit_env
from .models import Frame
from .png import check_png


def validate_frame(
    frame: Frame, limits: Limits, where: str = "", now: float | None = None, *, inflate_png: bool = True
) -> None:
    """Check a decoded Frame against the limits (raises WireError): the PNG chunk by chunk, its image data inflated
    under a bound (``inflate_png=False``: left to ``Frame.bev_image``, ``check_png``), OpenCV decoding nothing.
    Field rules (types, ranges, finite numbers, ids, schema version) are the models'; this adds the limits that
    depend on settings, on the receiver's clock and on the image content."""
    f = lambda name: f"{where}.{name}" if where else name  # noqa: E731
    if frame.stamp > limits.max_stamp_s:
        raise invalid(
            f("stamp"),
            f"stamp {frame.stamp} s is beyond {limits.max_stamp_s} s",
            limits.max_stamp_s,
            limit_env("max_stamp_s"),
        )
    if now is not None and limits.clock_checked:
        _check_stamp_clock(frame.stamp, now, limits, f("stamp"))
    if frame.num_points is not None and frame.num_points > limits.max_points:
        raise invalid(
            f("num_points"),
            f"{frame.num_points} points exceed {limits.max_points}",
            limits.max_points,
            limit_env("max_points"),
        )
    if frame.bev.ground_clearance_m >= frame.bev.max_height_m:
        raise invalid(
            f("bev.ground_clearance_m"),
            f"ground_clearance_m {frame.bev.ground_clearance_m} must be below max_height_m {frame.bev.max_height_m}",
            frame.bev.max_height_m,
        )
    n = image_size_px(BevConfig(range_m=frame.bev.range_m, resolution_m=frame.bev.resolution_m))
    if n < limits.min_image_px:
        raise invalid(
            f("bev.range_m"),
            f"range_m / resolution_m give a {n}x{n} px image, below {limits.min_image_px} px",
            limits.min_image_px,
            limit_env("min_image_px"),
        )
    if limits.engine_resolution_m is not None and limits.max_resampled_px is not None:
        resampled = int(round(n * frame.bev.resolution_m / limits.engine_resolution_m))
        if resampled > limits.max_resampled_px:
            raise invalid(
                f("bev.resolution_m"),
                f"a {n}x{n} px image at {frame.bev.resolution_m} m/px becomes {resampled}x{resampled} px at the "
                f"engine's {limits.engine_resolution_m} m/px, more than max_resampled_px",
                limits.max_resampled_px,
                limit_env("max_resampled_px"),
            )
    check_png(frame.png, n, limits, f("png"), inflate=inflate_png)
    _check_boxes(frame, limits, f)
    for field_name in ("pose", "odometry"):
        pose = getattr(frame, field_name)
        for name in ("x", "y", "z") if pose is not None else ():
            if abs(getattr(pose, name)) > limits.max_pose_m:
                raise invalid(
                    f(f"{field_name}.{name}"),
                    f"|{name}| exceeds {limits.max_pose_m} m",
                    limits.max_pose_m,
                    limit_env("max_pose_m"),
                )


def _check_stamp_clock(stamp: float, now: float, limits: Limits, field: str) -> None:
    """The stamp against the receiver's clock. The refusal says which setting governs it and, since the usual
    cause is recorded or simulated data on its own clock, how to replay such data."""
    if stamp < now - limits.max_stamp_age_s:
        raise invalid(
            field,
            f"stamp is {now - stamp:.3f} s before the receiver's clock, more than max_stamp_age_s "
            f"{limits.max_stamp_age_s:g} s ({limit_env('max_stamp_age_s')}); {REPLAY_HINT}",
            limits.max_stamp_age_s,
            limit_env("max_stamp_age_s"),
        )
    if stamp > now + limits.max_stamp_lead_s:
        raise invalid(
            field,
            f"stamp is {stamp - now:.3f} s after the receiver's clock, more than max_stamp_lead_s "
            f"{limits.max_stamp_lead_s:g} s ({limit_env('max_stamp_lead_s')}); {REPLAY_HINT}",
            limits.max_stamp_lead_s,
            limit_env("max_stamp_lead_s"),
        )


def _check_boxes(frame: Frame, limits: Limits, f) -> None:
    """Counts, centres and sizes. Yaw is not bounded: any finite angle is taken (the model wraps it into
    [-pi, pi)); non-finite numbers never get this far (the models refuse them)."""
    if len(frame.boxes) > limits.max_boxes:
        raise invalid(
            f("boxes"), f"{len(frame.boxes)} boxes exceed {limits.max_boxes}", limits.max_boxes, limit_env("max_boxes")
        )
    if frame.scores is not None and len(frame.scores) != len(frame.boxes):
        raise invalid(f("scores"), f"{len(frame.scores)} scores for {len(frame.boxes)} boxes")
    if not frame.boxes:
        return
    b = frame.boxes_array()
    big = np.abs(b[:, :3]) > limits.max_box_distance_m
    if big.any():
        i = int(np.argwhere(big)[0, 0])
        raise invalid(
            f(f"boxes.{i}"),
            f"box centre beyond {limits.max_box_distance_m} m",
            limits.max_box_distance_m,
            limit_env("max_box_distance_m"),
        )
    bad = (b[:, 3:6] <= 0) | (b[:, 3:6] > limits.max_box_size_m)
    if bad.any():
        i = int(np.argwhere(bad)[0, 0])
        raise invalid(
            f(f"boxes.{i}"),
            f"box sizes l, w, h must be in (0, {limits.max_box_size_m}] m",
            limits.max_box_size_m,
            limit_env("max_box_size_m"),
        )
