"""Reading clouds and boxes from the files users have: KITTI-style .bin, .npy, .pcd; boxes as JSON or CSV.

A file that cannot be read as what it should hold raises ``InputFileError`` (a ValueError) naming the file, what is
wrong and what is allowed; the ``bb-align`` command turns it into one line on stderr and exit code 2."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from bb_align.engine.boxes import BOX_FIELDS, as_boxes

from .errors import InputFileError

__all__ = ["InputFileError", "load_boxes", "load_cloud", "save_boxes_json"]

BIN_COLUMNS = (4, 5)  # KITTI x y z intensity; nuScenes / AV2 add a ring or time column


def load_cloud(path: str | Path, columns: int | None = None) -> np.ndarray:
    """(N, 3+) float32 points. ``.bin``: float32 with 4 columns (KITTI) or 5 (nuScenes/AV2), guessed from the
    size unless ``columns`` says; ``.npy``: (N, >=3); ``.pcd``: x y z (+ intensity) via pypcd4. Rows with a
    non-finite x, y or z (no return, in organised clouds) are dropped."""
    path = Path(path)
    suffix = path.suffix.lower()
    readers = {
        ".bin": lambda: _read_bin(path, columns),
        ".npy": lambda: _read_npy(path),
        ".pcd": lambda: _read_pcd(path),
    }
    if suffix not in readers:
        raise InputFileError(f"{path}: unknown cloud format {suffix or '(no suffix)'!r} (use .bin, .npy or .pcd)")
    pts = readers[suffix]()
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise InputFileError(f"{path}: a cloud is (N, >=3) columns x, y, z[, ...]; this one has shape {pts.shape}")
    try:
        pts = np.asarray(pts, dtype=np.float32)
    except (TypeError, ValueError) as e:
        raise InputFileError(f"{path}: cloud values must be numbers ({e})") from None
    return pts[np.isfinite(pts[:, :3]).all(axis=1)]


def _read_bin(path: Path, columns: int | None) -> np.ndarray:
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size == 0:
        raise InputFileError(f"{path}: empty file (a .bin cloud is float32 rows of 4 or 5 columns)")
    if columns is None:
        columns = next((c for c in BIN_COLUMNS if raw.size and raw.size % c == 0), None)
        if columns is None:
            raise InputFileError(
                f"{path}: {raw.size} float32 values do not split into rows of 4 (KITTI) or 5 (nuScenes/AV2) columns"
            )
    if raw.size % columns:
        raise InputFileError(f"{path}: {raw.size} float32 values do not split into rows of {columns} columns")
    return raw.reshape(-1, columns)


def _read_npy(path: Path) -> np.ndarray:
    with path.open("rb") as f:
        if f.read(6) != b"\x93NUMPY":
            raise InputFileError(f"{path}: not a .npy file (no NUMPY header; save with numpy.save)")
    try:
        pts = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise InputFileError(f"{path}: not a numeric .npy array ({e})") from None
    if not np.issubdtype(pts.dtype, np.number):
        raise InputFileError(f"{path}: a cloud holds numbers; this .npy holds {pts.dtype}")
    return pts


def _read_pcd(path: Path) -> np.ndarray:
    from pypcd4 import PointCloud

    from .pcd import check_pcd_header

    check_pcd_header(path)  # every number in the header bounded by the file's size, before pypcd4 allocates
    try:
        pc = PointCloud.from_path(path)
    except Exception as e:  # pypcd4 raises many kinds on a malformed header or body (pydantic's on many lines)
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise InputFileError(f"{path}: not a readable PCD file ({type(e).__name__}: {first})") from None
    fields = [f for f in ("x", "y", "z", "intensity") if f in pc.fields]
    missing = [f for f in ("x", "y", "z") if f not in fields]
    if missing:
        raise InputFileError(f"{path}: PCD lacks field(s) {missing} (needs x, y, z; has {list(pc.fields)})")
    return pc.numpy(fields)


def load_boxes(path: str | Path) -> np.ndarray:
    """(K, 7) boxes [x, y, z, l, w, h, yaw] (yaw radians) from a JSON list of objects with those keys (or of
    7-number lists; also ``{"boxes": [...]}``) or a CSV with those column names."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        rows = _json_box_rows(path)
    elif suffix == ".csv":
        rows = _csv_box_rows(path)
    else:
        raise InputFileError(f"{path}: boxes must be .json or .csv, got {suffix or '(no suffix)'!r}")
    try:
        return as_boxes(np.array(rows, dtype=float).reshape(-1, 7))
    except ValueError as e:
        raise InputFileError(f"{path}: {e}") from None


def _box_row(path: Path, i: int, box) -> list[float]:
    """One box as 7 floats, or an InputFileError naming the box and the field."""
    fields = ", ".join(BOX_FIELDS)
    if isinstance(box, dict):
        missing = [k for k in BOX_FIELDS if k not in box]
        if missing:
            raise InputFileError(f"{path}: box {i} lacks {', '.join(missing)} (each box needs {fields})")
        values = [box[k] for k in BOX_FIELDS]
    elif isinstance(box, list | tuple):
        if len(box) != 7:
            raise InputFileError(f"{path}: box {i} has {len(box)} numbers (needs 7: {fields})")
        values = list(box)
    else:
        raise InputFileError(f"{path}: box {i} is a {type(box).__name__} (needs an object or a list of {fields})")
    row = []
    for name, v in zip(BOX_FIELDS, values):
        if isinstance(v, bool) or not isinstance(v, int | float | str):
            raise InputFileError(f"{path}: box {i} {name} is {v!r}, not a number")
        try:
            row.append(float(v))
        except ValueError:
            raise InputFileError(f"{path}: box {i} {name} is {v!r}, not a number") from None
    return row


def _json_box_rows(path: Path) -> list[list[float]]:
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputFileError(f"{path}: not valid JSON ({e})") from None
    if isinstance(data, dict) and "boxes" in data:
        data = data["boxes"]
    if not isinstance(data, list):
        raise InputFileError(f"{path}: boxes are a JSON list of objects or of 7-number lists")
    return [_box_row(path, i, b) for i, b in enumerate(data)]


def _csv_box_rows(path: Path) -> list[list[float]]:
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [k for k in BOX_FIELDS if k not in (reader.fieldnames or [])]
        if missing:
            raise InputFileError(f"{path}: CSV lacks columns {missing} (needs {list(BOX_FIELDS)})")
        return [_box_row(path, i, {k: r[k] for k in BOX_FIELDS}) for i, r in enumerate(reader)]


def save_boxes_json(path: str | Path, boxes: np.ndarray) -> None:
    boxes = as_boxes(boxes)
    Path(path).write_text(json.dumps([dict(zip(BOX_FIELDS, map(float, b))) for b in boxes], indent=1))
