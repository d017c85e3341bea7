"""Sender-side encoding, REST and Zenoh clients for bb-align.

    from bb_align_client import encode_frame, AlignClient, ZenohPeer
    frame = encode_frame(points, boxes, vehicle_id="car1", stamp=t, seq=i, pose=T_world_sensor, key=fleet_key)
    with ZenohPeer("car1", connect=["tcp/127.0.0.1:7447"]) as peer:     # or ZenohPeer(..., key=fleet_key)
        peer.publish(frame)                               # the service publishes T_ego_peer on poses/<ego>/car1
        result = peer.request_align(frame, ego_id="ego")  # or ask and wait for the answer
    AlignClient("http://127.0.0.1:8000", token=rest_token).align(frame).T_ego_peer

Needs only ``bb_align.protocol`` and the BV encoder; Zenoh is loaded when ``ZenohPeer`` / ``PoseStream`` is
first used (a REST-only harness never loads it).
"""

from bb_align.protocol import Credential, Result

from .deskew import deskew_sweep
from .encode import decode_result, encode_frame, sign_frame
from .errors import FrameRefused, ServiceError
from .rest import AlignClient, AsyncAlignClient
from .trust import trust_store

__all__ = [
    "AlignClient",
    "AsyncAlignClient",
    "Credential",
    "FrameRefused",
    "PoseStream",
    "Result",
    "ServiceError",
    "ZenohPeer",
    "decode_result",
    "deskew_sweep",
    "encode_frame",
    "sign_frame",
    "trust_store",
]


def __getattr__(name: str):
    if name in ("ZenohPeer", "PoseStream", "ArrivalLog"):
        from . import zenoh_peer

        return getattr(zenoh_peer, name)
    raise AttributeError(f"module 'bb_align_client' has no attribute {name!r}")
