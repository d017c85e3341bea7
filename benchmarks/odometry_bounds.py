"""How close real 10 Hz poses come to the odometry check's bounds (bb_align.engine.odometry): per drive and per
pattern of dropped frames, the largest step residual against the car's recent motion, in metres and degrees and
as a share of the bound (1.0 would be taken for a jump).

    python benchmarks/odometry_bounds.py --data ../shared/data

Drives: KITTI 08's official poses (4071 frames, 6.8 minutes, residential, turns, stops and starts) and two
Argoverse 2 logs (their ~100 Hz poses taken at 10 Hz).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from bb_align.engine.config import TrackConfig
from bb_align.engine.odometry import motion_residual
from bb_align.lab.real_drives import real_drives

STRIDES = [(1, 1), (1, 2), (2, 1), (1, 3), (2, 2), (1, 5), (5, 5)]  # frames between the three poses a check sees


def worst(poses, stamps, strides, cfg: TrackConfig) -> tuple[float, float, float, float]:
    """(residual m, residual deg, share of the bound m, share of the bound deg), the largest over the drive."""
    s0, s1 = strides
    out = np.zeros(4)
    for k in range(s0 + s1, len(poses)):
        a, b = k - s0 - s1, k - s1
        m, deg, bound_m, bound_deg = motion_residual(
            cfg, (stamps[a], poses[a]), (stamps[b], poses[b]), (stamps[k], poses[k])
        )
        out = np.maximum(out, [m, deg, m / bound_m, deg / bound_deg])
    return tuple(float(v) for v in out)


def main(data: Path = typer.Option(Path("../shared/data"), help="the shared real data folder")) -> None:
    cfg = TrackConfig()
    drives = real_drives(data)
    typer.echo("| drive | frames seen (every s0-th, then s1-th) | residual m | residual deg | of the bound m | deg |")
    typer.echo("| --- | --- | ---: | ---: | ---: | ---: |")
    for name, (poses, stamps) in drives.items():
        for strides in STRIDES:
            m, deg, share_m, share_deg = worst(poses, stamps, strides, cfg)
            typer.echo(
                f"| {name} | {strides[0]}, {strides[1]} | {m:.2f} | {deg:.2f} | {share_m:.2f} | {share_deg:.2f} |"
            )


if __name__ == "__main__":
    typer.run(main)
