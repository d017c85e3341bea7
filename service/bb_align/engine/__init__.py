"""The BB-Align engine as a library: numpy arrays in, ``T_ego_peer`` out; no server, no network.

    from bb_align.engine import Aligner, make_bev
    aligner = Aligner()
    result = aligner.align(aligner.prepare(pts_ego, boxes_ego), aligner.prepare(pts_peer, boxes_peer))
    result.T_ego_peer  # 4x4, maps peer-frame points into the ego frame

    follower = Follower(aligner)  # through time: acquire once, then refine each frame from the prediction
    result = follower.step(aligner.prepare(pts_ego, features=False), aligner.prepare(pts_peer, features=False), t)

Imports nothing of the protocol, the server, io or lab (a test checks the import graph). The names below load on
first use, so ``import bb_align.engine.bev`` (the BV encoder a sender needs) does not load the pipeline.
"""

_API = {
    "BevImage": "bev",
    "make_bev": "bev",
    "AlignConfig": "config",
    "BevConfig": "config",
    "BoxConfig": "config",
    "FeatureConfig": "config",
    "MatchConfig": "config",
    "MimConfig": "config",
    "SuccessRule": "config",
    "Aligner": "pipeline",
    "align_clouds": "pipeline",
    "PreparedFrame": "frame",
    "AlignResult": "result",
    "FailureReason": "verdict",
    "TrackConfig": "config",
    "Follower": "follow",
    "PeerTrack": "tracker",
}
__all__ = sorted(_API)


def __getattr__(name: str):
    if name in _API:
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{_API[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
