"""Refusals the routes share: 422 items naming the field at fault (bench limits, plant time)."""

from __future__ import annotations

import contextlib
from typing import Any, Iterator

from fastapi import HTTPException, status

from service.api.errors import validation_error
from service.bench.bench import BenchUnreachable
from service.model.limits import LimitError
from service.runs.identify import PlantTimeError


def unprocessable(*errors: dict[str, Any]) -> HTTPException:
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, list(errors))


def limit_error(exc: LimitError, where: list[str]) -> HTTPException:
    """The bench's safety limits refused a setpoint: one 422 item per operating-point field at fault."""
    if not exc.problems:
        return unprocessable(validation_error(where, str(exc), exc.kind))
    return unprocessable(*(validation_error([*where, field], msg, exc.kind) for field, msg in exc.problems))


@contextlib.contextmanager
def refused_at(setpoints: list[str], options_at: tuple[str, ...] = ("body", "options")) -> Iterator[None]:
    """Submitting a run: a bench not reached at start is a 409 naming the device; bench limits become
    422s at the setpoint fields (`setpoints`, e.g. body.grid), a plant-time refusal a 422 at the options
    (`options_at`), any other ValueError a 422 at the setpoints."""
    try:
        yield
    except BenchUnreachable as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    except LimitError as exc:
        raise limit_error(exc, setpoints) from None
    except PlantTimeError as exc:
        raise unprocessable(validation_error(list(options_at), str(exc), "value_error.plant_time")) from None
    except ValueError as exc:
        raise unprocessable(validation_error(setpoints, str(exc))) from None
