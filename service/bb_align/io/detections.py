"""Per-frame detection files: the boxes an agent's own detector found, one file per agent and timestamp.

    DIR/<scenario>/<agent_id>/<timestamp>.npy    (K, 7) [x, y, z, l, w, h, yaw] or (K, 8, 3) corners
    DIR/<scenario>/<agent_id>/<timestamp>.json   [[x, y, z, l, w, h, yaw], ...], [{"x":..,"yaw":..}, ...],
                                                 or {"boxes": <either>, "scores": [...]} ; corners too
    DIR/<scenario>/<agent_id>/<timestamp>.txt    K rows of 7 numbers (whitespace or commas)

The layout mirrors the dataset's (``<scenario>`` includes the split folder, e.g. ``test/2021_08_18_19_48_05``).
Boxes are in the agent's own sensor frame (x forward, y left, z up; centre; yaw in radians) - what OpenCOOD's
single-agent inference gives before fusion. Corners follow OpenCOOD's ``boxes_to_corners_3d`` order (0-3 the
bottom face front-right, front-left, rear-left, rear-right; 4-7 the same on top), so a saved ``pred_box3d`` of
shape (K, 8, 3) works unchanged. A missing file means "no detections for that agent" (stage 2 is skipped).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bb_align.engine.boxes import BOX_FIELDS, as_boxes

SUFFIXES = (".npy", ".json", ".txt")


def corners_to_boxes(corners: np.ndarray) -> np.ndarray:
    """(K, 8, 3) corners in OpenCOOD's order -> (K, 7) [x, y, z, l, w, h, yaw]."""
    c = np.asarray(corners, dtype=float)
    if c.ndim != 3 or c.shape[1:] != (8, 3):
        raise ValueError(f"corners must be (K, 8, 3), got {c.shape}")
    centre = c.mean(axis=1)
    front = (c[:, 0] + c[:, 1]) / 2
    rear = (c[:, 2] + c[:, 3]) / 2
    length = np.linalg.norm(c[:, 0, :2] - c[:, 3, :2], axis=1)
    width = np.linalg.norm(c[:, 0, :2] - c[:, 1, :2], axis=1)
    height = np.abs(c[:, 4, 2] - c[:, 0, 2])
    yaw = np.arctan2(front[:, 1] - rear[:, 1], front[:, 0] - rear[:, 0])
    return np.column_stack([centre, length, width, height, yaw])


def boxes_from_array(arr, where: str = "boxes") -> np.ndarray:
    """(K, 7) boxes or (K, 8, 3) corners (or empty) -> (K, 7); errors name ``where``."""
    a = np.asarray(arr, dtype=float)
    try:
        if a.size == 0:
            return np.zeros((0, 7))
        if a.ndim == 3:
            return as_boxes(corners_to_boxes(a))
        if a.ndim == 1 and a.size == 7:
            a = a.reshape(1, 7)
        return as_boxes(a)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc} (expected (K, 7) [x, y, z, l, w, h, yaw] or (K, 8, 3) corners)") from exc


def load_detection_file(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """One detection file -> ((K, 7) boxes, (K,) scores or None)."""
    path = Path(path)
    suffix = path.suffix.lower()
    scores = None
    try:
        if suffix == ".npy":
            data = np.load(path, allow_pickle=False)
        elif suffix == ".txt":
            data = np.loadtxt(path.read_text().replace(",", " ").splitlines() or [], ndmin=2)
        elif suffix == ".json":
            data = json.loads(path.read_text())
            if isinstance(data, dict):
                if "boxes" not in data:
                    raise ValueError("a JSON object needs a 'boxes' key")
                scores = data.get("scores")
                data = data["boxes"]
            if isinstance(data, list) and data and isinstance(data[0], dict):
                missing = [k for k in BOX_FIELDS if k not in data[0]]
                if missing:
                    raise ValueError(f"box objects need keys {list(BOX_FIELDS)}, missing {missing}")
                data = [[b[k] for k in BOX_FIELDS] for b in data]
        else:
            raise ValueError(f"unknown detection file type {suffix!r} (use {', '.join(SUFFIXES)})")
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise ValueError(f"{path}: {exc}") from exc
    boxes = boxes_from_array(data, str(path))
    if scores is not None:
        scores = np.asarray(scores, dtype=float).reshape(-1)
        if len(scores) != len(boxes):
            raise ValueError(f"{path}: 'scores' has {len(scores)} entries for {len(boxes)} boxes")
    return boxes, scores


class DetectionDir:
    """Detections from a folder laid out like the dataset (see the module docstring)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"detections folder {self.root} is not a directory")

    def path_for(self, scenario: str, agent: str, timestamp: str) -> Path | None:
        for suffix in SUFFIXES:
            p = self.root / scenario / str(agent) / f"{timestamp}{suffix}"
            if p.is_file():
                return p
        return None

    def load(self, scenario: str, agent: str, timestamp: str) -> np.ndarray | None:
        """(K, 7) boxes, or None when the folder has no file for that agent frame."""
        p = self.path_for(scenario, agent, timestamp)
        return None if p is None else load_detection_file(p)[0]
