"""A schedule (a sweep submitted at the times of a cron expression), its firings and a preview."""

from __future__ import annotations

from datetime import datetime
from typing import TYPE_CHECKING, Any, Mapping
from zoneinfo import ZoneInfo

from pydantic import BaseModel, Field

from service.runs.schedules import iso, next_runs

if TYPE_CHECKING:
    from service.calibration_service import Records


class ScheduleRunPublic(BaseModel):
    """One firing of a schedule and what came of it."""

    id: int
    due_at: str = Field(description="when it fell due, ISO 8601 in the schedule's time zone")
    fired_at: str = Field(description="when the scheduler handled it, ISO 8601 in the schedule's time zone")
    outcome: str = Field(
        description="started (the bench was free) | queued (behind a run in progress) | skipped "
        "(this schedule's previous sweep still waits) | missed (the service was down "
        "longer than schedules.missed_grace_s) | failed (the sweep was refused)"
    )
    sweep_id: int | None = None
    sweep_state: str | None = Field(None, description="the state of that sweep now")
    note: str | None = None


class SchedulePublic(BaseModel):
    id: int
    name: str
    bench: str | None = Field(None, description="the bench whose service fires it")
    cron: str = Field(description="5 fields: minute hour day-of-month month day-of-week (Debian cron)")
    timezone: str = Field(description="IANA time zone the cron is read in")
    sweep: dict[str, Any] = Field(description="the sweep each firing submits: grid, method, options, confirm_large")
    enabled: bool
    created_at: str
    updated_at: str
    next_runs: list[str] = Field(description="the next firings, ISO 8601 with offset (empty while disabled)")
    runs: list[ScheduleRunPublic] = Field(description="recent firings, newest first")


class SchedulePreviewPublic(BaseModel):
    cron: str
    timezone: str
    runs: list[str] = Field(description="the firings after `start`, ISO 8601 with the zone's offset")


def schedule_public(
    records: Records, row: Mapping[str, Any], now: datetime, next_count: int = 5, run_count: int = 20
) -> SchedulePublic:
    """`now`: the scheduler's clock (aware), from which next_runs are counted."""
    zone = ZoneInfo(row["timezone"])

    def local(text: str) -> str:
        return iso(datetime.fromisoformat(text).astimezone(zone))

    upcoming = next_runs(row["cron"], zone, now, next_count) if row["enabled"] else []
    runs = [
        ScheduleRunPublic(
            id=r["id"],
            due_at=local(r["due_at"]),
            fired_at=local(r["fired_at"]),
            outcome=r["outcome"],
            sweep_id=r["sweep_id"],
            sweep_state=r["sweep_state"],
            note=r["note"],
        )
        for r in records.schedule_runs(row["id"], run_count)
    ]
    return SchedulePublic(
        id=row["id"],
        name=row["name"],
        bench=row.get("bench"),
        cron=row["cron"],
        timezone=row["timezone"],
        sweep=row["sweep"],
        enabled=bool(row["enabled"]),
        created_at=local(row["created_at"]),
        updated_at=local(row["updated_at"]),
        next_runs=[iso(t) for t in upcoming],
        runs=runs,
    )
