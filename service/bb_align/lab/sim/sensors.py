"""Rotating LiDAR models: beam layout, range, noise, dropout, spin rate, mounting.

Beam angles follow the manufacturers' published layouts (rounded); noise and dropout are typical datasheet /
field values. Cars in one scenario get different models, as in mixed fleets.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class SensorModel(BaseModel):
    """One spinning LiDAR. Angles in degrees, distances in metres."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    elevations_deg: tuple[float, ...] = Field(description="vertical angle of every beam")
    columns: int = Field(1800, ge=64, le=4096, description="firings per revolution (azimuth steps)")
    max_range_m: float = Field(100.0, gt=1)
    min_range_m: float = Field(1.0, ge=0)
    range_noise_m: float = Field(0.02, ge=0, description="Gaussian range noise, 1 sigma")
    dropout: float = Field(0.05, ge=0, lt=1, description="probability that a return is lost regardless of range")
    far_falloff: float = Field(3.0, gt=0, description="P(return) *= 1 - (r / reach)^far_falloff")
    range_10pct_m: float | None = Field(
        None,
        gt=0,
        description="datasheet range for a 10 % reflective target (max_range_m is the 80 % one); None: the lidar "
        "equation's square-root law, max_range_m / sqrt(8)",
    )
    incidence_exponent: float = Field(
        0.0,
        ge=0,
        le=1,
        description="a solid face returns as a target of reflectivity x cos(incidence)^this (1: Lambertian). 0 by "
        "default: the real KITTI scans' facades seen along a street stay visible to 70 m, which 0.5 or 1 do not "
        "reproduce (docs/simulation.md)",
    )
    elevation_jitter_deg: float = Field(0.03, ge=0, description="per-beam calibration error, 1 sigma")
    azimuth_phases: int = Field(
        8,
        ge=1,
        le=64,
        description="the lasers fire at this many distinct azimuths within one column step: a real laser's azimuth "
        "offset is no multiple of the step (in a 1 deg window of real scans, 63-93 % of the returns have an azimuth "
        "of their own: HDL-64E on KITTI and Apollo, HDL-32E on nuScenes, DAIR-V2X's vehicle and roadside LiDARs). "
        "1: every laser at the column's azimuth, which draws a wall seen at a grazing angle as a dotted line (one "
        "hit per column: 1.8 m apart on a facade 10 m aside, 75 m ahead); 8 puts one every 0.23 m, under a pixel",
    )
    spin_hz: float = Field(10.0, gt=0)

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    def beam_phases(self) -> np.ndarray:
        """When each beam fires within its column, in column steps, in (0, 1) (the middle for one phase; so a sweep
        stays within its revolution): neighbouring beams at phases far apart."""
        g = self.azimuth_phases
        stride = next(k for k in range(g // 2 + 1, g + 1) if np.gcd(k, g) == 1) if g > 2 else 1
        return ((np.arange(self.beams) * stride) % g + 0.5) / g

    @property
    def reflectivity_exponent(self) -> float:
        """k in reach = max_range (reflectivity / 0.8)^k, fitted to the datasheet's 10 % and 80 % ranges."""
        if self.range_10pct_m is None:
            return 0.5
        return float(np.log(self.max_range_m / self.range_10pct_m) / np.log(8.0))

    def reach_m(self, reflectivity) -> np.ndarray:
        """Detection range of a target of this reflectivity (0..1) at normal incidence. A target that fills the beam
        returns power ~ reflectivity / r^2, so with a fixed detection threshold the range goes as
        sqrt(reflectivity); datasheets quote two points of it (e.g. HDL-64E: 50 m at 10 %, 120 m at 80 %)."""
        rho = np.clip(np.asarray(reflectivity, dtype=float), 1e-4, 1.0)
        return self.max_range_m * (rho / 0.8) ** self.reflectivity_exponent

    def detect_probability(self, r, reflectivity) -> np.ndarray:
        """P(a return) at range r from a target of this (effective) reflectivity: 1 - (r / reach)^far_falloff."""
        return np.clip(1.0 - (np.asarray(r) / self.reach_m(reflectivity)) ** self.far_falloff, 0.0, 1.0)


_VLP32C = (
    -25.0,
    -15.64,
    -11.31,
    -8.84,
    -7.25,
    -6.15,
    -5.33,
    -4.67,
    -4.0,
    -3.67,
    -3.33,
    -3.0,
    -2.67,
    -2.33,
    -2.0,
    -1.67,
    -1.33,
    -1.0,
    -0.67,
    -0.33,
    0.0,
    0.33,
    0.67,
    1.0,
    1.33,
    1.67,
    2.33,
    3.33,
    4.67,
    7.0,
    10.33,
    15.0,
)

SENSOR_MODELS: dict[str, SensorModel] = {
    "hdl64": SensorModel(
        name="hdl64",
        elevations_deg=tuple(np.round(np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.9, 32)]), 3)),
        columns=2000,
        max_range_m=120,
        range_10pct_m=50,  # datasheet: 50 m for pavement (~10 %), 120 m for cars and foliage (~80 %)
        range_noise_m=0.02,
        dropout=0.04,
    ),
    "vlp32c": SensorModel(
        name="vlp32c", elevations_deg=_VLP32C, columns=1800, max_range_m=120, range_noise_m=0.03, dropout=0.06
    ),
    "os1_64": SensorModel(
        name="os1_64",
        elevations_deg=tuple(np.round(np.linspace(16.6, -16.6, 64), 3)),
        columns=1024,
        max_range_m=100,
        range_noise_m=0.03,
        dropout=0.05,
    ),
    "pandar40": SensorModel(
        name="pandar40",
        elevations_deg=tuple(
            np.round(
                np.concatenate(
                    [
                        [15.0, 11.0, 8.0, 5.0, 3.0, 2.0],
                        np.linspace(1.67, -4.0, 18),
                        [-4.33, -4.67, -5.0, -5.33, -5.67],
                        [-6.0, -7.0, -8.0, -9.0, -10.0, -11.0, -12.0, -13.0, -14.0, -19.0, -25.0],
                    ]
                ),
                3,
            )
        ),
        columns=1800,
        max_range_m=110,
        range_noise_m=0.03,
        dropout=0.05,
    ),
    "vlp16": SensorModel(
        name="vlp16",
        elevations_deg=tuple(float(a) for a in range(-15, 16, 2)),
        columns=1800,
        max_range_m=100,
        range_noise_m=0.03,
        dropout=0.05,
    ),
}
"""Presets. vlp16 is the sparse extreme; the default fleet draws from the others."""

DEFAULT_FLEET = ("hdl64", "vlp32c", "os1_64", "pandar40")


def pick_sensors(rng: np.random.Generator, n: int, fleet=DEFAULT_FLEET) -> list[SensorModel]:
    """n sensor models, all different while the fleet allows."""
    names = list(rng.permutation(list(fleet)))
    while len(names) < n:
        names += list(rng.permutation(list(fleet)))
    return [SENSOR_MODELS[str(k)] for k in names[:n]]
