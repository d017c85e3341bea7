"""The service's settings: one pydantic-settings model, read from ``BBALIGN_*`` environment variables.

Nested fields use ``__``: ``BBALIGN_ZENOH__MODE=client``, ``BBALIGN_ZENOH__CONNECT='["tcp/10.0.0.2:7447"]'``,
``BBALIGN_ALIGN__BEV__RANGE_M=60``, ``BBALIGN_LIMITS__MAX_BOXES=128``, ``BBALIGN_AUTH__FLEET_KEY=...``. Every
default binds to loopback only: REST on 127.0.0.1, Zenoh listening on tcp/127.0.0.1:7447 with multicast scouting
off. Opening the service to a vehicle network is an explicit choice (``--host``, ``--zenoh-listen``,
``--zenoh-connect``).

Peer authentication is on by default (``auth.mode = "signed"``): every frame must carry an Ed25519 signature by
the sender's own certified key (``auth.ca_cert``: the fleet authority's ``ca.pub``) or, the simpler option, an
HMAC-SHA256 made with the fleet key or the sender's own key (docs/security.md). ``auth.credential`` is the ego's
own identity: only it can sign as the ego id, and it signs every answer. Only the embedded demo profile
(``profile = "demo"``, ``bb-align serve --demo``, ``make run``) turns it off, and the service says so loudly
when it starts.
"""

from __future__ import annotations

import re
from functools import cached_property
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from bb_align.engine.bev import image_size_px
from bb_align.engine.config import AlignConfig
from bb_align.protocol.identity import Credential, TrustStore
from bb_align.protocol.limits import FLEET_KEY_ID, VEHICLE_ID_PATTERN, Limits
from bb_align.protocol.signatures import Keyring
from bb_align.protocol.zenoh_config import ZenohSettings

MIN_KEY_CHARS = 16


class AuthSettings(BaseModel):
    """Peer authentication (Ed25519 vehicle identities and/or HMAC-SHA256), the ego's own identity and the REST
    bearer token. Secrets never print."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["signed", "hmac", "off"] = Field(
        "signed", description="signed (or its old name hmac): every frame must be signed; off: no checks (demo)"
    )
    ca_cert: Path | None = Field(
        None,
        description="the fleet authority's ca.pub (bb-align keys init): frames signed (Ed25519) with a vehicle "
        "certificate it issued are accepted, each vehicle only as itself",
    )
    credential: Path | None = Field(
        None,
        description="this ego car's own credential (bb-align keys issue DIR <ego_id>): only this key may sign as "
        "the ego id, and it signs every answer (Zenoh and REST)",
    )
    fleet_key: SecretStr | None = Field(None, description=f"key shared by the fleet (key id {FLEET_KEY_ID!r})")
    peer_keys: dict[str, SecretStr] = Field(
        default_factory=dict,
        description="vehicle id -> its own key; a frame signed with one must carry that vehicle id",
    )
    rest_token: SecretStr | None = Field(
        None, description="REST: every /v1 call and /metrics need 'Authorization: Bearer <token>'"
    )
    fleet_ids: list[str] | None = Field(
        None,
        description="the fleet key's reserved id space: vehicle ids, or prefixes ending in '*' ('legacy-*'). With "
        "a fleet authority (ca_cert) the fleet key signs only for these (none by default) and no certificate for "
        "them is accepted, so the shared key can never speak for a certified car, seen or not, before or after a "
        "restart. Without an authority: when set, limits the fleet key the same way",
    )
    revocations: Path | None = Field(
        None,
        description="the authority's signed revocation list (bb-align keys revoke DIR <vehicle_id>, DIR/revoked.json):"
        " keys it names are refused; read again when the file changes; an older version than one verified before is"
        " refused, at run time and at start-up",
    )
    revocations_state: Path | None = Field(
        None,
        description="where the highest revocation-list version this service verified is kept, so that an older "
        "list put back is refused at start-up too (default: $XDG_STATE_HOME, else ~/.local/state, "
        "/bb-align/revocations-<authority>.json)",
    )

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

    @field_validator("fleet_ids")
    @classmethod
    def _fleet_ids(cls, v: list[str] | None) -> list[str] | None:
        for entry in v or []:
            vid = entry[:-1] if entry.endswith("*") else entry
            if not (re.match(VEHICLE_ID_PATTERN, vid) or (entry.endswith("*") and vid == "")) or vid == FLEET_KEY_ID:
                raise ValueError(f"fleet_ids: {entry!r} is not a vehicle id or a prefix ending in '*'")
        return v

    @property
    def has_keys(self) -> bool:
        return self.fleet_key is not None or bool(self.peer_keys) or self.ca_cert is not None

    @property
    def required(self) -> bool:
        return self.mode != "off"

    @cached_property
    def trust(self) -> TrustStore | None:
        if self.ca_cert is None:
            return None
        store = TrustStore.load(self.ca_cert)
        if self.revocations is not None:
            store.use_revocations(self.revocations, self.revocations_state or _default_state(self.ca_cert))
        return store

    @cached_property
    def ego_credential(self) -> Credential | None:
        return None if self.credential is None else Credential.load(self.credential)

    def keyring(self, ego_id: str | None = None) -> Keyring:
        """The protocol's keyring for these settings: the trusted authorities, the ego's pinned key, the fleet key
        under ``"fleet"`` and peer keys under their ids."""
        keys = {vid: k.get_secret_value() for vid, k in self.peer_keys.items()}
        if self.fleet_key is not None:
            keys[FLEET_KEY_ID] = self.fleet_key.get_secret_value()
        cred = self.ego_credential
        pinned = {} if cred is None else {cred.vehicle_id: cred.certificate.public_key}
        return Keyring(keys, required=self.required, trust=self.trust, pinned=pinned, fleet_ids=self.fleet_ids)

    def answer_key(self) -> tuple[Credential | str | None, str]:
        """What signs the service's answers, and its key id: the ego's credential (Ed25519), else the fleet key
        (HMAC: any fleet member could forge it), else nothing (demo)."""
        if self.ego_credential is not None:
            return self.ego_credential, self.ego_credential.vehicle_id
        if self.fleet_key is not None:
            return self.fleet_key.get_secret_value(), FLEET_KEY_ID
        return None, FLEET_KEY_ID

    def identity_problem(self, ego_id: str) -> str | None:
        """Why the configured identity files cannot be used (None: fine)."""
        try:
            cred = self.ego_credential
            if self.ca_cert is not None:
                TrustStore.load(self.ca_cert)
        except (OSError, ValueError, KeyError) as e:
            return f"auth.ca_cert / auth.credential: {type(e).__name__}: {e}"
        try:
            trust = self.trust
        except (OSError, ValueError, KeyError) as e:
            return f"auth.revocations: {e}"
        if self.revocations is not None and trust is None:
            return "auth.revocations needs auth.ca_cert (the authority that signed it)"
        if cred is not None:
            if cred.vehicle_id != ego_id:
                return f"auth.credential is {cred.vehicle_id!r}'s, but this service's ego id is {ego_id!r}"
            if trust is None:
                return "auth.credential needs auth.ca_cert (the authority that issued it)"
            try:
                trust.certificate(cred.certificate_bytes)
            except Exception as e:
                return f"auth.credential is not valid under auth.ca_cert: {e}"
        return None


class Settings(BaseSettings):
    """Everything the ego-side service needs: engine configuration, identity, doors, workers and limits."""

    model_config = SettingsConfigDict(env_prefix="BBALIGN_", env_nested_delimiter="__", extra="forbid")

    profile: Literal["vehicle", "demo"] = Field(
        "vehicle", description="demo: the embedded demo (authentication off, loopback); vehicle: secure defaults"
    )
    ego_id: str = Field("ego", pattern=VEHICLE_ID_PATTERN, description="vehicle id of this car's own frames")
    host: str = Field("127.0.0.1", description="REST bind address (loopback by default)")
    port: int = Field(8000, ge=0, le=65535, description="REST port (0: any free port)")
    insecure: bool = Field(
        False,
        description="serve REST beyond loopback without a bearer token (bb-align serve --insecure); otherwise the "
        "service refuses to start that way. Only behind another boundary (a container whose port is published on "
        "the host's loopback)",
    )
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    auth: AuthSettings = Field(default_factory=AuthSettings)
    align: AlignConfig = Field(default_factory=AlignConfig)
    use_pose_prior: bool = Field(
        True,
        description="when both frames carry a reported pose, the pose must lie within align.prior's window of it "
        "(10 m / 10 deg by default), which is searched alone when the search everywhere fails (multi mode; paper "
        "mode gates the descriptor matches by it); a report the images contradict fails the alignment "
        "(disagrees_with_prior) instead of biasing it",
    )
    limits: Limits = Field(default_factory=Limits)
    ego_cache_size: int = Field(10, ge=1, le=1000, description="K: last ego frames kept with their features")
    prefer_prepared_ego: bool = Field(
        False,
        description="align against an ego frame whose features are ready when one is within "
        "max_ego_skew_s, rather than preparing the nearest (about halves the ego work at 10 Hz under load; the "
        "result names the ego frame used). Off: the nearest ego frame in time, always",
    )
    max_ego_skew_s: float = Field(0.15, ge=0, description="a peer frame needs an ego frame this close in time")
    ego_wait_s: float = Field(
        0.1,
        ge=0,
        le=1.0,
        description="a prepared peer frame newer than every cached ego frame waits this long at most for the ego "
        "frame of its sweep (it travels in another Zenoh session and may land a little later); then the nearest "
        "in time within max_ego_skew_s is used. No wait when the ego's next frame (its newest plus its median "
        "period) is of a later sweep: a peer whose LiDAR is not synchronised with the ego's",
    )
    ego_same_sweep_s: float = Field(
        0.02,
        ge=0,
        le=1.0,
        description="an ego frame stamped at most this much before a peer frame counts as of the same sweep (the "
        "wait above ends when one is cached)",
    )
    workers: int = Field(2, ge=1, le=64, description="engine worker threads (the engine never runs on more)")
    unmeasured_after_s: float | None = Field(
        0.05,
        gt=0,
        le=1.0,
        description="with tracking and odometry, a tracked peer frame that waited longer than this for a worker "
        "is answered from its track's stream (the recent frames' evidence carried by both cars' odometry, source "
        "'stream', when that is a valid answer: track.stream_coast_s) instead of measured, so that a service "
        "behind its frames answers each in time instead of dropping some; such an overdue frame also goes before "
        "fresh ones when a tracked frame's turn comes; half a 10 Hz frame period; None: every frame is measured, "
        "in the fair order",
    )
    crosscheck_beside_track: bool = Field(
        True,
        description="with tracking and odometry, a track's periodic cross-check (a full acquisition, ~0.3 s) runs "
        "as a job of its own; the peer's frames are tracked meanwhile instead of waiting behind it (and dropped)",
    )
    crosscheck_share: float | None = Field(
        0.1,
        gt=0,
        le=1,
        description="cross-checks beside tracks (one per track every track.crosscheck_s, each a full acquisition) "
        "use at most this share of the workers' CPU (workers x this, in cores, their engine threads counted) while "
        "tracked frames are waiting (any amount when none are): their number grows with the tracks, and unbounded "
        "they took a worker from 16 peers' results (0.1: 16 peers deliver what 4 do, each track cross-checked "
        "about every 11-13 s at 16 peers, every 5-6 s at 4; docs/performance.md); None: no bound",
    )
    max_frame_wait_s: float | None = Field(
        None,
        gt=0,
        description="a stream frame that waited this long for a worker is dropped before any work (counted as "
        "dropped), for deployments where a late answer is worthless; None (default): a peer's latest frame waits "
        "for its turn however long (a frame whose ego frames are gone is answered stale_ego_frame before any "
        "engine work, and a newer frame replaces it anyway)",
    )
    peer_queue_depth: int = Field(
        1, ge=1, le=64, description="frames waiting per peer; older ones are dropped (1 = latest only)"
    )
    max_pending_requests: int = Field(
        8, ge=1, le=1024, description="REST /v1/align and Zenoh queries waiting for a worker"
    )
    request_timeout_s: float = Field(30.0, gt=0, description="REST /v1/align gives up (504) after this")
    shutdown_timeout_s: float = Field(30.0, gt=0, description="SIGTERM: longest wait for in-flight work")
    bandwidth_window_s: float = Field(5.0, gt=0, description="sliding window of the kbit/s rates")
    malloc_arena_max: int | None = Field(
        2,
        ge=1,
        le=64,
        description="glibc: at most this many malloc arenas (each keeps its own freed memory; glibc's default is 8 "
        "per core, and Zenoh runs over a hundred threads); set at start, an operator's MALLOC_ARENA_MAX wins; "
        "None: glibc's default (server/allocator.py)",
    )
    malloc_mmap_threshold_kb: int | None = Field(
        256,
        ge=0,
        le=32768,
        description="glibc: blocks from this size (KiB) up get a mapping of their own, given back to the system when "
        "freed (a fixed value turns off glibc's adaptive threshold, under which freed multi-MB arrays stayed in the "
        "heaps and the resident size crept); an operator's MALLOC_MMAP_THRESHOLD_ wins; None: glibc's default",
    )
    refusal_notice_interval_s: float = Field(
        0.1,
        ge=0,
        description="a refused Zenoh stream frame signed for its sender is answered with a Refusal on that "
        "sender's results key, at most once per this many seconds per sender (a flood of one car's replayed "
        "frames makes the service publish no faster)",
    )

    @field_validator("ego_id")
    @classmethod
    def _not_the_fleet_id(cls, v: str) -> str:
        if v == FLEET_KEY_ID:
            raise ValueError(f"{FLEET_KEY_ID!r} is reserved for the shared fleet key, not a vehicle id")
        return v

    @model_validator(mode="after")
    def _demo_profile_turns_auth_off(self) -> Settings:
        if self.profile == "demo":
            self.auth = self.auth.model_copy(update={"mode": "off"})
        if self.limits.engine_resolution_m is None or self.limits.max_resampled_px is None:
            # a frame is never resampled beyond the engine's own image (finding: a 100 px PNG at 5 m/px became
            # 1250 px at 0.4 m/px, seconds of CPU and a 300 MB filter bank per odd shape)
            own = image_size_px(self.align.bev)
            self.limits = self.limits.model_copy(
                update={
                    "engine_resolution_m": self.limits.engine_resolution_m or self.align.bev.resolution_m,
                    "max_resampled_px": self.limits.max_resampled_px or own,
                }
            )
        if self.zenoh.max_message_bytes is None:  # Zenoh's own reassembly limit backs up the door's size check
            self.zenoh = self.zenoh.model_copy(update={"max_message_bytes": self.limits.max_message_bytes})
        return self

    def startup_problem(self) -> str | None:
        """Why the service must not start with these settings (None: fine)."""
        if self.auth.required and not self.auth.has_keys:
            return (
                "authentication is on (auth.mode='signed') but nothing to verify frames with is configured: "
                "make credentials (bb-align keys init DIR; bb-align keys issue DIR <ego_id>) and set "
                "BBALIGN_AUTH__CA_CERT=DIR/ca.pub BBALIGN_AUTH__CREDENTIAL=DIR/<ego_id>.cred (or the simpler "
                "BBALIGN_AUTH__FLEET_KEY), or run the embedded demo without authentication (bb-align serve --demo, "
                "BBALIGN_PROFILE=demo)"
            )
        if not _loopback_host(self.host) and self.auth.rest_token is None and not self.insecure:
            return (
                f"REST on {self.host} (beyond loopback) without a bearer token would give anyone on the network every "
                "peer's pose: set BBALIGN_AUTH__REST_TOKEN, or serve on 127.0.0.1, or say --insecure"
            )
        return self.auth.identity_problem(self.ego_id)

    def security_warnings(self) -> list[str]:
        """What the startup banner must say loudly."""
        out = []
        if self.auth.mode == "off":
            why = "demo profile" if self.profile == "demo" else "auth.mode='off'"
            out.append(f"AUTHENTICATION IS OFF ({why}): any process that reaches the endpoints can inject frames")
        exposed = [e for e in self.zenoh.listen if not _loopback_endpoint(e)] if self.zenoh.enabled else []
        if not _loopback_host(self.host):
            exposed.append(f"REST on {self.host}")
        if self.limits.replay:
            out.append(
                "REPLAY PROFILE (limits.replay): replay protection is off; any frame signed by a fleet member, "
                "recorded at any time, is accepted again (recorded or simulated data only, never on a vehicle network)"
            )
        if exposed and self.auth.mode == "off":
            out.append("NOT LOOPBACK-ONLY WITHOUT AUTHENTICATION: " + ", ".join(exposed))
        if not _loopback_host(self.host) and self.auth.rest_token is None:
            out.append("REST is reachable beyond loopback without a bearer token (auth.rest_token; --insecure)")
        plain = (
            [
                e
                for e in self.zenoh.listen + self.zenoh.connect
                if not _loopback_endpoint(e) and not e.startswith(("tls/", "quic/"))
            ]
            if self.zenoh.enabled
            else []
        )
        if plain:
            out.append("Zenoh traffic beyond loopback is not encrypted (use tls/ endpoints): " + ", ".join(plain))
        return out


def _default_state(ca_cert: Path) -> Path:
    """Where a service keeps the highest revocation-list version it verified for the authority of ``ca_cert``."""
    import hashlib
    import os

    base = Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state")
    authority = hashlib.sha256(Path(ca_cert).read_bytes()).hexdigest()[:16]
    return base / "bb-align" / f"revocations-{authority}.json"


def _loopback_host(host: str) -> bool:
    import ipaddress

    try:
        return host == "localhost" or ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _loopback_endpoint(endpoint: str) -> bool:
    host = endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")
    return endpoint.startswith("unixsock-stream/") or _loopback_host(host)
