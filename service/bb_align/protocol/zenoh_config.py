"""One Zenoh config builder shared by the service, the client library and the tests (zenoh is imported only
when a config is built)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

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
        keys = {
            "root_ca_certificate": self.root_ca_certificate,
            "listen_certificate": self.certificate,
            "listen_private_key": self.private_key,
        }
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
    listen: list[str] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"],
        description="endpoints to listen on, e.g. tcp/127.0.0.1:7447 or tls/host:7447",
    )
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to (routers or peers)")
    multicast_scouting: bool = Field(False, description="find peers by UDP multicast (off: explicit endpoints)")
    prefix: str = Field(
        "bbalign",
        pattern=r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$",
        description="first key-expression chunk(s): <prefix>/frames/<vehicle_id>, ...",
    )
    tls: ZenohTls = Field(default_factory=ZenohTls, description="certificates for tls/ endpoints")
    max_message_bytes: int | None = Field(
        None,
        ge=1024,
        description="backstop: Zenoh drops messages far larger "
        "than this (its reassembly limit is set to this + 64 KiB) while "
        "reassembling them (None: Zenoh's default, 1 GiB)",
    )

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
            cfg.insert_json5(
                "transport/link/rx/max_message_size", json.dumps(self.max_message_bytes + _ZENOH_FRAME_OVERHEAD)
            )
        if any(e.startswith(("tls/", "quic/")) for e in self.listen + self.connect) or self.tls.mtls:
            self.tls.insert_into(cfg)
        return cfg
