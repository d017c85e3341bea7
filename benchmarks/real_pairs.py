"""The real pairs of ../shared/data under the paper and multi acquisition paths (issue #11 checks).

    PYTHONPATH=service:client:tests .venv/bin/python benchmarks/real_pairs.py [--data /work/shared/data] [--range 80]

KITTI 08 0 vs 49 (16 m; error against the ICP-refined reference), KITTI 0 vs 186 (130 m, no overlap: must fail),
Apollo-SouthBay 38908 (ego) vs 36822 (peer), 28.5 m (T_38908_36822 maps 36822 into 38908).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from bb_align import AlignConfig, Aligner  # noqa: E402
from bb_align.engine.config import AcquireConfig, BevConfig  # noqa: E402
from bb_align.engine.geometry import (
    pose_error,  # noqa: E402
    worst_sigma_m,  # noqa: E402
)
from bb_align.io.clouds import load_cloud  # noqa: E402
from realdata import kitti_scan  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="/work/shared/data", type=Path)
    ap.add_argument("--range", type=float, default=None, dest="range_m")
    args = ap.parse_args()
    d = args.data
    apollo = d / "apollo_southbay_pair"
    pairs = [
        (
            "KITTI 0 vs 49",
            kitti_scan(d, "000000"),
            kitti_scan(d, "000049"),
            np.loadtxt(d / "kitti_seq08_pair" / "T_velo0_velo49_icp_refined.txt"),
        ),
        ("KITTI 0 vs 186 (no overlap)", kitti_scan(d, "000000"), kitti_scan(d, "000186"), None),
        (
            "Apollo 38908 <- 36822",
            load_cloud(apollo / "apollo_21_38908.pcd"),
            load_cloud(apollo / "apollo_21_36822.pcd"),
            np.loadtxt(apollo / "T_38908_36822.txt"),
        ),
    ]
    for mode in ("paper", "multi"):
        cfg = AlignConfig(acquire=AcquireConfig(mode=mode))
        if args.range_m is not None:
            cfg = cfg.model_copy(update={"bev": BevConfig(range_m=args.range_m)})
        al = Aligner(cfg)
        for name, ego, peer, T in pairs:
            r = al.align(al.prepare(ego), al.prepare(peer))
            err = "" if T is None else "t err {:.3f} m, r err {:.3f} deg".format(*pose_error(r.T_ego_peer, T))
            sig = "" if r.covariance is None else f", worst 1-sigma {worst_sigma_m(r.covariance):.3f} m"
            m = "" if r.acquisition is None else f", margin {r.acquisition.margin:.2f}"
            print(
                f"{mode:5s} range {cfg.bev.range_m:.0f} | {name:28s} | success {r.success} ({r.reason}) | {err}"
                f"{sig}{m} | inliers_bv {r.inliers_bv} fitness {r.refine_fitness:.2f}"
            )


if __name__ == "__main__":
    main()
