"""The error the clients raise when the service refuses a message."""

from __future__ import annotations

from bb_align.protocol import ErrorBody, Refusal


class ServiceError(RuntimeError):
    """The service answered with an error: ``status`` (HTTP status, or None over Zenoh) and its ErrorBody
    (``field``, ``limit``, and ``setting``: the environment variable of the setting that governs it)."""

    def __init__(self, status: int | None, body: ErrorBody):
        setting = f", set by {body.setting}" if body.setting and body.setting not in body.detail else ""
        where = f" ({body.field}, limit {body.limit}{setting})" if body.field else ""
        super().__init__(f"{status or 'zenoh'} {body.error}{where}: {body.detail}")
        self.status = status
        self.body = body


class FrameRefused(ServiceError):
    """The service refused one of this car's published frames (Zenoh pub/sub) and said so on its results key:
    ``PoseStream.get`` raises it instead of waiting for a result that will never come. ``status`` is the HTTP
    status the same refusal gets over REST, ``body`` the ErrorBody (``field``, ``limit``, ``setting``),
    ``peer_seq`` / ``peer_stamp`` which frame it was (None when unreadable)."""

    def __init__(self, refusal: Refusal):
        super().__init__(refusal.status, refusal.refused)
        self.refusal = refusal
        self.peer_seq, self.peer_stamp = refusal.peer_seq, refusal.peer_stamp
