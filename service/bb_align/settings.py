"""The service's settings: one pydantic-settings model, read from ``BBALIGN_*`` environment variables.

Nested fields use ``__``: ``BBALIGN_ZENOH__MODE=client``, ``BBALIGN_ZENOH__CONNECT='["tcp/10.0.0.2:7447"]'``,
``BBALIGN_ALIGN__BEV__RANGE_M=60``, ``BBALIGN_LIMITS__MAX_BOXES=128``. Every default binds to loopback only:
REST on 127.0.0.1, Zenoh listening on tcp/127.0.0.1:7447 with multicast scouting off. Opening the service to a
vehicle network is an explicit choice (``--host``, ``--zenoh-listen``, ``--zenoh-connect``).
"""

from __future__ import annotations

import json
import re
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from .config import AlignConfig

VEHICLE_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"  # one Zenoh key chunk: no '/', '*', '$', '?', '#'
_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")


class ZenohSettings(BaseModel):
    """One Zenoh config builder shared by the service, the client library and the tests."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="False: REST only (no Zenoh session is opened)")
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"],
                              description="endpoints to listen on, e.g. tcp/127.0.0.1:7447")
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to (routers or peers)")
    multicast_scouting: bool = Field(False, description="find peers by UDP multicast (off: explicit endpoints)")
    prefix: str = Field("bbalign", pattern=r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$",
                        description="first key-expression chunk(s): <prefix>/frames/<vehicle_id>, ...")

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for e in v:
            if not _ENDPOINT.match(e):
                raise ValueError(f"not a Zenoh endpoint (e.g. tcp/127.0.0.1:7447): {e!r}")
        return v

    def to_zenoh_config(self):
        """A ``zenoh.Config`` with mode, endpoints and scouting set (listen endpoints are always explicit)."""
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("listen/endpoints", json.dumps(self.listen))
        cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        return cfg


class Limits(BaseModel):
    """What a frame may hold. Every message from either door (Zenoh, REST) is checked against these in
    ``bb_align.wire.validate_frame`` before any pixel is decoded."""

    model_config = ConfigDict(extra="forbid")

    max_message_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="whole message (msgpack or JSON body)")
    max_image_px: int = Field(1024, ge=16, le=8192, description="BV image width/height, pixels")
    max_boxes: int = Field(256, ge=0, description="boxes per frame")
    max_box_size_m: float = Field(40.0, gt=0, description="box length/width/height")
    max_box_distance_m: float = Field(500.0, gt=0, description="|x|, |y|, |z| of a box centre")
    max_points: int = Field(20_000_000, ge=0, description="the sender's reported raw point count")
    max_stamp_s: float = Field(4_102_444_800.0, gt=0, description="stamps are seconds in [0, this] (2100-01-01)")
    max_pose_m: float = Field(1.0e7, gt=0, description="|x|, |y|, |z| of a reported pose")
    max_peers: int = Field(64, ge=1, description="distinct peers tracked; frames from further peers are refused")


class Settings(BaseSettings):
    """Everything the ego-side service needs: engine configuration, identity, doors, workers and limits."""

    model_config = SettingsConfigDict(env_prefix="BBALIGN_", env_nested_delimiter="__", extra="forbid")

    ego_id: str = Field("ego", pattern=VEHICLE_ID_PATTERN, description="vehicle id of this car's own frames")
    host: str = Field("127.0.0.1", description="REST bind address (loopback by default)")
    port: int = Field(8000, ge=0, le=65535, description="REST port (0: any free port)")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    align: AlignConfig = Field(default_factory=AlignConfig)
    use_pose_prior: bool = Field(
        True, description="when both frames carry a reported pose, gate descriptor matches by it (align.prior "
        "tolerances, 10 m / 10 deg by default); a wrong report then fails the alignment instead of biasing it")
    limits: Limits = Field(default_factory=Limits)
    ego_cache_size: int = Field(10, ge=1, le=1000, description="K: last ego frames kept with their features")
    max_ego_skew_s: float = Field(0.15, ge=0, description="a peer frame needs an ego frame this close in time")
    workers: int = Field(2, ge=1, le=64, description="engine worker threads")
    peer_queue_depth: int = Field(1, ge=1, le=64,
                                  description="frames waiting per peer; older ones are dropped (1 = latest only)")
    max_pending_requests: int = Field(8, ge=1, le=1024,
                                      description="REST /v1/align and Zenoh queries waiting for a worker")
    request_timeout_s: float = Field(30.0, gt=0, description="REST /v1/align gives up (504) after this")
    bandwidth_window_s: float = Field(5.0, gt=0, description="sliding window of the kbit/s rates")
