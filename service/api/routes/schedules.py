"""Schedules: a sweep submitted at the times of a cron expression in an IANA time zone
(docs/interfaces.md, Schedules)."""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter, HTTPException, Query, Response, status

from service.api.deps import OperatorDep, ResourceId, ServiceDep
from service.api.errors import error_responses
from service.api.public.schedules import SchedulePreviewPublic, SchedulePublic, schedule_public
from service.api.refusals import refusals_at
from service.api.schemas import ScheduleCreate, ScheduleUpdate
from service.runs.schedules import MAX_PREVIEW_RUNS, iso, preview_runs

router = APIRouter(prefix="/api/v1", tags=["schedules"])

# a schedule's sweep is refused as POST /sweeps refuses it, at body.sweep...; a taken name is a 409
_REFUSED = refusals_at(
    ["body", "sweep", "grid"],
    options=("body", "sweep", "options"),
    confirm_large=["body", "sweep", "confirm_large"],
    orders=["body", "sweep", "orders"],
)


def _public(service, schedule_id: int) -> SchedulePublic:
    row = service.records.get_schedule(schedule_id)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"schedule {schedule_id} does not exist")
    return schedule_public(service.records, row, service.now())


# before /schedules/{schedule_id}, so "preview" is not read as an id
@router.get(
    "/schedules/preview",
    response_model=SchedulePreviewPublic,
    dependencies=[refusals_at(["query", "cron"], timezone=["query", "timezone"], start=["query", "start"])],
)
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
    cron, runs = preview_runs(cron, timezone, start or service.now(), count)
    return SchedulePreviewPublic(cron=cron, timezone=timezone, runs=[iso(t) for t in runs])


@router.post(
    "/schedules",
    status_code=status.HTTP_201_CREATED,
    response_model=SchedulePublic,
    responses=error_responses(400, 401, 403, 409, 413),
    dependencies=[_REFUSED],
)
def create(body: ScheduleCreate, service: ServiceDep, _: OperatorDep) -> SchedulePublic:
    schedule_id = service.create_schedule(
        body.name, body.cron, body.timezone, body.sweep, body.enabled, bench=body.bench or body.sweep.bench
    )
    return _public(service, schedule_id)


@router.get("/schedules", response_model=list[SchedulePublic])
def list_schedules(service: ServiceDep, limit: int = Query(100, ge=1, le=1000)) -> list[SchedulePublic]:
    now = service.now()
    return [schedule_public(service.records, row, now) for row in service.records.list_schedules(limit)]


@router.get("/schedules/{schedule_id}", response_model=SchedulePublic, responses=error_responses(404))
def get(schedule_id: ResourceId, service: ServiceDep) -> SchedulePublic:
    return _public(service, schedule_id)


@router.patch(
    "/schedules/{schedule_id}",
    response_model=SchedulePublic,
    responses=error_responses(400, 401, 403, 404, 409, 413),
    dependencies=[_REFUSED],
)
def update(schedule_id: ResourceId, body: ScheduleUpdate, service: ServiceDep, _: OperatorDep) -> SchedulePublic:
    changes = {name: getattr(body, name) for name in body.model_fields_set}
    service.update_schedule(schedule_id, changes)
    return _public(service, schedule_id)


@router.delete(
    "/schedules/{schedule_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=error_responses(401, 403, 404),
    dependencies=[_REFUSED],
)
def delete(schedule_id: ResourceId, service: ServiceDep, _: OperatorDep) -> Response:
    """No more firings. Its run history stays with its sweeps; a sweep it queued stays queued."""
    service.delete_schedule(schedule_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
