"""Schedules without the bench: cron in an IANA zone across DST (Debian cron semantics, via cronsim),
and the scheduler's pass over a real SQLite file, stepped on a clock the test owns. The engine is a
recorder here (what was submitted, with which schedule_id); tests/e2e/test_schedules_e2e.py runs the
same scheduler against the real engine and the emulated bench."""

from __future__ import annotations

from collections import Counter
from datetime import datetime, timedelta, timezone

import pytest
from pydantic import TypeAdapter

from service.api.schemas import SweepCreate
from service.runs.events import EventBroker
from service.runs.schedules import Scheduler, check_cron, check_timezone, create_schedule, next_runs
from service.settings import load_settings
from service.store.storage import Storage

UTC = timezone.utc
BERLIN = check_timezone("Europe/Berlin")
SWEEP = {"grid": {"torque_nm": [2.5], "speed_rpm": [2000], "udc_v": [12]}, "method": "probe"}


def _local_dates(runs):
    return [t.date() for t in runs]


@pytest.mark.parametrize("first_day", [datetime(2027, 3, 20), datetime(2027, 10, 24)])
@pytest.mark.parametrize("cron", ["30 2 * * *", "0 2 * * *", "59 2 * * *", "15 3 * * *"])
def test_preview_across_the_2027_dst_changes_in_berlin_runs_exactly_once_per_day(first_day, cron):
    """2027-03-28 02:00 -> 03:00 (02:xx does not exist: runs once right after the change) and
    2027-10-31 03:00 -> 02:00 (02:xx happens twice: runs once)."""
    runs = next_runs(cron, BERLIN, first_day, 15)
    dates = _local_dates(runs)
    assert dates == [first_day.date() + timedelta(days=i) for i in range(15)], [t.isoformat() for t in runs]
    gaps = [(b - a).total_seconds() / 3600 for a, b in zip(runs, runs[1:])]
    assert all(20 <= g <= 28 for g in gaps), gaps


def test_preview_names_the_times_debian_cron_runs_on_the_change_days():
    spring = next_runs("30 2 * * *", BERLIN, datetime(2027, 3, 27, 12), 2)
    assert [t.isoformat() for t in spring] == ["2027-03-28T03:00:00+02:00", "2027-03-29T02:30:00+02:00"]
    autumn = next_runs("30 2 * * *", BERLIN, datetime(2027, 10, 30, 12), 2)
    assert [t.isoformat() for t in autumn] == ["2027-10-31T02:30:00+02:00", "2027-11-01T02:30:00+01:00"]


@pytest.mark.parametrize(
    "bad, why",
    [
        ("* * * *", "5 fields"),
        ("* * * * * *", "5 fields"),
        ("61 * * * *", "minute takes 0-59"),  # the range, not only the field (issue 30)
        ("* 25 * * *", "hour takes 0-23"),
        ("0 0 30 2 *", "day-of-month"),
        ("a b c d e", "minute"),
        ("", "5 fields"),
    ],
)
def test_cron_refusals_name_the_problem(bad, why):
    with pytest.raises(ValueError, match=why):
        check_cron(bad)


@pytest.mark.parametrize("bad", ["Europe/Berlinx", "CET-1", "../../etc/passwd", "", "/usr/share/zoneinfo/UTC"])
def test_time_zone_must_be_an_iana_name(bad):
    with pytest.raises(ValueError, match="IANA"):
        check_timezone(bad)


class SteppedClock:
    def __init__(self, t: datetime):
        self.t = t

    def __call__(self) -> datetime:
        return self.t


class RecordingEngine:
    """Stands in for Engine.submit_sweep: records each submission, refuses nothing."""

    def __init__(self):
        self.submitted: list[dict] = []

    def submit_sweep(self, grid, method, options, schedule_id=None, regime=None) -> int:
        self.submitted.append(
            {"grid": grid.model_dump(), "method": method, "schedule_id": schedule_id, "regime": regime}
        )
        return None


def _scheduler(db_location, clock, **schedules_settings):
    """A scheduler on `db_location` (tests/conftest.py: each test runs on SQLite and on PostgreSQL)."""
    settings = load_settings(
        environ={},
        overrides={
            "server.db_path": db_location,
            **{f"schedules.{k}": v for k, v in schedules_settings.items()},
        },
    )
    storage = Storage(settings.server.db_path)
    engine = RecordingEngine()
    return storage, engine, settings, Scheduler(storage, engine, settings, EventBroker(), clock=clock)


def _add(storage, settings, clock, cron, zone="Europe/Berlin", name="nightly"):
    sweep = TypeAdapter(SweepCreate).validate_python(SWEEP)
    return create_schedule(storage, settings, clock(), name, cron, zone, sweep)


@pytest.mark.parametrize("first_day", [datetime(2027, 3, 26, tzinfo=UTC), datetime(2027, 10, 29, tzinfo=UTC)])
def test_scheduler_stepped_across_the_dst_change_fires_once_per_local_day(db_location, first_day):
    clock = SteppedClock(first_day)
    storage, engine, settings, scheduler = _scheduler(db_location, clock)
    sid = _add(storage, settings, clock, "30 2 * * *")
    while clock.t < first_day + timedelta(days=5):
        clock.t += timedelta(minutes=10)
        scheduler.tick()
    runs = storage.schedule_runs(sid, limit=100)
    assert [r["outcome"] for r in runs] == ["started"] * 5, runs
    per_day = Counter(datetime.fromisoformat(r["due_at"]).astimezone(BERLIN).date() for r in runs)
    assert sorted(per_day.values()) == [1] * 5 and len(per_day) == 5, per_day
    assert all(s["schedule_id"] == sid and s["method"] == "probe" for s in engine.submitted)
    assert len(engine.submitted) == 5


def test_a_firing_missed_within_grace_runs_once_and_older_ones_are_recorded_missed(db_location):
    """Down for two days with an every-minute schedule: one row sums up the firings beyond grace, the
    latest (within grace) runs once; no flood of sweeps when the service comes back."""
    clock = SteppedClock(datetime(2027, 6, 1, 12, 0, 30, tzinfo=UTC))
    storage, engine, settings, scheduler = _scheduler(db_location, clock, missed_grace_s=3600)
    sid = _add(storage, settings, clock, "* * * * *")
    clock.t += timedelta(days=2)
    scheduler.tick()
    runs = storage.schedule_runs(sid)
    assert [r["outcome"] for r in runs] == ["started", "missed"], runs
    assert runs[0]["due_at"] == "2027-06-03T12:00:00+00:00"
    assert "2879 firing(s)" in runs[1]["note"], runs[1]["note"]
    assert len(engine.submitted) == 1
    scheduler.tick()  # the same time again: nothing new
    assert len(storage.schedule_runs(sid)) == 2


def test_a_firing_beyond_grace_is_recorded_missed_not_run(db_location):
    clock = SteppedClock(datetime(2027, 6, 1, 0, 50, tzinfo=UTC))
    storage, engine, settings, scheduler = _scheduler(db_location, clock, missed_grace_s=3600)
    sid = _add(storage, settings, clock, "0 1 * * *", zone="UTC")
    clock.t = datetime(2027, 6, 1, 3, 20, tzinfo=UTC)
    scheduler.tick()
    (run,) = storage.schedule_runs(sid)
    assert run["outcome"] == "missed" and run["sweep_id"] is None
    assert "missed_grace_s" in run["note"]
    assert engine.submitted == []


def test_a_disabled_schedule_does_not_fire_and_enabling_counts_from_then(db_location):
    from service.runs.schedules import update_schedule

    clock = SteppedClock(datetime(2027, 6, 1, 12, 0, 30, tzinfo=UTC))
    storage, engine, settings, scheduler = _scheduler(db_location, clock)
    sid = _add(storage, settings, clock, "* * * * *")
    update_schedule(storage, settings, clock(), sid, {"enabled": False})
    clock.t += timedelta(minutes=5)
    scheduler.tick()
    assert storage.schedule_runs(sid) == []
    update_schedule(storage, settings, clock(), sid, {"enabled": True})
    scheduler.tick()
    assert storage.schedule_runs(sid) == []  # the five minutes while disabled are not caught up
    clock.t += timedelta(minutes=1)
    scheduler.tick()
    assert [r["outcome"] for r in storage.schedule_runs(sid)] == ["started"]
    assert storage.get_schedule(sid)["sweep"]["method"] == "probe"


def test_cli_schedule_add_list_preview_rm(tmp_path, capsys):
    """`ripplecal schedule ...` on a database file: add (checked like POST /sweeps), list, preview, rm."""
    from service.cli import main

    db = str(tmp_path / "cli.db")
    assert (
        main(
            [
                "schedule",
                "add",
                "--name",
                "nightly",
                "--cron",
                "30 2 * * *",
                "--timezone",
                "Europe/Berlin",
                "--torque",
                "1,2.5",
                "--speed",
                "2000",
                "--method",
                "probe",
                "--db",
                db,
            ]
        )
        == 0
    )
    assert "schedule 1 'nightly': 30 2 * * * (Europe/Berlin)" in capsys.readouterr().out
    assert (
        main(
            [
                "schedule",
                "add",
                "--name",
                "too much",
                "--cron",
                "0 3 * * *",
                "--torque",
                "9",
                "--speed",
                "2000",
                "--udc",
                "99",
                "--db",
                db,
            ]
        )
        == 2
    )
    # each field at fault on a line of its own, with this bench's limit
    refusal = [line for line in capsys.readouterr().err.splitlines() if line.startswith("ripplecal: 1 point(s)")]
    assert len(refusal) == 2, refusal
    assert "torque_nm 9 exceeds the limit of 5 Nm" in refusal[0] and "udc_v 99 outside 6..60 V" in refusal[1]
    assert main(["schedule", "list", "--db", db]) == 0
    listed = capsys.readouterr().out
    assert "nightly" in listed and "never fired" in listed and "too much" not in listed
    assert (
        main(
            [
                "schedule",
                "preview",
                "30 2 * * *",
                "--timezone",
                "Europe/Berlin",
                "--start",
                "2027-03-27",
                "--count",
                "2",
            ]
        )
        == 0
    )
    assert capsys.readouterr().out.split() == ["2027-03-27T02:30:00+01:00", "2027-03-28T03:00:00+02:00"]
    assert main(["schedule", "rm", "1", "--db", db]) == 0
    assert main(["schedule", "rm", "1", "--db", db]) == 1
    assert Storage(db).list_schedules() == []
