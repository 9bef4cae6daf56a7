"""Schedules: a sweep submitted at the times of a cron expression in an IANA time zone
(docs/interfaces.md, Schedules)."""

from __future__ import annotations

import contextlib
from datetime import datetime
from typing import Iterator

from fastapi import APIRouter, HTTPException, Query, Response, status

from service.api.deps import OperatorDep, ResourceId, ServiceDep
from service.api.errors import error_responses, validation_error
from service.api.public import SchedulePreviewPublic, SchedulePublic, schedule_public
from service.api.refusals import refused_at, unprocessable
from service.api.schemas import ScheduleCreate, ScheduleUpdate
from service.runs.plans import SweepTooLarge
from service.runs.schedules import MAX_PREVIEW_RUNS, ScheduleConflict, check_cron, check_timezone, iso, next_runs

router = APIRouter(prefix="/api/v1", tags=["schedules"])


@contextlib.contextmanager
def _refused(schedule_id: int | None = None) -> Iterator[None]:
    """A schedule's sweep is refused as POST /sweeps refuses it, at body.sweep...; a taken name is a 409."""
    with refused_at(["body", "sweep", "grid"], options_at=("body", "sweep", "options")):
        try:
            yield
        except ScheduleConflict as exc:
            raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
        except SweepTooLarge as exc:
            raise unprocessable(
                validation_error(["body", "sweep", "confirm_large"], str(exc), "value_error.confirm_large")
            ) from None
        except KeyError:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"schedule {schedule_id} does not exist") from None


def _public(service, schedule_id: int) -> SchedulePublic:
    row = service.get_schedule(schedule_id)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"schedule {schedule_id} does not exist")
    return schedule_public(service, row, service.now())


# before /schedules/{schedule_id}, so "preview" is not read as an id
@router.get("/schedules/preview", response_model=SchedulePreviewPublic)
def preview(
    service: ServiceDep,
    cron: str = Query(..., min_length=1, max_length=200, description="5 fields, e.g. 30 2 * * *"),
    timezone: str = Query("UTC", min_length=1, max_length=64, description="IANA time zone"),
    start: datetime | None = Query(
        None, description="count from here (ISO 8601; without an offset: wall time in `timezone`); default now"
    ),
    count: int = Query(10, ge=1, le=MAX_PREVIEW_RUNS),
) -> SchedulePreviewPublic:
    """The firings a schedule would have, with Debian cron semantics across DST."""
    try:
        cron = check_cron(cron)
    except ValueError as exc:
        raise unprocessable(validation_error(["query", "cron"], str(exc))) from None
    try:
        zone = check_timezone(timezone)
    except ValueError as exc:
        raise unprocessable(validation_error(["query", "timezone"], str(exc))) from None
    try:
        runs = next_runs(cron, zone, start or service.now(), count)
    except (OverflowError, ValueError) as exc:
        raise unprocessable(validation_error(["query", "start"], f"cannot count from this start: {exc}")) from None
    return SchedulePreviewPublic(cron=cron, timezone=timezone, runs=[iso(t) for t in runs])


@router.post(
    "/schedules",
    status_code=status.HTTP_201_CREATED,
    response_model=SchedulePublic,
    responses=error_responses(400, 401, 403, 409, 413),
)
def create(body: ScheduleCreate, service: ServiceDep, _: OperatorDep) -> SchedulePublic:
    with _refused():
        schedule_id = service.create_schedule(
            body.name, body.cron, body.timezone, body.sweep, body.enabled, bench=body.bench or body.sweep.bench
        )
    return _public(service, schedule_id)


@router.get("/schedules", response_model=list[SchedulePublic])
def list_schedules(service: ServiceDep, limit: int = Query(100, ge=1, le=1000)) -> list[SchedulePublic]:
    now = service.now()
    return [schedule_public(service, row, now) for row in service.list_schedules(limit)]


@router.get("/schedules/{schedule_id}", response_model=SchedulePublic, responses=error_responses(404))
def get(schedule_id: ResourceId, service: ServiceDep) -> SchedulePublic:
    return _public(service, schedule_id)


@router.patch(
    "/schedules/{schedule_id}", response_model=SchedulePublic, responses=error_responses(400, 401, 403, 404, 409, 413)
)
def update(schedule_id: ResourceId, body: ScheduleUpdate, service: ServiceDep, _: OperatorDep) -> SchedulePublic:
    changes = {name: getattr(body, name) for name in body.model_fields_set}
    with _refused(schedule_id):
        service.update_schedule(schedule_id, changes)
    return _public(service, schedule_id)


@router.delete(
    "/schedules/{schedule_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=error_responses(401, 403, 404),
)
def delete(schedule_id: ResourceId, service: ServiceDep, _: OperatorDep) -> Response:
    """No more firings. Its run history stays with its sweeps; a sweep it queued stays queued."""
    with _refused(schedule_id):
        service.delete_schedule(schedule_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
