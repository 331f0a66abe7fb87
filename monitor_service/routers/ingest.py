"""Ingestion: decisions, realized latents and outcomes, single or batched, JSON or msgpack, idempotent by key."""
from __future__ import annotations

import contextlib
import hashlib

from fastapi import APIRouter, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from pydantic import TypeAdapter, ValidationError

from monitor_service import metrics
from monitor_service.auth import Principal, authenticate
from monitor_service.encoding import MSGPACK_CONTENT_TYPE, BodyError, decode_body
from monitor_service.ingest import IngestError, IngestStore, StaleState
from monitor_service.ingest.validation import plain_records
from monitor_service.schemas import BatchIn, DecisionIn, IngestResult, OutcomeIn, TargetIn, errors

router = APIRouter(prefix="/v1", tags=["ingest"])


def validation_message(exc: ValidationError) -> str:
    """One line per problem, each naming the field path, e.g. 'records.3.decision.z_hat: latent has NaN ...'."""
    parts = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)


def _error(status: int, message: str) -> JSONResponse:
    return JSONResponse({"detail": message}, status_code=status)


def _handle(request: Request, body: bytes, route: tuple[TypeAdapter, str | None], principal: Principal,
            locked: bool = False) -> JSONResponse:
    """Validate and apply one ingest body under the process's write lock (``locked``: the caller holds it).
    Plain valid records skip pydantic (``ingest/validation.py``); anything else gets its checks and words."""
    adapter, kind = route
    try:
        decoded = decode_body(body, request.headers.get("content-type"))
        records = plain_records(decoded, kind)
        if records is None:
            payload = adapter.validate_python(decoded)
            records = payload.records if isinstance(payload, BatchIn) else [payload]
    except BodyError as exc:
        return _error(400, str(exc))
    except ValidationError as exc:
        return _error(422, validation_message(exc))
    key = request.headers.get("idempotency-key")
    if key is not None and not 1 <= len(key) <= 128:
        return _error(400, "Idempotency-Key must be 1 to 128 characters; use a UUID per logical request")
    body_hash = hashlib.sha256(body).hexdigest() if key is not None else ""
    store: IngestStore = request.app.state.ingest
    for attempt in range(2):   # a conflict with another process is retried once on fresh state
        with contextlib.nullcontext() if locked else request.app.state.write_lock:
            if key is not None:
                prior = store.idempotent_answer(principal.key_id, key)
                if prior is not None:
                    if prior[0] != body_hash:
                        return _error(409, f"Idempotency-Key {key!r} was used for a different body; use a new key")
                    return JSONResponse(prior[2], prior[1], headers={"Idempotent-Replayed": "true"})
            try:
                idem = None if key is None else (principal.key_id, key, body_hash)
                result, req = store.apply(records, principal, idem)
            except IngestError as exc:
                return _error(exc.status, exc.message)
            except StaleState:
                if attempt == 1:
                    return _error(409, "conflicting concurrent write; retry the request with the same Idempotency-Key")
                continue
        metrics.publish(req.observations, req.signal_observations)
        return JSONResponse(result, 200)
    raise AssertionError("unreachable")


async def ingest_response(request: Request, route: tuple[TypeAdapter, str | None]) -> JSONResponse:
    """Authenticate (robot keys only), read the body and apply it: the whole of an ingest request."""
    principal = authenticate(request, "robot", exact=True)
    body = await request.body()
    lock = request.app.state.write_lock
    # Inline on the event loop only when the write lock is free now: a request of another route may hold it until
    # its session's teardown, which the event loop must run, so waiting for it here would never end.
    if request.app.state.ingest.inline and lock.acquire(blocking=False):
        try:
            return _handle(request, body, route, principal, locked=True)
        finally:
            lock.release()
    return await run_in_threadpool(_handle, request, body, route, principal)


def _endpoint(route: tuple[TypeAdapter, str | None], summary: str):
    async def endpoint(request: Request) -> JSONResponse:
        return await ingest_response(request, route)

    endpoint.__doc__ = summary
    return endpoint


ROUTES = (
    ("/decisions", DecisionIn, "Record one decision's predicted future latent z_hat for step t + k."),
    ("/targets", TargetIn, "Record the realized latent of an episode's step; scores the decisions aimed at it."),
    ("/outcomes", OutcomeIn, "Record an episode's outcome (success or failure, held-out or not)."),
    ("/batch", BatchIn, "Apply a list of decision/target/outcome records in order, all or nothing."),
)
# path -> (its validator, the record kind of a single-record route; None for a batch)
ADAPTERS = {"/v1" + path: (TypeAdapter(model), None if model is BatchIn else model.model_fields["kind"].default)
            for path, model, _ in ROUTES}

for path, model, summary in ROUTES:
    router.add_api_route(
        path, _endpoint(ADAPTERS["/v1" + path], summary), methods=["POST"], response_model=IngestResult,
        summary=summary, responses=errors(404, 409),
        # The body is read by hand (JSON or msgpack, same fields), so document it explicitly; nested models'
        # "$defs" move to the document's components (app.openapi_with_errors).
        openapi_extra={"requestBody": {"required": True, "content": {
            media: {"schema": model.model_json_schema(ref_template="#/components/schemas/{model}")}
            for media in ("application/json", MSGPACK_CONTENT_TYPE)}}},
    )


class IngestFastPath:
    """ASGI middleware: a POST to one of the four ingest routes goes straight to :func:`ingest_response`,
    skipping routing, FastAPI's request handling and the exception middleware (measured: most of a
    single-record request's CPU outside the store on a 2-core host). The routes above serve the same function,
    so the documented and the fast path cannot differ. Everything else passes on unchanged."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        route = ADAPTERS.get(scope["path"]) if scope["type"] == "http" and scope["method"] == "POST" else None
        if route is None:
            return await self.app(scope, receive, send)
        try:
            response = await ingest_response(Request(scope, receive), route)
        except HTTPException as exc:   # 401 / 403 from authenticate
            response = JSONResponse({"detail": exc.detail}, exc.status_code, headers=exc.headers)
        await response(scope, receive, send)
