"""Decoders bounded before they are paid for: a PNG's ancillary chunks (allow-list, nothing inflated but the image
data) and a PCD header's numbers against the file's real size. The hostile files are built here."""

from __future__ import annotations

import os
import resource
import struct
import subprocess
import sys
import tracemalloc
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.io.clouds import InputFileError, load_cloud
from bb_align.protocol.errors import WireError
from bb_align.protocol.limits import Limits
from bb_align.protocol.png import ANCILLARY_ALLOWED, check_png

REPO = Path(__file__).resolve().parents[1]
N = 100


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)))


def _png_with(extra: bytes) -> bytes:
    """A genuine 100 px greyscale PNG (OpenCV's) with ``extra`` chunks put after IHDR."""
    img = np.random.default_rng(0).integers(0, 255, (N, N), dtype=np.uint8)
    png = cv2.imencode(".png", img)[1].tobytes()
    return png[:33] + extra + png[33:]


def _refusal(png: bytes) -> str:
    with pytest.raises(WireError) as e:
        check_png(png, N, Limits())
    assert (e.value.status, e.value.field) == (422, "png")
    return e.value.detail


def test_a_png_with_380_ztxt_chunks_is_refused_at_the_first_before_any_inflate(monkeypatch):
    """The attack: 380 zTXt chunks of 7.6 kB, each inflating to 8 MB in libpng. Refused at the first one, without
    inflating it (zlib is not called on it) and without OpenCV seeing the file."""
    body = b"Comment\x00\x00" + zlib.compress(bytes(8 * 2**20), 9)
    png = _png_with(_chunk(b"zTXt", body) * 380)
    assert len(png) > 380 * len(body)
    inflated = []
    real = zlib.decompressobj
    monkeypatch.setattr(zlib, "decompressobj", lambda *a: inflated.append(a) or real(*a))
    monkeypatch.setattr(cv2, "imdecode", lambda *a: pytest.fail("the decoder saw a refused PNG"))
    tracemalloc.start()
    detail = _refusal(png)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert "zTXt is not accepted" in detail and inflated == []
    assert peak < 2**20, f"the checker allocated {peak} bytes"


@pytest.mark.parametrize(
    "extra, says",
    [
        (_chunk(b"tEXt", b"Software\x00bb"), "tEXt is not accepted"),
        (_chunk(b"iTXt", b"k\x00\x01\x00\x00\x00" + zlib.compress(b"x" * 1000)), "iTXt is not accepted"),
        (_chunk(b"iCCP", b"icc\x00\x00" + zlib.compress(bytes(10_000))), "iCCP is not accepted"),
        (_chunk(b"prVt", b"x" * 10), "prVt is not accepted"),  # a private ancillary chunk
        (_chunk(b"gAMA", struct.pack(">I", 45455)) * 2, "more than once"),
        (_chunk(b"pHYs", bytes(4096)), "at most 64"),
    ],
)
def test_ancillary_chunks_outside_the_allow_list_or_repeated_are_refused(extra, says):
    assert says in _refusal(_png_with(extra))


def test_allowed_ancillary_chunks_pass_and_the_image_decodes():
    extra = _chunk(b"gAMA", struct.pack(">I", 45455)) + _chunk(b"pHYs", struct.pack(">IIB", 2835, 2835, 1))
    assert {b"gAMA", b"pHYs"} <= ANCILLARY_ALLOWED
    png = _png_with(extra)
    check_png(png, N, Limits())
    assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED).shape == (N, N)


def _pcd(header: dict, body: bytes = b"") -> bytes:
    base = {
        "VERSION": "0.7",
        "FIELDS": "x y z",
        "SIZE": "4 4 4",
        "TYPE": "F F F",
        "COUNT": "1 1 1",
        "WIDTH": "2",
        "HEIGHT": "1",
        "VIEWPOINT": "0 0 0 1 0 0 0",
        "POINTS": "2",
        "DATA": "binary",
    }
    text = "".join(f"{k} {v}\n" for k, v in {**base, **header}.items())
    return text.encode() + body


_TWO = np.arange(6, dtype=np.float32).tobytes()
_HOSTILE_PCDS = {
    "count_bomb.pcd": (_pcd({"COUNT": "100000000 1 1"}, _TWO), "COUNT 100000000"),
    "points_bomb.pcd": (_pcd({"WIDTH": "2000000000", "POINTS": "2000000000"}, _TWO), "POINTS 2000000000"),
    "wide_bomb.pcd": (_pcd({"WIDTH": "4000000000", "HEIGHT": "1"}, _TWO), "is not POINTS"),
    "lzf_bomb.pcd": (
        _pcd(
            {"WIDTH": "100000000", "POINTS": "100000000", "DATA": "binary_compressed"},
            struct.pack("<II", 20, 1_200_000_000) + bytes(20),
        ),
        "cannot inflate",
    ),
    "ascii_bomb.pcd": (_pcd({"WIDTH": "50000000", "POINTS": "50000000", "DATA": "ascii"}, b"1 2 3\n"), "cannot fit"),
    "no_data.pcd": (b"VERSION 0.7\nFIELDS x y z\n" + bytes(200), "no DATA line"),
    "mismatch.pcd": (_pcd({"SIZE": "4 4"}, _TWO), "one entry per field"),
    "bad_type.pcd": (_pcd({"TYPE": "F F Q"}, _TWO), "TYPE Q SIZE 4"),
    "half_float.pcd": (_pcd({"SIZE": "4 4 2"}, _TWO), "TYPE F SIZE 2"),
    "word.pcd": (_pcd({"POINTS": "two"}, _TWO), "POINTS 'two' is not an integer"),
    "negative.pcd": (_pcd({"WIDTH": "-2", "POINTS": "-2"}, _TWO), "negative"),
    "encoding.pcd": (_pcd({"DATA": "zip"}, _TWO), "DATA zip"),
    "short.pcd": (_pcd({}, _TWO[:12]), "the file holds 12"),
}


def test_hostile_and_malformed_pcd_headers_are_refused_naming_the_problem(tmp_path):
    for name, (data, says) in _HOSTILE_PCDS.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputFileError) as e:
            load_cloud(tmp_path / name)
        message = str(e.value)
        assert name in message and says in message and "\n" not in message, message
    (tmp_path / "good.pcd").write_bytes(_pcd({}, _TWO))
    np.testing.assert_array_equal(load_cloud(tmp_path / "good.pcd"), np.arange(6, dtype=np.float32).reshape(2, 3))


def test_every_malformed_pcd_is_one_line_and_exit_2_through_the_cli(tmp_path):
    runner = CliRunner()
    good = tmp_path / "good.npy"
    np.save(good, np.zeros((10, 3), np.float32))
    for name, (data, says) in _HOSTILE_PCDS.items():
        (tmp_path / name).write_bytes(data)
        out = runner.invoke(app, ["align", str(tmp_path / name), str(good)])
        lines = out.stderr.strip().splitlines()
        assert out.exit_code == 2 and len(lines) == 1 and says in lines[0], out.output
        assert "Traceback" not in out.output


def test_the_140_byte_count_bomb_is_refused_by_a_real_process_within_memory_and_time(tmp_path):
    """The reported attack end to end: `bb-align align` on a 140-byte PCD declaring COUNT 100000000 (it took
    23.6 GB before). The child runs under a 1 GB address-space cap; it must refuse with exit 2, one line."""
    bomb = tmp_path / "bomb.pcd"
    bomb.write_bytes(_pcd({"COUNT": "100000000 1 1"}, _TWO))
    assert len(bomb.read_bytes()) < 200
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "service"), str(REPO / "client")])}

    def cap():  # 1 GB of resident memory: the numba / OpenCV imports stay well under it
        resource.setrlimit(resource.RLIMIT_DATA, (2**30, 2**30))

    proc = subprocess.run(
        [sys.executable, "-m", "bb_align", "align", str(bomb), str(bomb)],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        preexec_fn=cap,
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "COUNT 100000000" in lines[0], proc.stderr
