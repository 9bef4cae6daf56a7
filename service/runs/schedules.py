"""Schedules: a sweep submitted at the times of a cron expression in an IANA time zone.

Cron is 5 fields with Debian cron semantics across DST, from `cronsim` (a maintained library that
follows Debian cron): a time that does not exist that day (spring forward) runs once right after
the change, a time that repeats (fall back) runs once. Times are stored in UTC and shown in the
schedule's own zone with their offset.

The scheduler thread fires due schedules through the engine (one sweep per firing, marked with
`schedule_id`). What it handles is kept in the schedule (`last_due_at`), so a service that was down
finds the firings it missed when it starts: the latest runs once if it fell due within
`schedules.missed_grace_s`, every other one is recorded as missed. A schedule whose previous sweep
still waits for the bench gets no second one (that firing is `skipped`): no pile-up overnight.
Time comes from an injectable clock, so tests step it instead of waiting for real minutes.
"""

from __future__ import annotations

import functools
import logging
import threading
from datetime import datetime, timedelta, timezone
from typing import Any, Callable, Protocol
from zoneinfo import ZoneInfo, available_timezones

from cronsim import CronSim, CronSimError

from service.errors import Conflict, Invalid, NotFound
from service.identification.common import MethodOptions
from service.names import check_name
from service.runs.events import EventBroker
from service.runs.identify import check_plant_time, parse_options
from service.runs.lab import is_own_bench
from service.runs.plans import Grid, RegimePlacement, SweepPlan, check_orders, check_sweep_size, plan_grid
from service.settings import Settings
from service.store.records import ScheduleRecord
from service.store.storage import Storage, StorageUnavailable

log = logging.getLogger(__name__)

UTC = timezone.utc
Clock = Callable[[], datetime]
MAX_PREVIEW_RUNS = 100
# a service down longer than this (more than the largest grace) has its older firings summed up,
# not walked one by one (an every-minute schedule down for a month)
_CATCH_UP_WINDOW = timedelta(days=8)
OUTCOMES = ("started", "queued", "skipped", "missed", "failed")


def utc_now() -> datetime:
    return datetime.now(UTC)


def iso(dt: datetime) -> str:
    return dt.isoformat(timespec="seconds") if dt.microsecond == 0 else dt.isoformat(timespec="milliseconds")


def parse_utc(text: str) -> datetime:
    return datetime.fromisoformat(text).astimezone(UTC)


class ScheduleConflict(Conflict, ValueError):
    """The request collides with another schedule (e.g. the same name)."""


# --- cron and zone ----------------------------------------------------------------------------------
@functools.cache
def _zone_names() -> frozenset[str]:
    return frozenset(available_timezones())


def check_timezone(name: str) -> ZoneInfo:
    """An IANA zone name (Europe/Berlin, UTC); anything else (paths, abbreviations like CET-1) is refused."""
    if name not in _zone_names():
        raise ValueError(f"unknown time zone {name[:60]!r}: use an IANA name such as Europe/Berlin or UTC")
    return ZoneInfo(name)


# what each field of a cron expression takes (Debian cron), for the refusal of a bad one
CRON_FIELDS = {
    "minute": "0-59",
    "hour": "0-23",
    "day-of-month": "1-31",
    "day of month": "1-31",
    "month": "1-12 or jan-dec",
    "day-of-week": "0-7 or sun-sat",
    "day of week": "0-7 or sun-sat",
}
CRON_RANGES = "minute 0-59, hour 0-23, day-of-month 1-31, month 1-12, day-of-week 0-7; * , - / allowed"


def check_cron(expr: str) -> str:
    """A 5-field cron expression (minute hour day-of-month month day-of-week) that fires at some time;
    returned with single spaces."""
    fields = expr.split()
    if len(fields) != 5:
        raise ValueError(f"cron needs 5 fields (minute hour day-of-month month day-of-week), got {len(fields)}")
    normal = " ".join(fields)
    try:
        next(CronSim(normal, datetime(2000, 1, 1, tzinfo=UTC)))
    except CronSimError as exc:
        # cronsim names the field ("Bad minute"); say what that field takes
        field = next((f for f in CRON_FIELDS if f in str(exc).lower()), None)
        takes = f" ({field} takes {CRON_FIELDS[field]})" if field else f" (the fields take {CRON_RANGES})"
        raise ValueError(f"cron {normal!r}: {exc}{takes}") from None
    except StopIteration:
        raise ValueError(f"cron {normal!r} never fires") from None
    return normal


def next_runs(cron: str, zone: ZoneInfo, after: datetime, count: int) -> list[datetime]:
    """The first `count` firings strictly after `after` (naive: wall time in `zone`), in `zone`."""
    start = after.replace(tzinfo=zone) if after.tzinfo is None else after.astimezone(zone)
    runs: list[datetime] = []
    it = CronSim(cron, start)
    try:
        while len(runs) < count:
            runs.append(next(it))
    except (StopIteration, OverflowError, ValueError):  # no firing left before year 9999
        pass
    return runs


def preview_runs(cron: str, timezone_name: str, start: datetime, count: int) -> tuple[str, list[datetime]]:
    """A schedule's next `count` firings from `start` (its cron with single spaces, the firings); each
    refusal names the part at fault (Invalid.at: cron, timezone, start)."""
    try:
        cron = check_cron(cron)
    except ValueError as exc:
        raise Invalid(str(exc), at="cron") from None
    try:
        zone = check_timezone(timezone_name)
    except ValueError as exc:
        raise Invalid(str(exc), at="timezone") from None
    try:
        return cron, next_runs(cron, zone, start, count)
    except (OverflowError, ValueError) as exc:
        raise Invalid(f"cannot count from this start: {exc}", at="start") from None


def due_between(cron: str, zone: ZoneInfo, after: datetime, until: datetime) -> tuple[list[datetime], int]:
    """Firings in (after, until]: the ones walked (at most the last _CATCH_UP_WINDOW of them) and how
    many older ones were not walked."""
    older = 0
    if until - after > _CATCH_UP_WINDOW:
        window_start = until - _CATCH_UP_WINDOW
        older = len(_walk(cron, zone, after, window_start, limit=100_000))
        after = window_start
    return _walk(cron, zone, after, until), older


def _walk(cron: str, zone: ZoneInfo, after: datetime, until: datetime, limit: int | None = None) -> list[datetime]:
    found: list[datetime] = []
    it = CronSim(cron, after.astimezone(zone))
    try:
        while limit is None or len(found) < limit:
            t = next(it)
            if t > until:
                break
            found.append(t)
    except (StopIteration, OverflowError, ValueError):
        pass
    return found


# --- the sweep a schedule submits -------------------------------------------------------------------
class SweepRequest(Protocol):
    """The sweep a schedule submits, as the API and the CLI give it (service/api/schemas.py SweepCreate: a
    model per method, built from the registry)."""

    @property
    def grid(self) -> Grid: ...
    @property
    def regime(self) -> RegimePlacement | None: ...
    @property
    def confirm_large(self) -> bool: ...
    @property
    def method(self) -> str: ...
    @property
    def orders(self) -> list[int] | None: ...
    @property
    def options(self) -> MethodOptions: ...
    def model_dump(self, *, mode: str = "python") -> dict[str, Any]: ...


class SweepSubmitter(Protocol):
    """The engine, as the scheduler sees it (service/runs/engine.py Engine.submit_sweep)."""

    def submit_sweep(
        self,
        grid: Grid,
        method: str,
        options: MethodOptions,
        schedule_id: int | None = None,
        regime: RegimePlacement | None = None,
    ) -> int: ...


def check_sweep(settings: Settings, sweep: SweepRequest) -> None:
    """The checks POST /sweeps makes before queueing (size, bench limits of every setpoint, plant time),
    made when the schedule is created, so a schedule cannot fail at 3 am on a request refused at 5 pm."""
    check_orders(sweep.orders, settings.identification.harmonic_order)
    grid = plan_grid(sweep.grid, sweep.regime, settings).grid  # the grid the sweep will measure
    check_sweep_size(grid, sweep.confirm_large, settings.safety)
    SweepPlan.from_grid(grid).dry_run(settings, sweep.options.override_envelope_model)
    check_plant_time(grid.speed_rpm, sweep.method, sweep.options, settings)


# --- the service side of the routes and the CLI ----------------------------------------------------
def create_schedule(
    storage: Storage,
    settings: Settings,
    now: datetime,
    name: str,
    cron: str,
    timezone_name: str,
    sweep: SweepRequest,
    enabled: bool = True,
    bench: str | None = None,
) -> int:
    """`bench`: the bench whose service fires it (default this one's: settings.bench_name). Another bench's
    sweep is checked by that bench's service when it fires (the firing fails with the reason)."""
    check_name(name, "schedule name")  # the API's schema checks it too; the CLI comes here directly
    cron = check_cron(cron)
    check_timezone(timezone_name)
    if is_own_bench(bench, settings.bench_name):
        check_sweep(settings, sweep)
    if storage.schedule_named(name) is not None:
        raise ScheduleConflict(f"a schedule named {name!r} exists already")
    # handled up to now: a new schedule fires from its next time on, never for times before it existed
    return storage.create_schedule(
        name, cron, timezone_name, sweep.model_dump(mode="json"), enabled, iso(now), bench=bench or settings.bench_name
    )


def update_schedule(
    storage: Storage, settings: Settings, now: datetime, schedule_id: int, changes: dict[str, Any]
) -> None:
    """Apply the fields given. A new cron or zone, or enabling, counts from now: no burst of firings for
    times before the change."""
    current = storage.get_schedule(schedule_id)
    if current is None:
        raise NotFound(f"schedule {schedule_id} does not exist")
    fields: dict[str, Any] = {}
    if "name" in changes and changes["name"] != current["name"]:
        other = storage.schedule_named(changes["name"])
        if other is not None and other["id"] != schedule_id:
            raise ScheduleConflict(f"a schedule named {changes['name']!r} exists already")
        fields["name"] = changes["name"]
    if "cron" in changes:
        fields["cron"] = check_cron(changes["cron"])
    if "timezone" in changes:
        check_timezone(changes["timezone"])
        fields["timezone"] = changes["timezone"]
    if "sweep" in changes:
        check_sweep(settings, changes["sweep"])
        fields["sweep"] = changes["sweep"].model_dump(mode="json")
    if "enabled" in changes:
        fields["enabled"] = int(bool(changes["enabled"]))
    restarts = (
        fields.get("cron", current["cron"]) != current["cron"]
        or fields.get("timezone", current["timezone"]) != current["timezone"]
        or (fields.get("enabled") == 1 and not current["enabled"])
    )
    if restarts:
        fields["last_due_at"] = iso(now)
    fields["updated_at"] = iso(now)
    storage.update_schedule(schedule_id, **fields)


def delete_schedule(storage: Storage, now: datetime, schedule_id: int) -> None:
    """No more firings; the row stays (deleted_at) so its run history and sweeps still name it. A sweep
    it already queued stays queued: cancel it like any other."""
    if storage.get_schedule(schedule_id) is None:
        raise NotFound(f"schedule {schedule_id} does not exist")
    storage.update_schedule(schedule_id, enabled=0, deleted_at=iso(now), updated_at=iso(now))


# --- the scheduler thread ---------------------------------------------------------------------------
class Scheduler:
    """Fires due schedules through the engine. `tick()` does one pass; the thread calls it every
    `schedules.tick_s` (and once at start, before the thread, so missed firings are handled by the
    time the service is up)."""

    def __init__(
        self,
        storage: Storage,
        engine: SweepSubmitter,
        settings: Settings,
        broker: EventBroker,
        clock: Clock = utc_now,
    ):
        self.storage, self.engine, self.settings, self.broker, self.clock = storage, engine, settings, broker, clock
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._tick_lock = threading.Lock()
        self.ticks = 0  # passes completed: tests wait on it instead of on wall time

    def start(self) -> None:
        self.tick()
        self._thread = threading.Thread(target=self._loop, name="ripplecal-scheduler", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _loop(self) -> None:
        while not self._stop.wait(self.settings.schedules.tick_s):
            try:
                self.tick()
            except StorageUnavailable as exc:  # the database away (locked, full, its server lost): the next pass
                log.warning("scheduler pass skipped: %s", exc)
            except Exception:  # one bad pass must not end the scheduler
                log.exception("scheduler pass failed")

    def tick(self) -> None:
        with self._tick_lock:
            now = self.clock()
            for schedule in self.storage.list_schedules():
                # a schedule fires only on its bench's service (no bench: from before benches, this one's)
                if schedule["enabled"] and is_own_bench(schedule.get("bench"), self.settings.bench_name):
                    self._handle(schedule, now)
            self.ticks += 1

    def _handle(self, schedule: ScheduleRecord, now: datetime) -> None:
        zone = ZoneInfo(schedule["timezone"])
        due, older = due_between(schedule["cron"], zone, parse_utc(schedule["last_due_at"]), now)
        if not due:
            return
        sid, latest = schedule["id"], due[-1]
        skipped_over = due[:-1]
        if skipped_over or older:
            n = len(skipped_over) + older
            first = iso(skipped_over[0]) if skipped_over else "earlier"
            last = iso(skipped_over[-1]) if skipped_over else "earlier"
            self._record(
                sid,
                skipped_over[-1] if skipped_over else latest,
                now,
                "missed",
                note=f"{n} firing(s) from {first} to {last} fell due while the service was not running",
            )
        age_s = (now - latest).total_seconds()
        if age_s > self.settings.schedules.missed_grace_s:
            self._record(
                sid,
                latest,
                now,
                "missed",
                note=f"fell due {age_s:.0f} s ago, more than schedules.missed_grace_s "
                f"({self.settings.schedules.missed_grace_s:g} s), while the service was not running",
            )
        else:
            self._fire(schedule, latest, now)
        self.storage.update_schedule(sid, last_due_at=iso(latest.astimezone(UTC)))

    def _fire(self, schedule: ScheduleRecord, due: datetime, now: datetime) -> None:
        sid = schedule["id"]
        pending = self.storage.pending_schedule_sweep(sid)
        if pending is not None:
            self._record(
                sid,
                due,
                now,
                "skipped",
                sweep_id=pending,
                note=f"sweep {pending} of this schedule is still waiting for the bench",
            )
            return
        busy = self.storage.bench_busy(self.settings.bench_name)
        request = schedule["sweep"]
        try:
            regime = RegimePlacement.model_validate(request["regime"]) if request.get("regime") else None
            sweep_id = self.engine.submit_sweep(
                Grid.model_validate(request["grid"]),
                request["method"],
                parse_options(request["method"], request.get("options") or {}),
                schedule_id=sid,
                regime=regime,
            )
        except Exception as exc:  # e.g. bench limits tightened since the schedule was made
            log.warning("schedule %s: sweep refused: %s", sid, exc)
            self._record(sid, due, now, "failed", note=f"sweep refused: {exc}")
            return
        self._record(
            sid,
            due,
            now,
            "queued" if busy else "started",
            sweep_id=sweep_id,
            note="the bench was busy: queued behind the run in progress" if busy else None,
        )

    def _record(
        self,
        schedule_id: int,
        due: datetime,
        now: datetime,
        outcome: str,
        sweep_id: int | None = None,
        note: str | None = None,
    ) -> None:
        run_id = self.storage.insert_schedule_run(
            schedule_id, iso(due.astimezone(UTC)), iso(now.astimezone(UTC)), outcome, sweep_id, note
        )
        log.info(
            "schedule %s: firing due %s %s%s",
            schedule_id,
            iso(due),
            outcome,
            f" (sweep {sweep_id})" if sweep_id else "",
        )
        self.broker.publish(
            "schedule.run",
            {
                "schedule_id": schedule_id,
                "run_id": run_id,
                "due_at": iso(due),
                "outcome": outcome,
                "sweep_id": sweep_id,
                "note": note,
            },
        )
