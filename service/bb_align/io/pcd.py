"""A PCD file's header checked against the file's real size before pypcd4 allocates anything.

pypcd4 trusts the header: ``COUNT 100000000`` makes it build a 100-million-field record type (a 140-byte file took
23 GB), a large ``POINTS`` makes it allocate the whole array before reading the data, and a binary_compressed
body's declared size is what LZF allocates. Here every number in the header is bounded by what the file can
hold; anything else raises ``InputFileError`` with one line naming the file, the header line and the limit."""

from __future__ import annotations

import struct
from pathlib import Path

from .errors import InputFileError

MAX_HEADER_BYTES = 64 * 1024  # the header's text (a few hundred bytes in practice)
MAX_HEADER_LINES = 10  # pypcd4 reads at most 10 lines before DATA
MAX_FIELDS = 64
MAX_COUNT = 1024  # values in one field of one point (e.g. a 33-bin FPFH descriptor)
LZF_MAX_RATIO = 100  # LZF encodes at most 264 bytes in 3 (~88:1): a body claiming more is a lie
SIZES = {"F": (4, 8), "U": (1, 2, 4, 8), "I": (1, 2, 4, 8)}
ENCODINGS = ("ascii", "binary", "binary_compressed", "binaryscompressed")


def check_pcd_header(path: Path) -> dict:
    """The header of ``path`` as {key: [values]} once it is consistent and fits in the file; else InputFileError."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(MAX_HEADER_BYTES)
    header, lines, offset = {}, 0, 0
    for raw in head.splitlines(keepends=True):
        offset += len(raw)
        line = raw.decode("latin-1").strip()
        if not line or line.startswith("#"):
            continue
        lines += 1
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            break
        if lines >= MAX_HEADER_LINES:
            raise _bad(path, f"no DATA line within the header's first {MAX_HEADER_LINES} lines")
    else:
        raise _bad(path, f"no DATA line in the first {min(size, MAX_HEADER_BYTES)} bytes (not a PCD header)")
    fields, sizes, types, counts = (header.get(k, []) for k in ("FIELDS", "SIZE", "TYPE", "COUNT"))
    if not fields or len(fields) > MAX_FIELDS:
        raise _bad(path, f"FIELDS names {len(fields)} fields (1 to {MAX_FIELDS})")
    if not (len(sizes) == len(types) == len(counts) == len(fields)):
        raise _bad(
            path,
            f"FIELDS, SIZE, TYPE and COUNT must list one entry per field "
            f"(got {len(fields)}, {len(sizes)}, {len(types)}, {len(counts)})",
        )
    row = values = 0
    for name, s, t, c in zip(fields, sizes, types, counts, strict=True):
        s_int, c_int = _int(path, "SIZE", s), _int(path, "COUNT", c)
        if t not in SIZES or s_int not in SIZES[t]:
            raise _bad(path, f"field {name}: TYPE {t} SIZE {s} is not a PCD number type (F 4/8, U or I 1/2/4/8)")
        if not 1 <= c_int <= MAX_COUNT:
            raise _bad(path, f"field {name}: COUNT {c} (1 to {MAX_COUNT} values per point)")
        row, values = row + s_int * c_int, values + c_int
    width, height = (
        _int(path, "WIDTH", _one(path, header, "WIDTH")),
        _int(path, "HEIGHT", _one(path, header, "HEIGHT", "1")),
    )
    points = _int(path, "POINTS", _one(path, header, "POINTS"))
    if width * height != points:
        raise _bad(path, f"WIDTH {width} x HEIGHT {height} is not POINTS {points}")
    data = _one(path, header, "DATA").lower()
    if data not in ENCODINGS:
        raise _bad(path, f"DATA {data} (one of ascii, binary, binary_compressed)")
    body = size - offset
    if data == "binary" and points * row > body:
        raise _bad(
            path, f"POINTS {points} of {row} bytes need {points * row} bytes; the file holds {body} after its header"
        )
    if data == "ascii" and points * values * 2 > body + 1:  # a value is at least one digit and one separator
        raise _bad(path, f"POINTS {points} of {values} values cannot fit in the {body} bytes after the header")
    if data.startswith("binary") and data != "binary":
        _check_compressed(path, offset, body, points * row)
    return header


def _check_compressed(path: Path, offset: int, body: int, expected: int) -> None:
    if body < 8:
        raise _bad(path, "binary_compressed data without its 8-byte size header")
    with path.open("rb") as f:
        f.seek(offset)
        compressed, uncompressed = struct.unpack("<II", f.read(8))
    if uncompressed != expected:
        raise _bad(path, f"compressed data inflates to {uncompressed} bytes, but the header's points need {expected}")
    if compressed > body - 8:
        raise _bad(path, f"compressed data of {compressed} bytes; the file holds {body - 8}")
    if uncompressed > LZF_MAX_RATIO * max(compressed, 1):
        raise _bad(
            path, f"{compressed} compressed bytes cannot inflate to {uncompressed} (LZF: at most {LZF_MAX_RATIO}:1)"
        )


def _one(path: Path, header: dict, key: str, default: str | None = None) -> str:
    values = header.get(key, [default] if default is not None else [])
    if len(values) != 1:
        raise _bad(path, f"{key} needs one value (got {len(values)})")
    return values[0]


def _int(path: Path, key: str, text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise _bad(path, f"{key} {text!r} is not an integer") from None
    if value < 0:
        raise _bad(path, f"{key} {value} is negative")
    return value


def _bad(path: Path, problem: str) -> InputFileError:
    return InputFileError(f"{path}: PCD header: {problem}")
