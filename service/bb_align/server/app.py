"""The REST door: ``create_app(settings)`` builds the FastAPI app that also runs the Zenoh link and the workers.

Bodies are raw msgpack (``application/msgpack``) or JSON with the PNG as base64 (``application/json``); results
come back as JSON, or msgpack when the request says ``Accept: application/msgpack``. Errors are ErrorBody JSON:
400 undecodable, 401 unsigned/wrongly signed frame or missing bearer token, 403 frame signed with another
vehicle's key, 409 replayed frame, 413 too large, 415 other media types, 422 invalid fields, 503 overloaded,
504 timeout. With ``auth.rest_token`` set, every /v1 call and /metrics need ``Authorization: Bearer <token>``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import hmac
import time
from contextlib import asynccontextmanager
from dataclasses import dataclass

from fastapi import Depends, FastAPI, Request
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse, JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST
from pydantic import BaseModel
from pydantic.json_schema import models_json_schema

from bb_align import __version__
from bb_align.protocol import (
    JSON,
    MSGPACK,
    AlignRequest,
    ErrorBody,
    Frame,
    Result,
    Signed,
    WireError,
    limit_env,
    load_align_request,
    load_frame,
    setting_env,
)

from .bandwidth import BandwidthReport
from .core import AlignService, Unavailable
from .docs_page import docs_html
from .door import Door, KeyRate, SignatureBudget, request_peer
from .peers import PeerStatus
from .settings import Settings

_MEDIA_TYPES = {"application/msgpack": MSGPACK, "application/x-msgpack": MSGPACK, "application/json": JSON}
_REF = "#/components/schemas/{model}"


class Accepted(BaseModel):
    accepted: bool
    kind: str  # "ego" or "peer"
    vehicle_id: str
    seq: int


class Health(BaseModel):
    status: str


class Readiness(BaseModel):
    ready: bool
    workers_running: bool
    zenoh: bool | None  # None: Zenoh disabled
    frames_accepted: bool  # False while frames are still refused as stamped before this service started
    ego_frames: int


def _errors(*codes: int) -> dict:
    text = {
        400: "Undecodable body",
        401: "Missing or wrong bearer token, or an unsigned or wrongly signed frame",
        403: "Frame signed with another vehicle's key",
        409: "Replayed frame: (stamp, seq) not newer than the last accepted from that sender",
        413: "Body too large",
        429: "Too many frames from one sender (limits.rest_rate_hz, after its signature verified)",
        415: "Unsupported media type",
        422: "Invalid field (named in `field`, with the `limit`)",
        503: "Overloaded or shutting down",
        504: "No result within request_timeout_s",
    }
    return {c: {"model": ErrorBody, "description": text[c]} for c in codes}


def _bearer(token: str | None):
    """A dependency refusing requests without ``Authorization: Bearer <token>`` (a no-op without a token)."""
    expected = None if token is None else f"Bearer {token}".encode()

    async def check(request: Request) -> None:
        if expected is None:
            return
        given = request.headers.get("authorization", "").encode("latin-1", "replace")
        if not hmac.compare_digest(given, expected):
            e = WireError(
                401, "unauthenticated", "send 'Authorization: Bearer <token>' (auth.rest_token)", "authorization"
            )
            e.counted = True  # a refused caller, not a refused frame
            raise e

    return Depends(check)


def _binary_body(model: type[BaseModel], description: str, alt: type[BaseModel] | None = None) -> dict:
    ref = {"$ref": _REF.format(model=model.__name__)}
    if alt is not None:
        ref = {"oneOf": [ref, {"$ref": _REF.format(model=alt.__name__)}]}
    return {
        "requestBody": {
            "required": True,
            "description": description,
            "content": {MSGPACK: {"schema": ref}, JSON: {"schema": ref}},
        }
    }


RETRY_AFTER_S = 1  # 429 (a car's REST allowance spent) and 503 overloaded: when to try again


def _error(e: WireError) -> JSONResponse:
    # A body refused for its size is not read to its end: the connection is closed after the answer.
    headers = {"connection": "close"} if e.status == 413 else {}
    if e.status == 429 or (e.status == 503 and e.error == "overloaded"):
        headers["retry-after"] = str(RETRY_AFTER_S)
    return JSONResponse(e.body().model_dump(mode="json"), status_code=e.status, headers=headers or None)


async def _read_body(request: Request, max_bytes: int) -> tuple[bytes, str]:
    """The raw body and its encoding; 415 for other media types, 413 past the limit (read no further)."""
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media not in _MEDIA_TYPES:
        raise WireError(
            415,
            "unsupported_media_type",
            f"send {MSGPACK} or {JSON}, not {media or 'nothing'}",
            "content-type",
            ", ".join(sorted(_MEDIA_TYPES)),
        )
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > max_bytes:
        raise WireError(413, "too_large", f"{declared} bytes exceed the limit of {max_bytes} bytes", "body", max_bytes)
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > max_bytes:
            raise WireError(413, "too_large", f"more than {max_bytes} bytes", "body", max_bytes)
        chunks.append(chunk)
    return b"".join(chunks), _MEDIA_TYPES[media]


def _result_response(request: Request, result: Result, service: AlignService) -> Response:
    """The answer, signed by the service (a Signed envelope around the Result, docs/security.md) when it has a key."""
    accept = request.headers.get("accept", "")
    encoding = MSGPACK if MSGPACK in accept or "application/x-msgpack" in accept else JSON
    return Response(service.encode_answer(result, encoding), media_type=encoding)


def _lifespan(service: AlignService, settings: Settings):
    """The app's lifespan: the service's workers, and the Zenoh link when enabled (stopped in the reverse order)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        link = None
        service.start()
        try:
            if settings.zenoh.enabled:
                from .zenoh_link import ZenohLink

                link = ZenohLink(service, settings)
                await asyncio.to_thread(link.open)
            app.state.link = link
            yield
        finally:
            if link is not None:
                await asyncio.to_thread(link.stop_intake)
            await asyncio.to_thread(service.stop)
            if link is not None:
                await asyncio.to_thread(link.close)

    return lifespan


@dataclass
class _Doors:
    """What the REST routes share: the service, its settings, the bearer guard, the per-sender rate and the REST
    door's own checks before any decoding (door.Door: its own signature budget)."""

    service: AlignService
    settings: Settings
    guard: list
    rate: KeyRate
    door: Door
    loaders: asyncio.Semaphore | None = None  # REST bodies decoded and checked at once (limits.rest_loaders)

    async def load(self, fn):
        """Run a body's decode and checks in a thread, at most ``rest_loaders`` at once (the others wait on the
        event loop, costing nothing): the stream's frames are loaded by one gate thread, and 8 REST threads
        loading one car's bodies at once took the GIL from it, so the other cars' frames reached the workers late
        and were dropped (issue 47, a key holder's REST flood)."""
        if self.loaders is None:
            self.loaders = asyncio.Semaphore(self.settings.limits.rest_loaders)
        async with self.loaders:
            return await asyncio.to_thread(fn)

    def screen(self, data: bytes, encoding: str, request: bool) -> None:
        """What a msgpack body costs before it is decoded (authentication on): the sender it claims is out of REST
        allowance (429, nothing decoded, no signature checked: a key holder's flood is refused for the cost of
        reading its headers); then the door's cheap checks (a stamp outside the clock window, a copy of a
        forgery; replays of verified frames are left to the peer table, whose refusal names the replay profile)
        and the signature under REST's own budget. The frame is
        then loaded (and its signature checked again) as before; a JSON body (the curl convenience) goes
        straight to that. ``request``: the body is an AlignRequest (its peer frame is screened)."""
        if not self.service.keyring.required or encoding != MSGPACK:
            return
        if request:
            peer = request_peer(data)
            if peer is None:
                return  # the loader names what is wrong with it
            data = peer
        try:
            env, claimed = self.door.envelope(data)
        except WireError as e:  # not a signed frame's shape: the loader names what is wrong (its own status and field)
            if e.error == "overloaded":  # the signature budget does not check this signer now: refused, not loaded
                raise
            return
        sender = Door.claimed_sender(env, claimed)
        if self.rate.empty(sender):
            raise self._too_many(sender)
        self.door.precheck(sender, env, claimed, replays=False)
        self.door.verify(env, claimed)

    def _too_many(self, vehicle_id: str) -> WireError:
        limits = self.settings.limits
        return WireError(
            429,
            "overloaded",
            f"{vehicle_id!r} sent more than {limits.rest_rate_hz:g} frames a second (burst {limits.rest_burst:g})"
            " over REST; retry later",
            "vehicle_id",
            limits.rest_rate_hz,
            limit_env("rest_rate_hz"),
        )

    def charge(self, vehicle_id: str) -> None:
        """One frame from a sender whose signature verified: 429 past its allowance (a frame this sender's key did
        not sign was refused before it got here). Not in the demo profile: there an id proves nothing."""
        if self.service.keyring.required and not self.rate.allow(vehicle_id):
            raise self._too_many(vehicle_id)

    async def outcome(self, future: concurrent.futures.Future, accepted: bool) -> Result:
        """The queued request's result, or the WireError that says why there is none."""
        settings = self.settings
        if not accepted:
            e = WireError(
                503,
                "overloaded",
                "the request queue is full, retry later",
                "requests",
                settings.max_pending_requests,
                setting_env("max_pending_requests"),
            )
            e.counted = True  # the service counted it when it refused to queue the request
            raise e
        try:
            outcome = await asyncio.wait_for(asyncio.wrap_future(future), settings.request_timeout_s)
        except TimeoutError:
            raise WireError(504, "timeout", f"no result within {settings.request_timeout_s} s") from None
        if isinstance(outcome, WireError):
            raise outcome
        if isinstance(outcome, Unavailable):
            raise WireError(503, "unavailable", str(outcome))
        if isinstance(outcome, Exception):
            raise outcome
        return outcome


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    service = AlignService(settings)
    token = settings.auth.rest_token
    # With a token, the schema and the interactive docs are behind it too (declared below with the guard).
    # /docs and /redoc are this service's own page (docs_page): FastAPI's load Swagger UI from a CDN.
    docs = {"docs_url": None, "redoc_url": None} | ({} if token is None else {"openapi_url": None})
    app = FastAPI(
        **docs,
        title="bb-align",
        version=__version__,
        lifespan=_lifespan(service, settings),
        description="Ego-side V2V pose recovery (BB-Align): peers' BV images and boxes in, T_ego_peer "
        "out. Wire format: proto_schemas/WIRE.md.",
    )
    app.state.settings = settings
    app.state.service = service
    app.state.link = None
    limits = settings.limits
    doors = _Doors(
        service,
        settings,
        [_bearer(None if token is None else token.get_secret_value())],
        KeyRate(limits.rest_rate_hz, limits.rest_burst, max_keys=limits.max_peers * 4 + 16),
        Door(
            service.keyring,
            limits,
            settings.ego_id,
            lambda vid, key: service.peer_table.newest(vid, "frames", key),
            limits.intake_recent_signatures,
            budget=SignatureBudget(limits.signature_share, limits.signature_burst_s),
        ),
    )

    @app.exception_handler(WireError)
    async def _wire_error(_: Request, e: WireError) -> JSONResponse:
        if not getattr(e, "counted", False):
            service.metrics.rejected.labels("rest", e.error).inc()
        return _error(e)

    _add_align_route(app, doors)
    _add_frame_route(app, doors)
    _add_status_routes(app, doors)
    _add_docs_routes(app, doors.guard, token is not None)
    return app


def _add_align_route(app: FastAPI, doors: _Doors) -> None:
    service, limits = doors.service, doors.settings.limits

    @app.post(
        "/v1/align",
        response_model=Result,
        summary="Align a peer frame now and return T_ego_peer",
        responses={
            200: {"content": {MSGPACK: {"schema": {"$ref": _REF.format(model="Result")}}}},
            **_errors(400, 401, 403, 409, 413, 415, 422, 429, 503, 504),
        },
        dependencies=doors.guard,
        openapi_extra=_binary_body(
            AlignRequest,
            "An AlignRequest: `peer` and optionally `ego` (else the "
            "cached ego frame nearest in time to the peer's stamp).",
        ),
    )
    async def align(request: Request) -> Response:
        received = time.perf_counter()
        data, encoding = await _read_body(request, limits.max_message_bytes)

        def load() -> AlignRequest:
            doors.screen(data, encoding, request=True)
            return load_align_request(data, limits, encoding, keyring=service.keyring, now=time.time())

        req = await doors.load(load)
        doors.charge(req.peer.vehicle_id)
        future: concurrent.futures.Future = concurrent.futures.Future()
        accepted = service.submit_request(
            future.set_result,
            frame=req.peer,
            ego=req.ego,
            nbytes=len(data),
            encoding=encoding,
            door="rest",
            received=received,
        )
        return _result_response(request, await doors.outcome(future, accepted), service)


def _add_frame_route(app: FastAPI, doors: _Doors) -> None:
    service, settings = doors.service, doors.settings

    @app.post(
        "/v1/frames",
        response_model=Accepted,
        status_code=202,
        summary="Hand in an ego or peer frame, as if it came over Zenoh",
        responses=_errors(400, 401, 403, 409, 413, 415, 422, 429, 503),
        dependencies=doors.guard,
        openapi_extra=_binary_body(
            Frame,
            "A Frame or a Signed frame (required when authentication is on). "
            "The ego id's frames fill the ego cache; others are aligned and their "
            "results published on Zenoh and listed by /v1/peers.",
            Signed,
        ),
    )
    async def post_frame(request: Request) -> Accepted:
        received = time.perf_counter()
        data, encoding = await _read_body(request, settings.limits.max_message_bytes)

        def load() -> Frame:
            doors.screen(data, encoding, request=False)
            return load_frame(data, settings.limits, encoding, keyring=service.keyring, now=time.time())

        frame = await doors.load(load)
        doors.charge(frame.vehicle_id)
        if not await asyncio.to_thread(service.submit_frame, frame, len(data), encoding, "rest", received):
            raise WireError(503, "unavailable", "the service is shutting down")
        kind = "ego" if frame.vehicle_id == settings.ego_id else "peer"
        return Accepted(accepted=True, kind=kind, vehicle_id=frame.vehicle_id, seq=frame.seq)


def _add_status_routes(app: FastAPI, doors: _Doors) -> None:
    service, settings, guard = doors.service, doors.settings, doors.guard

    @app.get(
        "/v1/peers",
        response_model=dict[str, PeerStatus],
        summary="Each peer's last result and bandwidth",
        responses=_errors(401),
        dependencies=guard,
    )
    async def peers() -> dict[str, PeerStatus]:
        return service.peers()

    @app.get(
        "/v1/bandwidth",
        response_model=BandwidthReport,
        summary="Bytes received per peer and in total",
        responses=_errors(401),
        dependencies=guard,
    )
    async def bandwidth() -> BandwidthReport:
        return service.meter.report()

    @app.get("/healthz", response_model=Health, summary="The process is up")
    async def healthz() -> Health:
        return Health(status="ok")

    @app.get(
        "/readyz",
        response_model=Readiness,
        summary="Workers running, Zenoh open, and frames stamped now accepted",
        responses={503: {"model": Readiness, "description": "Not ready"}},
    )
    async def readyz() -> JSONResponse:
        link = app.state.link
        zenoh_ok = None if not settings.zenoh.enabled else bool(link is not None and link.is_open)
        floor = service.peer_table.not_before  # frames stamped earlier are refused (replays across a restart)
        accepting = floor is None or time.time() >= floor
        r = Readiness(
            ready=service.running and zenoh_ok is not False and accepting,
            workers_running=service.running,
            zenoh=zenoh_ok,
            frames_accepted=accepting,
            ego_frames=len(service.cache),
        )
        return JSONResponse(r.model_dump(), status_code=200 if r.ready else 503)

    _add_metrics_route(app, doors)


def _add_metrics_route(app: FastAPI, doors: _Doors) -> None:
    @app.get(
        "/metrics",
        summary="Prometheus metrics",
        response_class=Response,
        dependencies=doors.guard,
        responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}, **_errors(401)},
    )
    async def metrics() -> Response:
        return Response(doors.service.metrics.exposition(), media_type=CONTENT_TYPE_LATEST)


def _add_docs_routes(app: FastAPI, guard: list, guarded_schema: bool) -> None:
    """The OpenAPI schema (with the binary bodies' models) and the local docs page."""

    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            _, defs = models_json_schema(
                [(AlignRequest, "validation"), (Frame, "validation"), (Signed, "validation")], ref_template=_REF
            )
            schema.setdefault("components", {}).setdefault("schemas", {}).update(defs["$defs"])
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi
    if guarded_schema:

        @app.get("/openapi.json", include_in_schema=False, dependencies=guard)
        async def openapi_json() -> JSONResponse:
            return JSONResponse(app.openapi())

    @app.get("/docs", include_in_schema=False, dependencies=guard)
    @app.get("/redoc", include_in_schema=False, dependencies=guard)
    async def docs_page() -> HTMLResponse:
        return HTMLResponse(docs_html(app.openapi()))
