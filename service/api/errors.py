"""Error answers: one shape (FastAPI's `{"detail": ...}`), documented in the OpenAPI per route, and a
422 handler that can always serialise what it refuses (NaN, inf, deep or huge inputs). Never a plain-text
500: storage trouble that passes is a 503 with Retry-After, anything unexpected a JSON 500 whose
`error_id` is in the log line with the traceback. A ServiceError (service/errors.py) answers its kind's
status through the one handler here (`service_error`, registered once in app.py): routes hold no `try`."""

from __future__ import annotations

import json
import logging
import math
import secrets
from typing import Any

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field, ValidationError

from service.api.refusals import location
from service.api.schemas import ErrorPublic
from service.errors import BenchFailed, Conflict, Invalid, NotFound, ServiceError, Unavailable
from service.identification.registry import METHODS
from service.validation_words import in_our_words

log = logging.getLogger(__name__)


class UnavailablePublic(BaseModel):
    """503: the database cannot be used now, for a reason that passes; try again after Retry-After."""

    detail: str = Field(
        ..., description="what is wrong with the database, e.g. 'database ripplecal.db: its disk is full (...)'"
    )
    cause: str = Field(
        ..., description="locked | read_only | disk_full | io_error | cannot_open | unreachable | timeout"
    )
    retry_after_s: float = Field(..., description="try again after this many seconds (also the Retry-After header)")


class InternalErrorPublic(BaseModel):
    """500: a fault of the service; the service's log has the traceback under the same error_id."""

    detail: str = Field("internal error", description="always 'internal error' (the cause is in the log)")
    error_id: str = Field(..., description="the id of the log line with the traceback")


_DESCRIPTIONS = {
    400: "Malformed request (not JSON, or an unreadable header)",
    401: "No bearer token, or the token is unknown or revoked",
    403: "The token's role may not do this",
    404: "No such resource",
    409: "The resource's state does not allow this now (e.g. resume a finished sweep, bench busy)",
    413: "Request body larger than server.max_body_bytes",
    429: "Too many unknown or revoked tokens from this client address (server.auth_max_failures per "
    "server.auth_failure_window_s): try again after Retry-After",
    500: "Internal error: the body's error_id names the log line with the traceback",
    502: "The drive refused or did not answer",
    503: "The database cannot be used now (locked by another process, read-only or full filesystem, I/O error): "
    "try again after Retry-After",
}
_MODELS: dict[int, type[BaseModel]] = {500: InternalErrorPublic, 503: UnavailablePublic}
_RETRY_AFTER = {"Retry-After": {"description": "seconds to wait before trying again", "schema": {"type": "integer"}}}


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """`responses=` for a route: each status it can answer besides its success (a route that checks a
    token can also answer 429: service/api/auth_throttle.py)."""
    if 401 in codes:
        codes = (*codes, 429)
    return {
        code: {
            "model": _MODELS.get(code, ErrorPublic),
            "description": _DESCRIPTIONS[code],
            **({"headers": _RETRY_AFTER} if code in (429, 503) else {}),
        }
        for code in codes
    }


# every route can meet storage trouble or a fault of its own (app.include_router adds them to each)
EVERY_ROUTE = error_responses(500, 503)


def validation_error(loc: list[str | int], msg: str, type_: str = "value_error") -> dict[str, Any]:
    """One item of a 422's detail list, as FastAPI's own (the OpenAPI's HTTPValidationError)."""
    return {"loc": loc, "msg": msg, "type": type_}


def _json_safe(value: Any) -> bool:
    """Echo an input back only when it is a small scalar JSON can carry (NaN and inf cannot)."""
    if value is None or isinstance(value, (bool, int)):
        return not isinstance(value, int) or abs(value) < 2**63
    if isinstance(value, float):
        return math.isfinite(value)
    return isinstance(value, str) and len(value) <= 200


async def request_validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    detail = []
    for e in exc.errors():
        loc = [p if isinstance(p, (str, int)) else str(p) for p in e["loc"]]
        # the method union's tag: the field is body.options..., not body.probe.options... (a schedule's
        # sweep likewise: body.sweep.options...)
        at = 2 if loc[:2] == ["body", "sweep"] else 1
        if len(loc) > at and loc[0] == "body" and loc[at] in METHODS:
            del loc[at]
        elif loc in (["body"], ["body", "sweep"]) and e["type"] == "union_tag_invalid":
            loc = [*loc, "method"]  # an unknown method
        if e["type"] == "json_invalid":  # the body as a whole; its loc's second part is a character position
            at_char = f" at character {loc[1]}" if len(loc) > 1 else ""
            detail.append(
                validation_error(
                    ["body"], f"the body is not valid JSON{at_char}: {(e.get('ctx') or {}).get('error')}", e["type"]
                )
            )
            continue
        item = validation_error(loc, in_our_words(e, loc), e["type"])
        if "input" in e and _json_safe(e["input"]):
            item["input"] = e["input"]
        detail.append(item)
    return JSONResponse(status_code=422, content={"detail": detail})


def _invalid_items(exc: Invalid, request: Request) -> list[dict[str, Any]]:
    where = location(request, exc.at) or ["body"]
    if not exc.problems:
        return [validation_error(where, str(exc), exc.error_type)]
    return [validation_error([*where, field], msg, exc.error_type) for field, msg in exc.problems]


# the kinds the handler answers; Unavailable (503 with Retry-After) and the bare root (a fault: 500 with its
# traceback logged) go on to ErrorAnswers, which answers them wherever they come from (a stream, a middleware)
ANSWERED_KINDS: tuple[type[ServiceError], ...] = (NotFound, Conflict, BenchFailed, Invalid)


async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
    """The one answer of every ServiceError kind a route meets: its kind's status (service/errors.py), the
    detail in FastAPI's shape (a 422's items name the field at fault where the route declares it)."""
    if isinstance(exc, Invalid):
        return JSONResponse({"detail": _invalid_items(exc, request)}, status_code=exc.http_status)
    return JSONResponse({"detail": str(exc)}, status_code=exc.http_status)


async def value_error(request: Request, exc: ValueError) -> JSONResponse:
    """A plain ValueError from the service layer on a route that declares its refusals (refusals_at) is a 422
    at the request's subject; a method's options refused by their model, one item per field where the
    route declares `method_options`. Anywhere else it is a fault of the service (500 by ErrorAnswers)."""
    where = location(request, "subject")
    if where is None:
        raise exc
    options_at = location(request, "method_options", default=None)
    if isinstance(exc, ValidationError):  # a model built inside the route: each field at its path, in our words
        at = options_at if options_at is not None else where
        items = []
        for e in exc.errors():
            loc = [*at, *map(str, e["loc"])]
            items.append(validation_error(loc, in_our_words(e, loc), e["type"]))
    else:
        items = [validation_error(where, str(exc))]
    return JSONResponse({"detail": items}, status_code=422)


class ErrorAnswers:
    """Pure ASGI middleware around the whole app (outside the body limit): an Unavailable kind
    (StorageUnavailable) from anywhere below a route (the route, the service, the auth dependency reading
    tokens) answers 503 with Retry-After; any other exception answers 500 as JSON with a short error_id,
    logged with its traceback under the same id. Answers name no server paths: the database is named by its
    file name (StorageUnavailable.public). Once a response has started (a stream), nothing can be answered
    any more: the error is logged and the connection ends."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked_send(message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        what = f"{scope.get('method', '?')} {scope.get('path', '?')}"  # never the query: it may hold a token
        try:
            await self.app(scope, receive, tracked_send)
        except Unavailable as exc:
            log.warning("%s: 503, %s", what, exc)
            if not started:
                # the database named by its file name (StorageUnavailable.public), never a server path
                body = {
                    "detail": getattr(exc, "public", str(exc)),
                    "cause": getattr(exc, "cause", "unavailable"),
                    "retry_after_s": exc.retry_after_s,
                }
                await _answer(send, 503, body, [(b"retry-after", str(max(1, math.ceil(exc.retry_after_s))).encode())])
        except Exception as exc:  # noqa: BLE001 - the one place an unexpected fault becomes an answer
            error_id = secrets.token_hex(4)
            log.error("internal error %s answering %s: %s: %s", error_id, what, type(exc).__name__, exc, exc_info=exc)
            if not started:
                await _answer(send, 500, {"detail": "internal error", "error_id": error_id})


async def _answer(send, status: int, body: dict[str, Any], headers: list[tuple[bytes, bytes]] = ()) -> None:
    data = json.dumps(body).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(data)).encode()), *headers],
        }
    )
    await send({"type": "http.response.body", "body": data})
