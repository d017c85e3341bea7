"""bb_align: V2V relative pose recovery from LiDAR BV images and object boxes (BB-Align), as a library.

    from bb_align import Aligner, make_bev
    aligner = Aligner()
    result = aligner.align(aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, boxes_peer))
    result.T_ego_peer  # 4x4, maps peer-frame points into the ego frame
"""

from .bev import BevImage, make_bev
from .config import AlignConfig, BevConfig, BoxConfig, FeatureConfig, MatchConfig, MimConfig, SuccessRule
from .pipeline import Aligner, PreparedFrame, align_clouds
from .result import AlignResult, FailureReason

__all__ = [
    "AlignConfig", "AlignResult", "Aligner", "BevConfig", "BevImage", "BoxConfig", "FailureReason",
    "FeatureConfig", "MatchConfig", "MimConfig", "PreparedFrame", "SuccessRule", "align_clouds", "make_bev",
]
__version__ = "0.1.0"
