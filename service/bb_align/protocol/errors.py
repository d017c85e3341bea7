"""The one error every refusal raises: status, error kind, the offending field and the limit."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .models import ErrorBody


class WireError(ValueError):
    """A message that cannot be used. ``status``: 400 undecodable, 401 unsigned or wrongly signed, 403 signed
    with another vehicle's key, 409 replayed, 413 too large, 415 other media type, 422 invalid field."""

    def __init__(self, status: int, error: str, detail: str, field: str | None = None, limit: Any = None):
        super().__init__(f"{field}: {detail}" if field else detail)
        self.status, self.error, self.detail, self.field, self.limit = status, error, detail, field, limit

    def body(self) -> ErrorBody:
        from .models import ErrorBody  # the models raise WireError: imported here, not at the top

        return ErrorBody(error=self.error, detail=self.detail, field=self.field, limit=self.limit)


def too_large(field: str, size: int, limit: int) -> WireError:
    return WireError(413, "too_large", f"{size} bytes exceed the limit of {limit} bytes", field, limit)


def invalid(field: str, detail: str, limit: Any = None) -> WireError:
    return WireError(422, "invalid", detail, field, limit)
