"""The whole PNG structure checked before any decoder sees it (chunks, CRCs, header, bounded inflate)."""

from __future__ import annotations

import struct
import zlib

import numpy as np

from .errors import invalid
from .limits import Limits, limit_env

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


_MAX_CHUNK = 2**31 - 1  # the PNG specification's largest chunk length
# The ancillary chunks a greyscale BV image may carry: fixed-size, never compressed, each at most once (the PNG
# specification's rule). Text (tEXt, zTXt, iTXt), ICC profiles (iCCP) and any other ancillary chunk are refused at
# once: zTXt and iCCP hold zlib streams a decoder inflates (hundreds of them kept libpng busy for 40 s).
ANCILLARY_ALLOWED = frozenset({b"gAMA", b"sRGB", b"pHYs", b"tIME", b"cHRM", b"sBIT", b"bKGD"})
_MAX_ANCILLARY_BYTES = 64  # the largest allowed one (cHRM) is 32 bytes


def check_png(data: bytes, size_px: int, limits: Limits, field: str = "png", *, inflate: bool = True) -> None:
    """The whole PNG structure, before any decoder sees it (raises WireError 422 naming ``field``).

    Signature; every chunk inside the file with a correct CRC; IHDR first: 8-bit greyscale, not interlaced,
    square, at most ``limits.max_image_px`` and exactly ``size_px`` a side; ancillary chunks only from
    ``ANCILLARY_ALLOWED``, each once and small (nothing else to inflate); consecutive IDAT chunks whose total
    is neither absurdly small (decoded/compressed over ``limits.max_png_ratio``) nor larger than an uncompressed
    image needs; no unknown critical chunk; IEND last, nothing after it. Then the image data is inflated with an
    output bound of the size the header implies (a decompression bomb stops there) and must fill it exactly,
    with a valid filter byte on every row. ``inflate=False`` stops before that inflate (about nine tenths of the
    cost): for a receiver that keeps only a car's latest frame, so that the frames it replaces unread never pay
    for it; ``Frame.bev_image`` checks the whole again before any decoder sees the image."""
    if len(data) < 8 + 25 + 12 or data[:8] != _PNG_SIGNATURE:
        raise invalid(field, "not a PNG file (bad signature or truncated)")
    pos, chunks, idat, idat_total, idat_closed, ended = 8, 0, [], 0, False, False
    ancillary: set[bytes] = set()
    width = height = 0
    while pos < len(data):
        if pos + 12 > len(data):
            raise invalid(field, f"truncated PNG chunk at byte {pos}")
        length, ctype = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 12 + length
        if length > _MAX_CHUNK or end > len(data):
            raise invalid(field, f"PNG chunk {ctype!r} at byte {pos} runs past the end of the file")
        body = data[pos + 8 : pos + 8 + length]
        if zlib.crc32(body, zlib.crc32(ctype)) != struct.unpack(">I", data[end - 4 : end])[0]:
            what = ctype.decode("latin-1") if ctype.isalpha() else repr(ctype)
            raise invalid(field, f"PNG {what} checksum mismatch")
        chunks += 1
        if chunks > limits.max_png_chunks:
            raise invalid(
                field,
                f"more than {limits.max_png_chunks} PNG chunks",
                limits.max_png_chunks,
                limit_env("max_png_chunks"),
            )
        if chunks == 1:
            if ctype != b"IHDR" or length != 13:
                raise invalid(field, "PNG must start with a 13-byte IHDR chunk")
            width, height = _check_ihdr(body, size_px, limits, field)
        elif ctype == b"IDAT":
            if idat_closed:
                raise invalid(field, "PNG IDAT chunks must be consecutive")
            idat.append(body)
            idat_total += length
        elif ctype == b"IEND":
            ended = True
            pos = end
            break
        elif ctype == b"IHDR" or not ctype[:1].islower():
            raise invalid(field, f"unexpected critical PNG chunk {ctype!r} (a greyscale PNG has IHDR, IDAT, IEND)")
        else:
            _check_ancillary(ctype, length, ancillary, field)
        if idat and ctype != b"IDAT":
            idat_closed = True
        pos = end
    if not ended or pos != len(data):
        raise invalid(field, "PNG must end with its IEND chunk" if not ended else "bytes after the PNG's IEND")
    _check_image_data(idat, idat_total, width, height, limits, field, inflate)


def _check_ancillary(ctype: bytes, length: int, seen: set[bytes], field: str) -> None:
    """An ancillary chunk: one of ``ANCILLARY_ALLOWED``, at most once, at most ``_MAX_ANCILLARY_BYTES``."""
    what = ctype.decode("latin-1") if ctype.isalpha() else repr(ctype)
    if ctype not in ANCILLARY_ALLOWED:
        allowed = ", ".join(sorted(c.decode() for c in ANCILLARY_ALLOWED))
        raise invalid(field, f"PNG ancillary chunk {what} is not accepted (allowed: {allowed}; no text or ICC chunks)")
    if ctype in seen:
        raise invalid(field, f"PNG ancillary chunk {what} appears more than once")
    if length > _MAX_ANCILLARY_BYTES:
        raise invalid(field, f"PNG {what} chunk of {length} bytes (at most {_MAX_ANCILLARY_BYTES})")
    seen.add(ctype)


def _check_ihdr(body: bytes, size_px: int, limits: Limits, field: str) -> tuple[int, int]:
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", body)
    if width > limits.max_image_px or height > limits.max_image_px:
        raise invalid(
            field,
            f"image {width}x{height} px exceeds {limits.max_image_px} px",
            limits.max_image_px,
            limit_env("max_image_px"),
        )
    if width < limits.min_image_px or height < limits.min_image_px:
        raise invalid(
            field,
            f"image {width}x{height} px is below {limits.min_image_px} px",
            limits.min_image_px,
            limit_env("min_image_px"),
        )
    if depth != 8 or colour != 0:
        raise invalid(
            field, f"PNG must be 8-bit greyscale (bit depth 8, colour type 0), got depth {depth}, colour type {colour}"
        )
    if compression != 0 or filtering != 0 or interlace != 0:
        raise invalid(
            field,
            f"PNG compression, filter and interlace methods must be 0 (got {compression}, {filtering}, {interlace})",
        )
    if (width, height) != (size_px, size_px):
        raise invalid(
            field, f"image is {width}x{height} px but bev.range_m and bev.resolution_m imply {size_px}x{size_px}"
        )
    return width, height


def _check_image_data(
    idat: list[bytes], total: int, width: int, height: int, limits: Limits, field: str, inflate: bool = True
) -> None:
    expected = height * (width + 1)  # one filter byte per row, one byte per pixel
    if total == 0:
        raise invalid(field, "PNG has no image data (IDAT)")
    if expected / total > limits.max_png_ratio:
        raise invalid(
            field,
            f"{total} bytes of image data cannot hold a {width}x{height} image (ratio "
            f"{expected / total:.0f} over {limits.max_png_ratio:g})",
            limits.max_png_ratio,
            limit_env("max_png_ratio"),
        )
    stored_max = expected + 5 * (expected // 16383 + 1) + 6  # deflate's uncompressed blocks plus zlib framing
    if total > stored_max:
        raise invalid(
            field,
            f"{total} bytes of image data for a {width}x{height} image, more than the "
            f"{stored_max} an uncompressed one takes",
            stored_max,
        )
    if not inflate:
        return
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(b"".join(idat), expected + 1)  # output bound: a bomb stops here
    except zlib.error as e:
        raise invalid(field, f"corrupt PNG image data: {e}") from None
    if len(raw) != expected or not inflater.eof or inflater.unconsumed_tail or inflater.unused_data:
        raise invalid(
            field, f"PNG image data does not inflate to exactly the {expected} bytes its header implies", expected
        )
    if expected and int(np.frombuffer(raw, np.uint8)[:: width + 1].max()) > 4:
        raise invalid(field, "PNG row filter types must be 0-4")
