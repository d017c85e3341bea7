"""The service's settings: one pydantic-settings model, read from ``BBALIGN_*`` environment variables.

Nested fields use ``__``: ``BBALIGN_ZENOH__MODE=client``, ``BBALIGN_ZENOH__CONNECT='["tcp/10.0.0.2:7447"]'``,
``BBALIGN_ALIGN__BEV__RANGE_M=60``, ``BBALIGN_LIMITS__MAX_BOXES=128``, ``BBALIGN_AUTH__FLEET_KEY=...``. Every
default binds to loopback only: REST on 127.0.0.1, Zenoh listening on tcp/127.0.0.1:7447 with multicast scouting
off. Opening the service to a vehicle network is an explicit choice (``--host``, ``--zenoh-listen``,
``--zenoh-connect``).

Peer authentication is on by default (``auth.mode = "hmac"``): every frame must carry an HMAC-SHA256 made with
the fleet key or the sender's own key (docs/security.md). Only the embedded demo profile (``profile = "demo"``,
``bb-align serve --demo``, ``make run``) turns it off, and the service says so loudly when it starts.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from .config import AlignConfig

VEHICLE_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"  # one Zenoh key chunk: no '/', '*', '$', '?', '#'
FLEET_KEY_ID = "fleet"  # the key id of the shared fleet key (per-peer keys use the vehicle id)
MIN_KEY_CHARS = 16
_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")
_ZENOH_FRAME_OVERHEAD = 64 * 1024  # Zenoh headers around one message (the rx limit is the payload limit + this)


class ZenohTls(BaseModel):
    """TLS for ``tls/`` (and ``quic/``) endpoints: PEM files; ``mtls`` also requires and checks peer certificates.

    These map onto Zenoh's ``transport/link/tls/*`` configuration keys (docs/security.md)."""

    model_config = ConfigDict(extra="forbid")

    root_ca_certificate: Path | None = Field(None, description="CA that signed the other side's certificate")
    certificate: Path | None = Field(None, description="this node's certificate (listen and, with mtls, connect)")
    private_key: Path | None = Field(None, description="this node's private key")
    mtls: bool = Field(False, description="mutual TLS: both sides present a certificate signed by the CA")
    verify_name_on_connect: bool = Field(True, description="the server certificate must name the endpoint host")

    def insert_into(self, cfg) -> None:
        keys = {"root_ca_certificate": self.root_ca_certificate, "listen_certificate": self.certificate,
                "listen_private_key": self.private_key}
        if self.mtls:
            keys.update(connect_certificate=self.certificate, connect_private_key=self.private_key)
        for k, v in keys.items():
            if v is not None:
                cfg.insert_json5(f"transport/link/tls/{k}", json.dumps(str(v)))
        cfg.insert_json5("transport/link/tls/enable_mtls", json.dumps(self.mtls))
        cfg.insert_json5("transport/link/tls/verify_name_on_connect", json.dumps(self.verify_name_on_connect))


class ZenohSettings(BaseModel):
    """One Zenoh config builder shared by the service, the client library and the tests."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="False: REST only (no Zenoh session is opened)")
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"],
                              description="endpoints to listen on, e.g. tcp/127.0.0.1:7447 or tls/host:7447")
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to (routers or peers)")
    multicast_scouting: bool = Field(False, description="find peers by UDP multicast (off: explicit endpoints)")
    prefix: str = Field("bbalign", pattern=r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$",
                        description="first key-expression chunk(s): <prefix>/frames/<vehicle_id>, ...")
    tls: ZenohTls = Field(default_factory=ZenohTls, description="certificates for tls/ endpoints")
    max_message_bytes: int | None = Field(None, ge=1024, description="backstop: Zenoh drops messages far larger "
                                          "than this (its reassembly limit is set to this + 64 KiB) while "
                                          "reassembling them (None: Zenoh's default, 1 GiB)")

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for e in v:
            if not _ENDPOINT.match(e):
                raise ValueError(f"not a Zenoh endpoint (e.g. tcp/127.0.0.1:7447): {e!r}")
        return v

    def to_zenoh_config(self):
        """A ``zenoh.Config`` with mode, endpoints and scouting set (listen endpoints are always explicit).

        Connecting never gives up: a router or peer that is down at start or restarts later is retried."""
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("listen/endpoints", json.dumps(self.listen))
        cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
        cfg.insert_json5("connect/exit_on_failure", "false")
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        if self.max_message_bytes is not None:
            cfg.insert_json5("transport/link/rx/max_message_size",
                             json.dumps(self.max_message_bytes + _ZENOH_FRAME_OVERHEAD))
        if any(e.startswith(("tls/", "quic/")) for e in self.listen + self.connect) or self.tls.mtls:
            self.tls.insert_into(cfg)
        return cfg


class Limits(BaseModel):
    """What a frame may hold. Every message from either door (Zenoh, REST) is checked against these in
    ``bb_align.wire`` (load_frame -> validate_frame) before any pixel is decoded."""

    model_config = ConfigDict(extra="forbid")

    max_message_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="whole message (msgpack or JSON body)")
    max_image_px: int = Field(1024, ge=16, le=8192, description="BV image width/height, pixels")
    max_png_ratio: float = Field(1032.0, gt=1, description="decoded / compressed image bytes (1032: the most "
                                 "deflate can reach; a higher claim is not a real PNG)")
    max_png_chunks: int = Field(4096, ge=3, description="chunks in one PNG file")
    max_boxes: int = Field(256, ge=0, description="boxes per frame")
    max_box_size_m: float = Field(40.0, gt=0, description="box length/width/height")
    max_box_distance_m: float = Field(500.0, gt=0, description="|x|, |y|, |z| of a box centre")
    max_points: int = Field(20_000_000, ge=0, description="the sender's reported raw point count")
    max_stamp_s: float = Field(4_102_444_800.0, gt=0, description="stamps are seconds in [0, this] (2100-01-01)")
    check_stamp_clock: bool = Field(True, description="refuse stamps far from the receiver's clock (False for "
                                    "replays of recorded or simulated data on their own clock)")
    max_stamp_age_s: float = Field(30.0, gt=0, description="a frame stamped this much before the receiver's clock "
                                   "is refused")
    max_stamp_lead_s: float = Field(2.0, ge=0, description="a frame stamped this much after the receiver's clock "
                                    "is refused (clock offset between cars)")
    max_pose_m: float = Field(1.0e7, gt=0, description="|x|, |y|, |z| of a reported pose")
    max_peers: int = Field(64, ge=1, description="distinct senders tracked at once besides the ego (only "
                           "authenticated, valid frames create one); when full, a new sender is refused (503) until "
                           "an idle one is forgotten")
    peer_idle_s: float = Field(60.0, gt=0, description="a sender silent this long is forgotten (queues, replay "
                               "state, metrics labels, bandwidth tallies)")
    intake_queue: int = Field(64, ge=1, description="raw Zenoh messages waiting for the gate (oldest dropped)")
    intake_bytes: int = Field(32 * 1024 * 1024, ge=1024, description="bytes waiting for the gate")

    @model_validator(mode="after")
    def _replay_window_covers_eviction(self) -> "Limits":
        if self.check_stamp_clock and self.peer_idle_s < self.max_stamp_age_s:
            raise ValueError(f"peer_idle_s ({self.peer_idle_s}) must be at least max_stamp_age_s "
                             f"({self.max_stamp_age_s}): a forgotten peer's old frames must be too old to replay")
        return self


class AuthSettings(BaseModel):
    """Peer authentication (HMAC-SHA256 over each frame) and the REST bearer token. Secrets never print."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["hmac", "off"] = Field("hmac", description="hmac: every frame must be signed; off: no checks")
    fleet_key: SecretStr | None = Field(None, description=f"key shared by the fleet (key id {FLEET_KEY_ID!r})")
    peer_keys: dict[str, SecretStr] = Field(default_factory=dict, description="vehicle id -> its own key; a frame "
                                            "signed with one must carry that vehicle id")
    rest_token: SecretStr | None = Field(None, description="REST: every /v1 call and /metrics need "
                                         "'Authorization: Bearer <token>'")

    @field_validator("fleet_key", "rest_token")
    @classmethod
    def _long_enough(cls, v: SecretStr | None) -> SecretStr | None:
        if v is not None and len(v.get_secret_value()) < MIN_KEY_CHARS:
            raise ValueError(f"secrets need at least {MIN_KEY_CHARS} characters (use secrets.token_hex(32))")
        return v

    @field_validator("peer_keys")
    @classmethod
    def _peer_keys(cls, v: dict[str, SecretStr]) -> dict[str, SecretStr]:
        for vid, key in v.items():
            if not re.match(VEHICLE_ID_PATTERN, vid) or vid == FLEET_KEY_ID:
                raise ValueError(f"peer_keys: {vid!r} is not a vehicle id (or is the reserved {FLEET_KEY_ID!r})")
            if len(key.get_secret_value()) < MIN_KEY_CHARS:
                raise ValueError(f"peer_keys[{vid!r}]: keys need at least {MIN_KEY_CHARS} characters")
        return v

    @property
    def has_keys(self) -> bool:
        return self.fleet_key is not None or bool(self.peer_keys)


class Settings(BaseSettings):
    """Everything the ego-side service needs: engine configuration, identity, doors, workers and limits."""

    model_config = SettingsConfigDict(env_prefix="BBALIGN_", env_nested_delimiter="__", extra="forbid")

    profile: Literal["vehicle", "demo"] = Field(
        "vehicle", description="demo: the embedded demo (authentication off, loopback); vehicle: secure defaults")
    ego_id: str = Field("ego", pattern=VEHICLE_ID_PATTERN, description="vehicle id of this car's own frames")
    host: str = Field("127.0.0.1", description="REST bind address (loopback by default)")
    port: int = Field(8000, ge=0, le=65535, description="REST port (0: any free port)")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    auth: AuthSettings = Field(default_factory=AuthSettings)
    align: AlignConfig = Field(default_factory=AlignConfig)
    use_pose_prior: bool = Field(
        True, description="when both frames carry a reported pose, gate descriptor matches by it (align.prior "
        "tolerances, 10 m / 10 deg by default); a wrong report then fails the alignment instead of biasing it")
    limits: Limits = Field(default_factory=Limits)
    ego_cache_size: int = Field(10, ge=1, le=1000, description="K: last ego frames kept with their features")
    prefer_prepared_ego: bool = Field(
        False, description="align against an ego frame whose features are ready when one is within "
        "max_ego_skew_s, rather than preparing the nearest (about halves the ego work at 10 Hz under load; the "
        "result names the ego frame used). Off: the nearest ego frame in time, always")
    max_ego_skew_s: float = Field(0.15, ge=0, description="a peer frame needs an ego frame this close in time")
    workers: int = Field(2, ge=1, le=64, description="engine worker threads (the engine never runs on more)")
    peer_queue_depth: int = Field(1, ge=1, le=64,
                                  description="frames waiting per peer; older ones are dropped (1 = latest only)")
    max_pending_requests: int = Field(8, ge=1, le=1024,
                                      description="REST /v1/align and Zenoh queries waiting for a worker")
    request_timeout_s: float = Field(30.0, gt=0, description="REST /v1/align gives up (504) after this")
    shutdown_timeout_s: float = Field(30.0, gt=0, description="SIGTERM: longest wait for in-flight work")
    bandwidth_window_s: float = Field(5.0, gt=0, description="sliding window of the kbit/s rates")

    @model_validator(mode="after")
    def _demo_profile_turns_auth_off(self) -> "Settings":
        if self.profile == "demo":
            self.auth = self.auth.model_copy(update={"mode": "off"})
        if self.zenoh.max_message_bytes is None:  # Zenoh's own reassembly limit backs up the door's size check
            self.zenoh = self.zenoh.model_copy(update={"max_message_bytes": self.limits.max_message_bytes})
        return self

    def startup_problem(self) -> str | None:
        """Why the service must not start with these settings (None: fine)."""
        if self.auth.mode == "hmac" and not self.auth.has_keys:
            return ("authentication is on (auth.mode='hmac') but no key is configured: set "
                    "BBALIGN_AUTH__FLEET_KEY (or BBALIGN_AUTH__PEER_KEYS), or run the embedded demo without "
                    "authentication (bb-align serve --demo, BBALIGN_PROFILE=demo)")
        return None

    def security_warnings(self) -> list[str]:
        """What the startup banner must say loudly."""
        out = []
        if self.auth.mode == "off":
            why = "demo profile" if self.profile == "demo" else "auth.mode='off'"
            out.append(f"AUTHENTICATION IS OFF ({why}): any process that reaches the endpoints can inject frames")
        exposed = [e for e in self.zenoh.listen if not _loopback_endpoint(e)] if self.zenoh.enabled else []
        if self.host not in ("127.0.0.1", "localhost", "::1"):
            exposed.append(f"REST on {self.host}")
        if exposed and self.auth.mode == "off":
            out.append("NOT LOOPBACK-ONLY WITHOUT AUTHENTICATION: " + ", ".join(exposed))
        if self.host not in ("127.0.0.1", "localhost", "::1") and self.auth.rest_token is None:
            out.append("REST is reachable beyond loopback without a bearer token (auth.rest_token)")
        plain = [e for e in self.zenoh.listen + self.zenoh.connect if not _loopback_endpoint(e)
                 and not e.startswith(("tls/", "quic/"))] if self.zenoh.enabled else []
        if plain:
            out.append("Zenoh traffic beyond loopback is not encrypted (use tls/ endpoints): " + ", ".join(plain))
        return out


def _loopback_endpoint(endpoint: str) -> bool:
    host = endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")
    return endpoint.startswith("unixsock-stream/") or host in ("127.0.0.1", "localhost", "::1")
