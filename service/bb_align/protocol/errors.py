"""The one error every refusal raises: status, error kind, the offending field and the limit."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .models import ErrorBody


class WireError(ValueError):
    """A message that cannot be used. ``status``: 400 undecodable, 401 unsigned or wrongly signed, 403 signed
    with another vehicle's key, 409 replayed, 413 too large, 415 other media type, 422 invalid field.
    ``setting``: the environment variable of the setting that governs the refusal, when one does (so a user who
    meets a limit knows which knob it is, e.g. ``BBALIGN_LIMITS__MAX_STAMP_AGE_S``)."""

    def __init__(
        self,
        status: int,
        error: str,
        detail: str,
        field: str | None = None,
        limit: Any = None,
        setting: str | None = None,
    ):
        super().__init__(f"{field}: {detail}" if field else detail)
        self.status, self.error, self.detail, self.field, self.limit = status, error, detail, field, limit
        self.setting = setting

    def body(self) -> ErrorBody:
        from .models import ErrorBody  # the models raise WireError: imported here, not at the top

        return ErrorBody(error=self.error, detail=self.detail, field=self.field, limit=self.limit, setting=self.setting)


def too_large(field: str, size: int, limit: int, setting: str | None = None) -> WireError:
    return WireError(413, "too_large", f"{size} bytes exceed the limit of {limit} bytes", field, limit, setting)


def invalid(field: str, detail: str, limit: Any = None, setting: str | None = None) -> WireError:
    return WireError(422, "invalid", detail, field, limit, setting)
