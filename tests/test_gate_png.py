"""A stream frame's PNG image data is inflated when a worker takes the frame, not on the gate (issue 47: at 16
peers most frames are replaced unread, and the gate's inflate of each was most of its time per frame). A frame
whose image data is bad is still refused, by the worker: a failed result, never a pose."""

from __future__ import annotations

import struct
import zlib

import pytest

from bb_align.protocol import Limits, WireError, load_frame
from bb_align.protocol.png import check_png
from bb_align_client import encode_frame
from service_support import RANGE_M, moving_pair, service_settings, wait_for


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)))


def _with_corrupt_image_data(png: bytes) -> bytes:
    """The same PNG with its image data's zlib stream cut short: every chunk and CRC well formed, sizes plausible."""
    ihdr_end = 8 + 12 + 13
    chunks, pos, idat = [], 8, b""
    while pos < len(png):
        length, kind = struct.unpack(">I4s", png[pos : pos + 8])
        if kind == b"IDAT":
            idat += png[pos + 8 : pos + 8 + length]
        pos += 12 + length
    chunks.append(png[:ihdr_end])
    chunks.append(_chunk(b"IDAT", idat[: len(idat) - 40]))
    chunks.append(_chunk(b"IEND", b""))
    return b"".join(chunks)


@pytest.fixture(scope="module")
def pair():
    return moving_pair(1)[0]


def _frame(car, name: str, seq: int, stamp: float = 0.0, png: bytes | None = None) -> bytes:
    from bb_align.protocol import pack

    data = encode_frame(car.points, car.boxes, vehicle_id=name, stamp=stamp, seq=seq, range_m=RANGE_M)
    if png is None:
        return data
    frame = load_frame(data, Limits())
    return pack(frame.model_copy(update={"png": png}))


def test_the_structure_is_checked_without_inflating_and_the_whole_when_decoding(pair):
    _, _, peer = pair
    frame = load_frame(_frame(peer, "car1", 0), Limits())
    bad = _with_corrupt_image_data(frame.png)
    n = int(round(2 * RANGE_M / frame.bev.resolution_m))
    check_png(bad, n, Limits(), inflate=False)  # chunks, CRCs, header, sizes: all well formed
    with pytest.raises(WireError) as e:
        check_png(bad, n, Limits())
    assert e.value.field == "png" and "inflate" in e.value.detail
    deferred = load_frame(_frame(peer, "car1", 1, png=bad), Limits(), inflate_png=False)
    with pytest.raises(WireError) as e:  # the decode checks the whole again before OpenCV sees it
        deferred.bev_image()
    assert e.value.field == "png"
    with pytest.raises(WireError):
        load_frame(_frame(peer, "car1", 1, png=bad), Limits())  # by default load_frame inflates


def test_a_stream_frame_with_bad_image_data_is_refused_by_the_worker_never_a_pose(pair):
    from bb_align.server import AlignService

    _, ego, peer = pair
    settings = service_settings(zenoh=False, workers=1)
    service = AlignService(settings)
    results: list = []
    service.publishers.append(results.append)
    service.start()
    try:
        service.submit_frame(load_frame(_frame(ego, "ego", 0), settings.limits), 1000)
        bad = _with_corrupt_image_data(load_frame(_frame(peer, "car1", 0), settings.limits).png)
        service.submit_message("car1", _frame(peer, "car1", 0, png=bad))
        wait_for(lambda: len(results) >= 1, 60, "the bad frame's result")
        service.submit_message("car1", _frame(peer, "car1", 1))
        wait_for(lambda: len(results) >= 2, 120, "the next frame's result")
    finally:
        service.stop()
    first, second = results[0], results[1]
    assert (first.peer_seq, first.success, first.reason, first.T_ego_peer) == (0, False, "invalid_frame", None)
    assert any("png" in n for n in first.notes)
    assert second.peer_seq == 1 and second.success  # the car's next frame is answered as ever
