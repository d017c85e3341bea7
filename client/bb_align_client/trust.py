"""What a car trusts for the service's answers: every Result is verified by default (docs/security.md)."""

from __future__ import annotations

from pathlib import Path

from bb_align.protocol import (
    FLEET_KEY_ID,
    AnswerTrust,
    Credential,
    Refusal,
    Result,
    TrustStore,
    WireError,
    load_answer,
    load_result,
)


def answer_trust(
    key: bytes | str | Credential | None,
    key_id: str,
    trust: AnswerTrust | TrustStore | Path | str | None,
    verify_answers: bool,
) -> AnswerTrust | None:
    """``trust``: the fleet authority's ``ca.pub`` (a path or a TrustStore; answers must then be signed with the
    ego's certificate) or an AnswerTrust. Without it, a fleet HMAC ``key`` verifies HMAC-signed answers.
    ``verify_answers=False``: accept unsigned answers (the demo profile only). Otherwise: ValueError, so that
    a car never takes unverified poses by accident."""
    if not verify_answers:
        return None
    fleet = key if isinstance(key, (bytes, str)) and key_id == FLEET_KEY_ID else None
    if isinstance(trust, AnswerTrust):
        return trust
    if isinstance(trust, (str, Path)):
        trust = TrustStore.load(trust)
    if trust is not None or fleet is not None:
        return AnswerTrust(trust, fleet)
    raise ValueError(
        "answers are verified by default: pass trust=<the fleet authority's ca.pub> (or the fleet key as key=), "
        "or verify_answers=False for the unauthenticated demo profile"
    )


def read_answer(
    data: bytes, trust: AnswerTrust | None, ego_id: str | None = None, refusals: bool = False
) -> Result | Refusal:
    """Decode (and, with ``trust``, verify) one answer; with ``ego_id``, it must come from that ego.
    ``refusals``: a Refusal is a valid answer too (a results key carries them); otherwise only a Result is."""
    answer = load_answer(data, trust) if refusals else load_result(data, trust)
    if trust is not None and ego_id is not None and answer.ego_id != ego_id:
        raise WireError(403, "forbidden", f"answer from {answer.ego_id!r}, expected {ego_id!r}", "ego_id", ego_id)
    return answer
