"""Schedules end to end: the real service (SQLite file with migrations, engine, emulated bench) and its
API, with the scheduler on a clock the test steps, so an every-minute schedule is tested without
waiting for real minutes. What the scheduler has looked at is known from its pass counter
(`Scheduler.ticks`), never from a sleep."""

from __future__ import annotations

import contextlib
import threading
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator

import pytest
from pydantic import TypeAdapter

from service.api.schemas import SweepCreate
from service.calibration_service import CalibrationService
from service.runs.schedules import create_schedule
from service.settings import load_settings
from service.store.storage import Storage
from tests.support.live_app import bearer, client_for, wait_finished
from tests.support.waiting import wait_until

pytestmark = pytest.mark.e2e
UTC = timezone.utc
API = "/api/v1"
SWEEP = {"grid": {"torque_nm": [2.5], "speed_rpm": [2000], "udc_v": [12]}, "method": "probe"}
TICK_S = 0.1


class SteppedClock:
    def __init__(self, t: datetime):
        self._t = t
        self._lock = threading.Lock()

    def __call__(self) -> datetime:
        with self._lock:
            return self._t

    def set(self, t: datetime) -> None:
        with self._lock:
            self._t = t


def _settings(db: Path, grace_s: float = 3600):
    return load_settings(
        environ={},
        overrides={
            "emulator.speedup": 0.0,
            "server.db_path": str(db),
            "schedules.tick_s": TICK_S,
            "schedules.missed_grace_s": grace_s,
        },
    )


@contextlib.contextmanager
def _service(db: Path, clock: SteppedClock) -> Iterator[CalibrationService]:
    service = CalibrationService(_settings(db), clock=clock)
    service.start(status_period_s=None)
    try:
        yield service
    finally:
        service.stop()


def _passes(service: CalibrationService, n: int = 2) -> None:
    """Let the scheduler finish n more passes over the current clock."""
    target = service.scheduler.ticks + n
    wait_until(lambda: service.scheduler.ticks >= target, timeout_s=30, what=f"{n} scheduler passes")


def _runs(client, schedule_id: int) -> list[dict]:
    return client.get(f"{API}/schedules/{schedule_id}").json()["runs"]


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    clock = SteppedClock(datetime(2027, 6, 1, 12, 0, 30, tzinfo=UTC))
    with _service(tmp_path_factory.mktemp("schedules") / "api.db", clock) as service:
        yield service, client_for(service), bearer(service, "operator"), clock


def test_every_minute_schedule_fires_a_sweep_on_time_and_stops_after_delete(live):
    service, client, operator, clock = live
    clock.set(datetime(2027, 6, 1, 12, 0, 30, tzinfo=UTC))
    r = client.post(
        f"{API}/schedules",
        headers=operator,
        json={"name": "every minute", "cron": "* * * * *", "timezone": "Europe/Berlin", "sweep": SWEEP},
    )
    assert r.status_code == 201, r.text
    schedule = r.json()
    sid = schedule["id"]
    assert schedule["next_runs"][:2] == ["2027-06-01T14:01:00+02:00", "2027-06-01T14:02:00+02:00"]
    assert schedule["runs"] == [] and schedule["enabled"] is True
    _passes(service)
    assert _runs(client, sid) == []  # 12:00:30: nothing due yet

    clock.set(datetime(2027, 6, 1, 12, 1, 0, 500_000, tzinfo=UTC))  # half a second after it fell due
    (run,) = wait_until(lambda: _runs(client, sid), timeout_s=30, what="the first firing")
    assert run["due_at"] == "2027-06-01T14:01:00+02:00"
    assert run["fired_at"] == "2027-06-01T14:01:00.500+02:00"
    assert run["outcome"] == "started" and run["sweep_id"] is not None
    sweep = wait_finished(client, f"{API}/sweeps/{run['sweep_id']}")
    assert sweep["state"] == "done", sweep
    assert sweep["schedule_id"] == sid
    assert sweep["grid"] == {"torque_nm": [2.5], "speed_rpm": [2000.0], "udc_v": [12.0]} and sweep["method"] == "probe"
    assert _runs(client, sid)[0]["sweep_state"] == "done"

    assert client.delete(f"{API}/schedules/{sid}").status_code == 401
    r = client.delete(f"{API}/schedules/{sid}", headers=operator)
    assert r.status_code == 204, r.text
    assert client.get(f"{API}/schedules/{sid}").status_code == 404
    assert sid not in [s["id"] for s in client.get(f"{API}/schedules").json()]
    sweeps_before = {s["id"] for s in client.get(f"{API}/sweeps").json()}
    clock.set(datetime(2027, 6, 1, 12, 3, 0, 500_000, tzinfo=UTC))  # two more minutes have fallen due
    _passes(service)
    assert {s["id"] for s in client.get(f"{API}/sweeps").json()} == sweeps_before
    assert len(service.storage.schedule_runs(sid)) == 1


def test_a_busy_bench_queues_one_pending_run_per_schedule(live):
    """A sweep runs on the bench: the first firing is queued behind it, the next one is skipped (no
    pile-up); once the bench is free the queued sweep runs and the next firing starts."""
    service, client, operator, clock = live
    clock.set(datetime(2027, 6, 2, 12, 0, 30, tzinfo=UTC))
    # 12 points (some 10 s even at speedup 0): the two firings below take a second; it is cancelled after them
    r = client.post(
        f"{API}/sweeps",
        headers=operator,
        json={
            "grid": {"torque_nm": [1.0, 1.5, 2.0, 2.5], "speed_rpm": [1500, 2000, 2500], "udc_v": [12]},
            "method": "probe",
        },
    )
    assert r.status_code == 202, r.text
    manual = r.json()["id"]
    wait_until(
        lambda: client.get(f"{API}/sweeps/{manual}").json()["state"] == "running",
        timeout_s=60,
        what="the manual sweep running",
    )
    r = client.post(
        f"{API}/schedules",
        headers=operator,
        json={"name": "busy", "cron": "* * * * *", "timezone": "UTC", "sweep": SWEEP},
    )
    assert r.status_code == 201, r.text
    sid = r.json()["id"]

    clock.set(datetime(2027, 6, 2, 12, 1, 0, 200_000, tzinfo=UTC))
    (first,) = wait_until(lambda: _runs(client, sid), timeout_s=30, what="the first firing")
    assert first["outcome"] == "queued", first
    assert client.get(f"{API}/sweeps/{first['sweep_id']}").json()["state"] == "queued"
    clock.set(datetime(2027, 6, 2, 12, 2, 0, 200_000, tzinfo=UTC))
    second = wait_until(
        lambda: (runs := _runs(client, sid)) and len(runs) == 2 and runs[0], timeout_s=30, what="the second firing"
    )
    assert second["outcome"] == "skipped" and second["sweep_id"] == first["sweep_id"], second
    assert sum(1 for s in client.get(f"{API}/sweeps").json() if s["schedule_id"] == sid) == 1

    assert client.post(f"{API}/sweeps/{manual}/cancel", headers=operator).status_code == 200
    assert wait_finished(client, f"{API}/sweeps/{first['sweep_id']}")["state"] == "done"
    wait_until(lambda: not service.storage.bench_busy(service.settings.bench_name), timeout_s=60, what="the bench free")
    clock.set(datetime(2027, 6, 2, 12, 3, 0, 200_000, tzinfo=UTC))
    third = wait_until(
        lambda: (runs := _runs(client, sid)) and len(runs) == 3 and runs[0], timeout_s=30, what="the third firing"
    )
    assert third["outcome"] == "started", third
    assert client.patch(f"{API}/schedules/{sid}", headers=operator, json={"enabled": False}).json()["next_runs"] == []
    wait_finished(client, f"{API}/sweeps/{third['sweep_id']}")
    assert client.delete(f"{API}/schedules/{sid}", headers=operator).status_code == 204


def test_schedule_requests_are_checked_like_sweeps(live):
    service, client, operator, _ = live
    body = {"name": "checked", "cron": "0 2 * * *", "timezone": "Europe/Berlin", "sweep": SWEEP}

    def refused(patch: dict, status: int = 422) -> list:
        r = client.post(f"{API}/schedules", headers=operator, json={**body, **patch})
        assert r.status_code == status, r.text
        return r.json()["detail"]

    assert refused({"cron": "0 2 * *"})[0]["loc"] == ["body", "cron"]
    assert refused({"timezone": "Mars/Olympus"})[0]["loc"] == ["body", "timezone"]
    assert refused({"sweep": {**SWEEP, "method": "nope"}})[0]["loc"] == ["body", "sweep", "method"]
    assert refused({"sweep": {**SWEEP, "options": {"nope": 1}}})[0]["loc"] == ["body", "sweep", "options", "nope"]
    # beyond safety.max_torque_nm (5 N m): the bench limits refuse it, at the field, as for POST /sweeps
    over = refused({"sweep": {**SWEEP, "grid": {"torque_nm": [7], "speed_rpm": [2000], "udc_v": [12]}}})
    assert over[0]["loc"][:3] == ["body", "sweep", "grid"] and "torque" in str(over), over
    assert client.post(f"{API}/schedules", json=body).status_code == 401
    viewer = bearer(service, "viewer")
    assert client.post(f"{API}/schedules", headers=viewer, json=body).status_code == 403

    r = client.post(f"{API}/schedules", headers=operator, json={**body, "enabled": False})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    assert r.json()["next_runs"] == []
    assert "exists already" in refused({}, status=409)
    r = client.patch(f"{API}/schedules/{sid}", headers=operator, json={"enabled": True, "cron": "30 2 * * *"})
    assert r.status_code == 200, r.text
    assert r.json()["cron"] == "30 2 * * *" and len(r.json()["next_runs"]) == 5
    assert client.patch(f"{API}/schedules/{sid}", headers=operator, json={"cron": None}).status_code == 422
    assert client.patch(f"{API}/schedules/{sid + 1000}", headers=operator, json={}).status_code == 404
    assert client.delete(f"{API}/schedules/{sid}", headers=operator).status_code == 204
    assert client.delete(f"{API}/schedules/{sid}", headers=operator).status_code == 404


def test_preview_route_across_the_2027_dst_changes(live):
    _, client, _, _ = live
    for start, expected_change in (
        ("2027-03-26T00:00", "2027-03-28T03:00:00+02:00"),
        ("2027-10-29T00:00", "2027-10-31T02:30:00+02:00"),
    ):
        r = client.get(
            f"{API}/schedules/preview",
            params={"cron": "30 2 * * *", "timezone": "Europe/Berlin", "start": start, "count": 5},
        )
        assert r.status_code == 200, r.text
        runs = r.json()["runs"]
        days = [t[:10] for t in runs]
        assert len(set(days)) == 5 == len(days), runs
        assert expected_change in runs
    r = client.get(f"{API}/schedules/preview", params={"cron": "* * *", "timezone": "UTC"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "cron"]


def test_a_firing_missed_within_grace_runs_once_at_start(tmp_path):
    """Made while the service ran at 00:50 UTC, the service down from then to 03:20: the 03:00 firing
    (20 min ago, grace 1 h) runs once at start; the 01:00 firing (2 h 20 min ago) is recorded missed."""
    db = tmp_path / "missed.db"
    clock = SteppedClock(datetime(2027, 6, 1, 0, 50, tzinfo=UTC))
    settings = _settings(db)
    storage = Storage(db)
    sweep = TypeAdapter(SweepCreate).validate_python(SWEEP)
    nightly = create_schedule(storage, settings, clock(), "nightly", "0 3 * * *", "UTC", sweep)
    early = create_schedule(storage, settings, clock(), "early", "0 1 * * *", "UTC", sweep)

    clock.set(datetime(2027, 6, 1, 3, 20, tzinfo=UTC))
    with _service(db, clock) as service:
        client = client_for(service)
        (run,) = _runs(client, nightly)  # handled by the time start() returns
        assert run["outcome"] == "started" and run["due_at"] == "2027-06-01T03:00:00+00:00", run
        (missed,) = _runs(client, early)
        assert missed["outcome"] == "missed" and missed["sweep_id"] is None, missed
        assert "missed_grace_s" in missed["note"]
        clock.set(datetime(2027, 6, 1, 3, 21, tzinfo=UTC))
        _passes(service)
        assert len(_runs(client, nightly)) == 1 and len(_runs(client, early)) == 1
        sweep_public = wait_finished(client, f"{API}/sweeps/{run['sweep_id']}")
        assert sweep_public["state"] == "done" and sweep_public["schedule_id"] == nightly
        assert [s["schedule_id"] for s in client.get(f"{API}/sweeps").json()] == [nightly]
