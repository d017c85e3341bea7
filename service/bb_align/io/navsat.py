"""GNSS fixes (latitude, longitude, altitude on WGS84) as metres in one local east-north-up frame, so two cars'
fixes and headings make poses in a shared map frame (x east, y north, z up, as ROS's REP 103 has it)."""

from __future__ import annotations

import numpy as np

WGS84_A = 6378137.0  # semi-major axis, m
WGS84_E2 = 6.69437999014e-3  # first eccentricity squared


def ecef(lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
    """Geodetic (degrees, metres above the ellipsoid) -> Earth-centred, Earth-fixed x, y, z in metres."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)  # prime vertical radius of curvature
    return np.array(
        [
            (n + alt_m) * np.cos(lat) * np.cos(lon),
            (n + alt_m) * np.cos(lat) * np.sin(lon),
            (n * (1.0 - WGS84_E2) + alt_m) * np.sin(lat),
        ]
    )


def enu(fix, origin) -> np.ndarray:
    """A fix (lat deg, lon deg, alt m) as east, north, up metres from ``origin`` (another fix)."""
    lat0, lon0 = np.radians(origin[0]), np.radians(origin[1])
    d = ecef(*fix) - ecef(*origin)
    sl, cl, so, co = np.sin(lat0), np.cos(lat0), np.sin(lon0), np.cos(lon0)
    R = np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])
    return R @ d
