"""Bandwidth accounting against hand-counted bytes and a controlled clock."""

from __future__ import annotations

import json

import cv2
import msgpack
import numpy as np
import pytest

from bb_align.protocol import JSON, BevMeta, Frame, pack, to_json
from bb_align.server.bandwidth import RAW_POINT_BYTES, BandwidthMeter, FrameBytes


def _frame(n_boxes=3, num_points=100_000) -> Frame:
    img = np.zeros((100, 100), np.uint8)
    img[10:20, 30:60] = 200
    return Frame(
        vehicle_id="car1",
        stamp=1.0,
        png=cv2.imencode(".png", img)[1].tobytes(),
        bev=BevMeta(resolution_m=0.4, range_m=20),
        boxes=[[1.0, 2.0, 0.5, 4.0, 2.0, 1.5, 0.1]] * n_boxes,
        num_points=num_points,
    )


def test_parts_add_up_and_raw_sizes_follow_their_definitions():
    f = _frame()
    data = pack(f)
    fb = FrameBytes.of(f, len(data))
    assert fb.png == len(f.png)
    assert fb.boxes == len(msgpack.packb(f.boxes))
    assert fb.png + fb.boxes + fb.header == len(data) and 0 < fb.header < 300
    assert fb.raw_points == RAW_POINT_BYTES * 100_000 == 1_600_000
    assert fb.raw_bev == 100 * 100


def test_json_parts_count_base64_text():
    f = _frame(n_boxes=0, num_points=None)
    data = to_json(f)
    fb = FrameBytes.of(f, len(data), JSON)
    assert fb.png == len(json.loads(data)["png"]) and fb.boxes == 0 and fb.raw_points is None
    assert fb.png + fb.header == len(data)


class _Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


def test_meter_totals_window_rate_and_ratios():
    clock = _Clock()
    meter = BandwidthMeter(window_s=2.0, clock=clock)
    f = _frame()
    fb = FrameBytes.of(f, 5000)
    for peer in ("car1", "car1", "car2"):  # three messages at t=1000
        meter.record_message(peer, 5000)
        meter.record_frame(peer, fb)
    clock.t += 1.5
    meter.record_message("car1", 1000)  # arrived but dropped before decoding: counted in bytes only
    rep = meter.report()
    car1 = rep.peers["car1"]
    assert (car1.messages, car1.bytes, car1.frames_decoded) == (3, 11000, 2)
    assert car1.kbit_s == pytest.approx(11000 * 8 / 1000 / 2.0)  # all within the 2 s window
    assert car1.bytes_per_frame == 5000
    assert car1.by_part.png == 2 * fb.png and car1.by_part.header == 2 * fb.header
    assert car1.ratio_vs_points == pytest.approx(10000 / (2 * 1_600_000))
    assert car1.ratio_vs_raw_bev == pytest.approx(10000 / 20000)
    assert (rep.total.messages, rep.total.bytes, rep.total.frames_decoded) == (4, 16000, 3)
    clock.t += 1.0  # the three first messages leave the window; the 1000-byte one stays
    rep = meter.report()
    assert rep.peers["car1"].kbit_s == pytest.approx(1000 * 8 / 1000 / 2.0)
    assert rep.peers["car2"].kbit_s == 0.0 and rep.total.kbit_s == pytest.approx(4.0)
    assert meter.peer("nobody") is None
