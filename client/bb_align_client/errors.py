"""The error the clients raise when the service refuses a message."""

from __future__ import annotations

from bb_align.protocol import ErrorBody


class ServiceError(RuntimeError):
    """The service answered with an error: ``status`` (HTTP status, or None over Zenoh) and its ErrorBody."""

    def __init__(self, status: int | None, body: ErrorBody):
        where = f" ({body.field}, limit {body.limit})" if body.field else ""
        super().__init__(f"{status or 'zenoh'} {body.error}{where}: {body.detail}")
        self.status = status
        self.body = body
