"""What the README says its quick-start numbers are checked with (read by the README tests, so one phrase in one
place sets the tolerance of both)."""

from __future__ import annotations

import re

_TOLERANCE = re.compile(r"within\s+±([\d.]+) deg / ±([\d.]+) m \(inliers within ([\d.]+) %\)")


def quickstart_tolerance(readme: str) -> tuple[float, float, float]:
    """(yaw deg, translation m, inliers as a fraction) the README's quick start states for its printed numbers."""
    tol = _TOLERANCE.search(readme)
    assert tol, "the README states the tolerance its quick-start numbers are checked with"
    return float(tol.group(1)), float(tol.group(2)), float(tol.group(3)) / 100
