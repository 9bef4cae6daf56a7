"""Where a route's refusals point: a route declares, once in its decorator, which part of its request each
kind of refusal is about (`dependencies=[refusals_at(...)]`); the one handler for ServiceError
(service/api/errors.py) reads it to name the field at fault in a 422. The service layer says what is wrong
(`Invalid.at`: "subject", "options", "confirm_large", ...), the route says where that is in its request."""

from __future__ import annotations

from typing import Any

from fastapi import Depends, Request

Location = list[str | int]


def refusals_at(subject: list[str], options: tuple[str, ...] = ("body", "options"), **more: list[str]) -> Any:
    """The route's locations: `subject` is what the request is about (body.grid, path.map_id...): bench
    limits, a plain ValueError and any refusal without a location of its own name it; `options` the
    method's options (a plant-time refusal); `more` any other part a refusal may name (regime=...,
    confirm_large=..., cron=...). A refusal whose part the route does not declare names the subject."""
    locations: dict[str, Location] = {"subject": list(subject), "options": list(options)}
    locations.update({name: list(where) for name, where in more.items()})

    def declare(request: Request) -> None:
        request.state.refusals_at = locations

    return Depends(declare)


_SUBJECT: Any = object()


def location(request: Request, at: str, default: Any = _SUBJECT) -> Location | None:
    """The route's location for a refusal about `at`; a part it does not declare: `default`, else its
    subject. None: the route declares no refusals."""
    locations: dict[str, Location] | None = getattr(request.state, "refusals_at", None)
    if locations is None:
        return None
    return locations.get(at, locations["subject"] if default is _SUBJECT else default)
