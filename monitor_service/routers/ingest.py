"""Ingestion: decisions, realized latents and outcomes, single or batched, JSON or msgpack, idempotent by key."""
from __future__ import annotations

import hashlib

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from pydantic import TypeAdapter, ValidationError
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from monitor_service.auth import Principal, require
from monitor_service.db import IdempotencyKey
from monitor_service.encoding import MSGPACK_CONTENT_TYPE, BodyError, decode_body
from monitor_service.schemas import BatchIn, DecisionIn, IngestResult, OutcomeIn, TargetIn, errors
from monitor_service.service import IngestContext, IngestError, ingest, publish_metrics

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


def _handle(request: Request, body: bytes, adapter: TypeAdapter, principal: Principal) -> JSONResponse:
    try:
        payload = adapter.validate_python(decode_body(body, request.headers.get("content-type")))
    except BodyError as exc:
        return _error(400, str(exc))
    except ValidationError as exc:
        return _error(422, validation_message(exc))
    records = payload.records if isinstance(payload, BatchIn) else [payload]
    key = request.headers.get("idempotency-key")
    if key is not None and not 1 <= len(key) <= 128:
        return _error(400, "Idempotency-Key must be 1 to 128 characters; use a UUID per logical request")
    body_hash = hashlib.sha256(body).hexdigest()
    app = request.app
    for attempt in range(2):
        with app.state.write_lock:
            response, ctx = _apply(app, records, principal, key, body_hash, attempt)
        if ctx is not None:
            publish_metrics(ctx)
        if response is not None:
            return response
    raise AssertionError("unreachable")


def _apply(app, records, principal: Principal, key: str | None, body_hash: str, attempt: int):
    """One attempt in one transaction: (response, committed context) or (None, None) to retry once."""
    session = app.state.sessionmaker()
    ctx = None
    try:
        if key is not None:
            prior = session.scalar(
                select(IdempotencyKey).where(IdempotencyKey.api_key_id == principal.key_id, IdempotencyKey.key == key)
            )
            if prior is not None:
                if prior.request_hash != body_hash:
                    return _error(409, f"Idempotency-Key {key!r} was used for a different body; use a new key"), None
                return JSONResponse(prior.response, prior.status_code, headers={"Idempotent-Replayed": "true"}), None
        ctx = IngestContext(session, principal, app.state.settings, app.state.known_dims)
        try:
            ingest(ctx, records)
        except IngestError as exc:
            session.rollback()
            return _error(exc.status, exc.message), None
        result = IngestResult(
            accepted=len(records), decisions=ctx.counts["decision"], targets=ctx.counts["target"],
            outcomes=ctx.counts["outcome"], scored=ctx.scored, alerts_raised=ctx.alerts_raised,
        ).model_dump()
        if key is not None:
            session.add(
                IdempotencyKey(api_key_id=principal.key_id, key=key, request_hash=body_hash, status_code=200, response=result)
            )
        session.commit()
    except IntegrityError:
        # A concurrent request created the same episode or used the same key first: retry once against
        # the now-committed state (which replays the key or sees the existing episode).
        session.rollback()
        if attempt == 1:
            return _error(409, "conflicting concurrent write; retry the request with the same Idempotency-Key"), None
        return None, None
    finally:
        session.close()
    return JSONResponse(result, 200), ctx


def _endpoint(adapter: TypeAdapter, summary: str):
    async def endpoint(request: Request, principal: Principal = Depends(require("robot", exact=True))) -> JSONResponse:
        body = await request.body()
        return await run_in_threadpool(_handle, request, body, adapter, principal)

    endpoint.__doc__ = summary
    return endpoint


for path, model, summary in (
    ("/decisions", DecisionIn, "Record one decision's predicted future latent z_hat for step t + k."),
    ("/targets", TargetIn, "Record the realized latent of an episode's step; scores the decisions aimed at it."),
    ("/outcomes", OutcomeIn, "Record an episode's outcome (success or failure, held-out or not)."),
    ("/batch", BatchIn, "Apply a list of decision/target/outcome records in order, all or nothing."),
):
    router.add_api_route(
        path, _endpoint(TypeAdapter(model), summary), methods=["POST"], response_model=IngestResult, summary=summary,
        responses=errors(404, 409),
        # The body is read by hand (JSON or msgpack, same fields), so document it explicitly; nested models'
        # "$defs" move to the document's components (app.openapi_with_errors).
        openapi_extra={"requestBody": {"required": True, "content": {
            media: {"schema": model.model_json_schema(ref_template="#/components/schemas/{model}")}
            for media in ("application/json", MSGPACK_CONTENT_TYPE)}}},
    )
