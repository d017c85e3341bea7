"""Reading clouds and boxes from the files users have: KITTI-style .bin, .npy, .pcd; boxes as JSON or CSV."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from bb_align.engine.boxes import BOX_FIELDS, as_boxes


def load_cloud(path: str | Path, columns: int | None = None) -> np.ndarray:
    """(N, 3+) float32 points. ``.bin``: float32 with 4 columns (KITTI) or 5 (nuScenes/AV2), guessed from the
    size unless ``columns`` says; ``.npy``: (N, >=3); ``.pcd``: x y z (+ intensity) via pypcd4."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".bin":
        raw = np.fromfile(path, dtype=np.float32)
        if columns is None:
            columns = next((c for c in (4, 5) if raw.size % c == 0), None)
            if columns is None:
                raise ValueError(f"{path}: {raw.size} floats is neither 4 nor 5 columns; pass columns=")
        if raw.size % columns:
            raise ValueError(f"{path}: {raw.size} floats do not split into {columns} columns")
        pts = raw.reshape(-1, columns)
    elif suffix == ".npy":
        pts = np.load(path)
    elif suffix == ".pcd":
        from pypcd4 import PointCloud

        pc = PointCloud.from_path(path)
        fields = [f for f in ("x", "y", "z", "intensity") if f in pc.fields]
        pts = pc.numpy(fields)
    else:
        raise ValueError(f"{path}: unknown cloud format {suffix!r} (use .bin, .npy or .pcd)")
    pts = np.asarray(pts, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"{path}: cloud must be (N, >=3), got {pts.shape}")
    return pts


def load_boxes(path: str | Path) -> np.ndarray:
    """(K, 7) boxes [x, y, z, l, w, h, yaw] (yaw radians) from a JSON list of objects with those keys (or of
    7-number lists) or a CSV with those column names."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        data = json.loads(path.read_text())
        if isinstance(data, dict) and "boxes" in data:
            data = data["boxes"]
        rows = [[float(b[k]) for k in BOX_FIELDS] if isinstance(b, dict) else [float(v) for v in b] for b in data]
    elif path.suffix.lower() == ".csv":
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            missing = [k for k in BOX_FIELDS if k not in (reader.fieldnames or [])]
            if missing:
                raise ValueError(f"{path}: CSV lacks columns {missing} (needs {list(BOX_FIELDS)})")
            rows = [[float(r[k]) for k in BOX_FIELDS] for r in reader]
    else:
        raise ValueError(f"{path}: boxes must be .json or .csv")
    return as_boxes(np.array(rows, dtype=float).reshape(-1, 7))


def save_boxes_json(path: str | Path, boxes: np.ndarray) -> None:
    boxes = as_boxes(boxes)
    Path(path).write_text(json.dumps([dict(zip(BOX_FIELDS, map(float, b))) for b in boxes], indent=1))
