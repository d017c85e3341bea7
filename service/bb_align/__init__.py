"""bb_align: V2V relative pose recovery from LiDAR BV images and object boxes (BB-Align).

    from bb_align import Aligner, make_bev
    aligner = Aligner()
    result = aligner.align(aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, boxes_peer))
    result.T_ego_peer  # 4x4, maps peer-frame points into the ego frame

One subpackage per concern; imports point one way (engine <- protocol <- server; io and lab use anything):

    bb_align.engine     the method (numpy in, T_ego_peer out)     bb_align.io    clouds, datasets, plots
    bb_align.protocol   wire models, codec, validation, keys      bb_align.lab   simulator, evaluation, bench, soak
    bb_align.server     the ego-side service (Zenoh and REST)     bb_align.cli   the ``bb-align`` command

The engine's public names are re-exported here lazily, so ``import bb_align.protocol`` (what a sender needs)
does not load the engine's stages.
"""

__version__ = "0.1.0"

from .engine import _API as _ENGINE_API
from .engine import __getattr__ as _engine_attr

__all__ = [*sorted(_ENGINE_API), "__version__"]


def __getattr__(name: str):
    if name in _ENGINE_API:
        return _engine_attr(name)
    raise AttributeError(f"module 'bb_align' has no attribute {name!r}")
