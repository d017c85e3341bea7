"""What a frame may hold, and the identifiers both sides agree on.

Every message from either door (Zenoh, REST) is checked against :class:`Limits` in
:mod:`bb_align.protocol.codec` (load_frame -> validate_frame) before any pixel is decoded.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

VEHICLE_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"  # one Zenoh key chunk: no '/', '*', '$', '?', '#'


FLEET_KEY_ID = "fleet"  # the key id of the shared fleet key (per-peer keys use the vehicle id)


SETTINGS_PREFIX = "BBALIGN_"  # the service's environment prefix (bb_align.server.settings); Limits sit under LIMITS


REPLAY_HINT = "for recorded or simulated data: BBALIGN_LIMITS__REPLAY=true, i.e. `bb-align serve --replay`"


def setting_env(name: str) -> str:
    """The environment variable of a service setting given by its dotted path (``limits.max_boxes`` ->
    ``BBALIGN_LIMITS__MAX_BOXES``): what refusals name, so the user knows which knob governs them."""
    return SETTINGS_PREFIX + name.replace(".", "__").upper()


def limit_env(name: str) -> str:
    """The environment variable of a Limits field (checked, so a renamed field cannot leave a stale name)."""
    if name not in Limits.model_fields:
        raise KeyError(f"Limits has no field {name!r}")
    return setting_env(f"limits.{name}")


class Limits(BaseModel):
    """What a frame may hold. Every message from either door (Zenoh, REST) is checked against these in
    ``bb_align.protocol`` (load_frame -> validate_frame) before any pixel is decoded."""

    model_config = ConfigDict(extra="forbid")

    max_message_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="whole message (msgpack or JSON body)")
    max_image_px: int = Field(1024, ge=16, le=8192, description="BV image width/height, pixels")
    min_image_px: int = Field(16, ge=1, le=1024, description="smallest BV image width/height, pixels (0x0 is no image)")
    max_png_ratio: float = Field(
        1032.0,
        gt=1,
        description="decoded / compressed image bytes (1032: the most "
        "deflate can reach; a higher claim is not a real PNG)",
    )
    max_png_chunks: int = Field(4096, ge=3, description="chunks in one PNG file")
    max_boxes: int = Field(256, ge=0, description="boxes per frame")
    max_box_size_m: float = Field(40.0, gt=0, description="box length/width/height")
    max_box_distance_m: float = Field(500.0, gt=0, description="|x|, |y|, |z| of a box centre")
    max_points: int = Field(20_000_000, ge=0, description="the sender's reported raw point count")
    max_stamp_s: float = Field(4_102_444_800.0, gt=0, description="stamps are seconds in [0, this] (2100-01-01)")
    check_stamp_clock: bool = Field(
        True,
        description="refuse stamps far from the receiver's clock (False for "
        "replays of recorded or simulated data on their own clock; replay implies False)",
    )
    replay: bool = Field(
        False,
        description="recorded or simulated data (bb-align serve --replay): stamps are not compared with the "
        "receiver's clock, and a sender whose (stamp, seq) goes back (a recording played again) starts a new "
        "pass instead of being refused as a replay. Gives up replay protection (docs/security.md)",
    )
    max_stamp_age_s: float = Field(
        30.0, gt=0, description="a frame stamped this much before the receiver's clock is refused"
    )
    max_stamp_lead_s: float = Field(
        2.0,
        ge=0,
        description="a frame stamped this much after the receiver's clock is refused (clock offset between cars)",
    )
    max_pose_m: float = Field(1.0e7, gt=0, description="|x|, |y|, |z| of a reported pose")
    max_peers: int = Field(
        64,
        ge=1,
        description="distinct senders tracked at once besides the ego (only "
        "authenticated, valid frames create one); when full, a new sender is refused (503) until "
        "an idle one is forgotten",
    )
    peer_idle_s: float = Field(
        60.0,
        gt=0,
        description="a sender silent this long is forgotten (queues, replay state, metrics labels, bandwidth tallies)",
    )
    engine_resolution_m: float | None = Field(
        None,
        gt=0,
        description="the engine's BV cell size (the service sets it from align.bev): a peer image at another "
        "resolution is resampled to it",
    )
    max_resampled_px: int | None = Field(
        None,
        ge=16,
        description="largest image side after that resampling (the service sets it to its own BV image side): "
        "a small frame at a coarse resolution cannot make the engine work on a huge image",
    )
    intake_queue: int = Field(
        64, ge=1, description="signed Zenoh messages (signature verified at the door) waiting for the gate"
    )
    intake_bytes: int = Field(32 * 1024 * 1024, ge=1024, description="bytes of those")
    intake_ego_queue: int = Field(16, ge=1, description="the ego's own messages waiting for the gate (own lane)")
    intake_unverified_queue: int = Field(
        64,
        ge=1,
        description="messages waiting for the gate whose signature the door did not accept for their key (queries "
        "that must be answered, a genuine signer under another's key chunk): their own lane, displacing only "
        "each other",
    )
    intake_unverified_bytes: int = Field(8 * 1024 * 1024, ge=1024, description="bytes of those")
    door_queue: int = Field(
        16,
        ge=1,
        description="Zenoh stream messages waiting for the door thread in Zenoh's own FIFO; full, it pushes back "
        "on the senders' links (each message up to max_message_bytes: this bounds that memory too)",
    )
    zenoh_max_sessions: int = Field(
        128,
        ge=2,
        le=4096,
        description="Zenoh sessions (cars, tools, routers; one per remote process) the service's Zenoh takes at "
        "once; Zenoh gets one receive thread more than this, so a session whose messages wait for the door's full "
        "FIFO (it holds one thread while it waits) can never leave another session's link unread",
    )
    rest_rate_hz: float = Field(
        20.0,
        gt=0,
        description="REST: frames a second one verified sender may hand in (/v1/frames and /v1/align together), on "
        "average; past it 429. An empty bucket is refused before decoding or any signature check; only a verified "
        "signature spends it, so nobody spends another car's allowance",
    )
    rest_loaders: int = Field(
        2,
        ge=1,
        le=64,
        description="REST: request bodies decoded and checked at once (in threads; the others wait, costing "
        "nothing): the stream's frames are loaded by one gate thread, which more REST threads at once starve",
    )
    rest_burst: float = Field(40.0, ge=1, description="REST: frames one sender may hand in at once (the bucket)")
    query_queue: int = Field(
        4,
        ge=1,
        description="Zenoh queries waiting for the query thread in Zenoh's own FIFO; full, Zenoh pushes back on the "
        "queriers' links (a Python callback is fed through an unbounded channel: a 4 MB query flood grew the "
        "service by 1.1 GB). Bounds that memory to this many messages of up to max_message_bytes",
    )
    door_share: float = Field(
        0.02,
        gt=0,
        description="most of one core the Zenoh door may spend on the stream messages it refuses (what a keyless "
        "flood of junk can take from the engine), a token bucket of the door thread's CPU-seconds: past it the "
        "door drops unread large messages (door_unread_bytes) under a key chunk refused lately or never accepted "
        "and reads the rest as they come (a flood of small junk meets waits of 1 ms at most). Signature checks "
        "are not counted here (signature_share)",
    )
    signature_share: float = Field(
        0.05,
        gt=0,
        le=1,
        description="per door (Zenoh stream, Zenoh queries, REST): most of one core, on average, spent on signature "
        "checks that fail (a token bucket of CPU-seconds); while it is spent, only senders that verified lately and "
        "failed no check are checked, anything else is refused at once (503 overloaded), never waited for",
    )
    signature_burst_s: float = Field(
        0.02, gt=0, le=10, description="CPU-seconds of failed signature checks a door may spend at once (the bucket)"
    )
    door_burst_s: float = Field(
        0.01,
        gt=0,
        le=10,
        description="CPU-seconds of refusals the Zenoh door may spend at once (door_share's bucket)",
    )
    door_unread_bytes: int = Field(
        256 * 1024,
        ge=1,
        description="while door_share is spent, Zenoh stream messages this large or larger under a key chunk "
        "refused lately or never accepted are dropped before they are copied out of Zenoh (copying one costs "
        "~0.4-1.3 ms from 512 KB up); smaller ones are still read",
    )
    intake_recent_signatures: int = Field(
        4096,
        ge=1,
        description="signatures verified at the Zenoh door remembered, so a byte-for-byte replay is refused there "
        "without a signature check",
    )

    @property
    def clock_checked(self) -> bool:
        """Whether stamps are compared with the receiver's clock (not in the replay profile)."""
        return self.check_stamp_clock and not self.replay

    @model_validator(mode="after")
    def _replay_window_covers_eviction(self) -> Limits:
        if self.clock_checked and self.peer_idle_s < self.max_stamp_age_s:
            raise ValueError(
                f"peer_idle_s ({self.peer_idle_s}) must be at least max_stamp_age_s "
                f"({self.max_stamp_age_s}): a forgotten peer's old frames must be too old to replay"
            )
        return self
