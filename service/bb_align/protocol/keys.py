"""Zenoh key expressions of the wire protocol: where frames go, where poses come back, the align queryable."""

from __future__ import annotations


def frames_key(prefix: str, vehicle_id: str) -> str:
    """Where a car publishes its frames."""
    return f"{prefix}/frames/{vehicle_id}"


def poses_key(prefix: str, ego_id: str, peer_id: str) -> str:
    """Where the ego service publishes T_ego_peer for one peer."""
    return f"{prefix}/poses/{ego_id}/{peer_id}"


def align_key(prefix: str, ego_id: str) -> str:
    """The ego service's queryable: a query carrying a peer frame is answered with a Result."""
    return f"{prefix}/align/{ego_id}"
