"""Error answers: one shape (FastAPI's `{"detail": ...}`), documented in the OpenAPI per route, and a
422 handler that can always serialise what it refuses (NaN, inf, deep or huge inputs)."""
from __future__ import annotations

import math
from typing import Any

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from service.api.schemas import ErrorPublic
from service.identification.registry import METHODS

_DESCRIPTIONS = {
    400: "Malformed request (not JSON, or an unreadable header)",
    401: "No bearer token, or the token is unknown or revoked",
    403: "The token's role may not do this",
    404: "No such resource",
    409: "The resource's state does not allow this now (e.g. resume a finished sweep, bench busy)",
    413: "Request body larger than server.max_body_bytes",
    502: "The drive refused or did not answer",
}


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """`responses=` for a route: each status it can answer besides its success."""
    return {code: {"model": ErrorPublic, "description": _DESCRIPTIONS[code]} for code in codes}


def validation_error(loc: list[str | int], msg: str, type_: str = "value_error") -> dict[str, Any]:
    """One item of a 422's detail list, as FastAPI's own (the OpenAPI's HTTPValidationError)."""
    return {"loc": loc, "msg": msg, "type": type_}


def _json_safe(value: Any) -> bool:
    """Echo an input back only when it is a small scalar JSON can carry (NaN and inf cannot)."""
    if value is None or isinstance(value, (bool, int)):
        return not isinstance(value, int) or abs(value) < 2 ** 63
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
            loc = [*loc, "method"]          # an unknown method
        item = validation_error(loc, e["msg"], e["type"])
        if "input" in e and _json_safe(e["input"]):
            item["input"] = e["input"]
        detail.append(item)
    return JSONResponse(status_code=422, content={"detail": detail})
