"""REST clients (httpx): sync ``AlignClient`` and ``AsyncAlignClient``, same methods."""

from __future__ import annotations

import httpx

from bb_align.protocol import (
    FLEET_KEY_ID,
    JSON,
    MSGPACK,
    AnswerTrust,
    Credential,
    ErrorBody,
    Limits,
    Result,
    TrustStore,
    WireError,
    json_align_request,
    pack_align_request,
    peek_frame,
)

from .encode import sign_frame
from .errors import ServiceError
from .trust import answer_trust, bound_to, read_answer


def _align_body(peer: bytes, ego: bytes | None) -> tuple[bytes, str]:
    is_json = [f[:1] == b"{" for f in (peer, ego) if f is not None]
    if all(is_json):
        return json_align_request(peer, ego), JSON
    if not any(is_json):
        return pack_align_request(peer, ego), MSGPACK
    raise ValueError("peer and ego frames must use the same encoding")


def _frame_type(frame: bytes) -> str:
    return JSON if frame[:1] == b"{" else MSGPACK


def _check(r: httpx.Response) -> httpx.Response:
    if r.status_code >= 400:
        try:
            body = ErrorBody.model_validate(r.json())
        except Exception:
            body = ErrorBody(error="unavailable", detail=r.text[:500])
        raise ServiceError(r.status_code, body)
    return r


class _Signer:
    def __init__(self, key: bytes | str | Credential | None, key_id: str):
        self._key, self._key_id = key, key_id

    def __call__(self, frame: bytes | None) -> bytes | None:
        """Sign an unsigned frame when the client has a key (frames signed by the caller stay as they are)."""
        return frame if frame is None or self._key is None else sign_frame(frame, self._key, self._key_id)


def _bound_answer(content: bytes, trust, ego_id: str, peer: bytes) -> Result:
    """The answer, verified as ``ego_id``'s and naming exactly the peer frame sent (its id, seq and stamp): a
    genuine answer to another request, played back, is refused (WireError 409)."""
    answer = read_answer(content, trust, ego_id)
    if trust is not None and not bound_to(answer, *peek_frame(peer, Limits())):
        raise WireError(
            409,
            "replayed",
            f"answer for {answer.peer_id!r} seq {answer.peer_seq} stamp {answer.peer_stamp}: not the frame sent",
            "peer_seq",
        )
    return answer


def _headers(token: str | None) -> dict:
    return {} if token is None else {"authorization": f"Bearer {token}"}


class AlignClient:
    """``AlignClient("http://127.0.0.1:8000", token=..., key=...)``; usable as a context manager.

    ``token``: the service's REST bearer token; ``key``/``key_id``: sign unsigned frames (a Credential: Ed25519; or
    an HMAC key, fleet by default). ``trust`` / ``verify_answers``: every answer is verified (see ZenohPeer): signed
    by ``ego_id`` (the service's ego id, pinned) and naming the peer frame sent (id, seq, stamp)."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        timeout: float = 60.0,
        token: str | None = None,
        key: bytes | str | Credential | None = None,
        key_id: str = FLEET_KEY_ID,
        trust: AnswerTrust | TrustStore | str | None = None,
        verify_answers: bool = True,
        ego_id: str = "ego",
    ):
        self._trust = answer_trust(key, key_id, trust, verify_answers)
        self.ego_id = ego_id
        self._http = httpx.Client(base_url=base_url, timeout=timeout, headers=_headers(token))
        self._sign = _Signer(key, key_id)

    def align(self, peer: bytes, ego: bytes | None = None) -> Result:
        """Align an encoded peer frame against ``ego`` (or the service's cached ego frame nearest in time)."""
        peer = self._sign(peer)
        body, media = _align_body(peer, self._sign(ego))
        r = self._http.post("/v1/align", content=body, headers={"content-type": media, "accept": MSGPACK})
        return _bound_answer(_check(r).content, self._trust, self.ego_id, peer)

    def post_frame(self, frame: bytes) -> dict:
        """Hand in an encoded ego or peer frame (202 Accepted; its result is published like a Zenoh frame's)."""
        frame = self._sign(frame)
        return _check(self._http.post("/v1/frames", content=frame, headers={"content-type": _frame_type(frame)})).json()

    def peers(self) -> dict:
        return _check(self._http.get("/v1/peers")).json()

    def bandwidth(self) -> dict:
        return _check(self._http.get("/v1/bandwidth")).json()

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> AlignClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class AsyncAlignClient:
    """The asyncio twin of AlignClient: ``async with AsyncAlignClient(url) as c: await c.align(frame)``."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        timeout: float = 60.0,
        token: str | None = None,
        key: bytes | str | Credential | None = None,
        key_id: str = FLEET_KEY_ID,
        trust: AnswerTrust | TrustStore | str | None = None,
        verify_answers: bool = True,
        ego_id: str = "ego",
    ):
        self._trust = answer_trust(key, key_id, trust, verify_answers)
        self.ego_id = ego_id
        self._http = httpx.AsyncClient(base_url=base_url, timeout=timeout, headers=_headers(token))
        self._sign = _Signer(key, key_id)

    async def align(self, peer: bytes, ego: bytes | None = None) -> Result:
        peer = self._sign(peer)
        body, media = _align_body(peer, self._sign(ego))
        r = await self._http.post("/v1/align", content=body, headers={"content-type": media, "accept": MSGPACK})
        return _bound_answer(_check(r).content, self._trust, self.ego_id, peer)

    async def post_frame(self, frame: bytes) -> dict:
        frame = self._sign(frame)
        r = await self._http.post("/v1/frames", content=frame, headers={"content-type": _frame_type(frame)})
        return _check(r).json()

    async def peers(self) -> dict:
        return _check(await self._http.get("/v1/peers")).json()

    async def bandwidth(self) -> dict:
        return _check(await self._http.get("/v1/bandwidth")).json()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncAlignClient:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.aclose()
