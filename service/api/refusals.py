"""Refusals the routes share: 422 items naming the field at fault (bench limits, plant time)."""
from __future__ import annotations

from typing import Any

from fastapi import HTTPException, status

from service.api.errors import validation_error
from service.limits import LimitError


def unprocessable(*errors: dict[str, Any]) -> HTTPException:
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, list(errors))


def limit_error(exc: LimitError, where: list[str]) -> HTTPException:
    """The bench's safety limits refused a setpoint: one 422 item per operating-point field at fault."""
    if not exc.problems:
        return unprocessable(validation_error(where, str(exc), "value_error.bench_limits"))
    return unprocessable(*(validation_error([*where, field], msg, "value_error.bench_limits")
                           for field, msg in exc.problems))
