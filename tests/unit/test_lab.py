"""A lab on one database (service/runs/lab.py, migration 0009): the bench-name claim, the claim of a
bench's jobs, recovery of only this bench's rows, and other benches' progress as events. Each on SQLite and
PostgreSQL (the `storage` fixture of tests/conftest.py)."""

from __future__ import annotations

import threading
import time
from datetime import datetime, timedelta, timezone

import pytest

from service.runs.engine import Engine
from service.runs.events import EventBroker
from service.runs.lab import BenchInUse, Lab, LabWatch
from service.settings import load_settings
from service.store.storage import Storage

IDENT = {"operating_point": {"torque_nm": 2.5, "speed_rpm": 2000, "udc_v": 12}, "method": "adaptive", "options": {}}


def _sweep(storage: Storage, bench: str | None) -> int:
    grid = {"torque_nm": [1.0], "speed_rpm": [1000.0], "udc_v": [12.0]}
    return storage.create_sweep("adaptive", 6, grid, {}, 1, "emulated", "t", bench=bench)


def test_a_live_bench_name_is_refused_naming_its_holder(storage):
    first = Lab(storage, "B", "first", 8001, "1.0", stale_s=1.0)
    first.claim()
    stop = threading.Event()

    def renew():
        while not stop.wait(0.2):
            first.heartbeat("idle", False, None)

    beat = threading.Thread(target=renew)
    beat.start()
    try:
        with pytest.raises(BenchInUse) as refused:
            Lab(storage, "B", "second", 8002, "1.0", stale_s=1.0).claim(poll_s=0.2)
    finally:
        stop.set()
        beat.join()
    text = str(refused.value)
    assert "bench B is served by another ripplecal serve" in text and "port 8001" in text and "pid" in text
    assert "since" in text
    assert storage.get_bench("B")["instance"] == "first"


def test_a_crashed_holder_is_waited_out_and_an_orderly_stop_frees_the_name_at_once(storage):
    Lab(storage, "B", "crashed", 8001, "1.0", stale_s=1.0).claim()  # no heartbeat follows: kill -9
    t0 = time.monotonic()
    Lab(storage, "B", "restarted", 8001, "1.0", stale_s=1.0).claim(poll_s=0.1)
    assert time.monotonic() - t0 <= 2.0
    assert storage.get_bench("B")["instance"] == "restarted"
    Lab(storage, "B", "restarted", 8001, "1.0", stale_s=1.0).stopped()  # not claimed by this object: no-op
    lab = Lab(storage, "B", "restarted", 8001, "1.0", stale_s=60.0)
    lab.claim()  # its own row
    lab.stopped()
    assert storage.get_bench("B")["state"] == "stopped"
    t0 = time.monotonic()
    Lab(storage, "B", "next", 8001, "1.0", stale_s=60.0).claim()
    assert time.monotonic() - t0 < 0.5


def test_a_heartbeat_that_cannot_be_written_never_raises(storage, monkeypatch):
    lab = Lab(storage, "A", "me", 8000, "1.0")
    lab.claim()

    def away(*_a, **_k):
        raise RuntimeError("database away")

    monkeypatch.setattr(storage, "bench_heartbeat", away)
    lab.heartbeat("idle", False, None)  # logged, not raised


def test_the_overview_says_online_or_not_seen_since_and_the_queue(storage):
    lab = Lab(storage, "A", "me", 8000, "9.9")
    lab.claim()
    lab.heartbeat("busy", True, "sweep 3")
    storage.create_job("identification", IDENT, bench="B")
    benches = {b["name"]: b for b in lab.overview()}
    assert benches["A"]["online"] and benches["A"]["own"] and benches["A"]["software_version"] == "9.9"
    assert benches["A"]["running"] == "sweep 3" and benches["A"]["busy"]
    assert not benches["B"]["online"] and benches["B"]["queue"] == 1 and benches["B"]["state"] == "unknown"
    assert lab.waiting_for("B") == "bench B (never seen: no service has served it)"
    assert lab.waiting_for("A") is None


def test_a_bench_claims_only_its_own_jobs_oldest_first_and_not_a_paused_sweeps(storage):
    other = storage.create_job("identification", IDENT, bench="B")
    paused_sweep = _sweep(storage, "A")
    storage.update_sweep(paused_sweep, state="paused")
    storage.create_job("sweep", {"sweep_id": paused_sweep}, sweep_id=paused_sweep, bench="A", claimed_by="me")
    elsewhere = storage.create_job("identification", IDENT, bench="A")  # queued for A by B's service
    mine = storage.create_job("identification", IDENT, bench="A", claimed_by="me")
    reserved = storage.create_job("identification", IDENT, bench="A", claimed_by="a CLI run")
    assert storage.claim_job("A", "me") == elsewhere
    assert storage.claim_job("A", "me") == mine
    assert storage.claim_job("A", "me") is None  # the paused sweep's job and a CLI run's job wait
    assert storage.get_job(elsewhere)["state"] == "running" and storage.get_job(elsewhere)["claimed_by"] == "me"
    assert storage.get_job(other)["state"] == "queued"
    assert storage.claim_job("A", "a CLI run", job_id=reserved) == reserved
    assert storage.claim_job("A", "a CLI run", job_id=reserved) is None  # taken once


def test_recovery_touches_only_this_benches_rows(storage, tmp_path):
    settings = load_settings(environ={}, overrides={"server.db_path": str(tmp_path / "lab.db"), "bench_name": "A"})
    a_running = storage.create_job("identification", IDENT, bench="A", claimed_by="old A")
    storage.update_job(a_running, state="running")
    b_running = storage.create_job("identification", IDENT, bench="B", claimed_by="B")
    storage.update_job(b_running, state="running")
    for_a = storage.create_job("identification", IDENT, bench="A")  # queued for A by B while A was down
    legacy = storage.create_job("identification", IDENT)  # from before benches: one database, one bench
    a_sweep, b_sweep, waiting_sweep = _sweep(storage, "A"), _sweep(storage, "B"), _sweep(storage, "A")
    storage.update_sweep(a_sweep, state="running", started_at="2026-01-01T00:00:00+00:00")
    storage.update_sweep(b_sweep, state="running", started_at="2026-01-01T00:00:00+00:00")
    storage.create_job("sweep", {"sweep_id": waiting_sweep}, sweep_id=waiting_sweep, bench="A")

    Engine(storage, None, settings, EventBroker()).recover()

    assert storage.get_job(a_running)["state"] == "failed"
    assert storage.get_job(legacy)["state"] == "failed" and storage.get_job(legacy)["bench"] == "A"
    assert storage.get_job(b_running)["state"] == "running"
    assert storage.get_job(for_a)["state"] == "queued"
    assert storage.get_sweep(a_sweep)["state"] == "interrupted"
    assert storage.get_sweep(b_sweep)["state"] == "running"
    assert storage.get_sweep(waiting_sweep)["state"] == "queued"


def test_a_pause_asked_at_another_service_is_acted_on_by_the_benches_own_and_a_refusal_noted(storage, tmp_path):
    settings = load_settings(environ={}, overrides={"server.db_path": str(tmp_path / "lab.db"), "bench_name": "A"})
    queued, done = _sweep(storage, "A"), _sweep(storage, "A")
    storage.create_job("sweep", {"sweep_id": queued}, sweep_id=queued, bench="A")
    storage.update_sweep(done, state="done")
    elsewhere = Engine(storage, None, load_settings(environ={}, overrides={"bench_name": "B"}), EventBroker())
    elsewhere.control_sweep(queued, "pause")  # asked at B's service: written, not done
    assert storage.get_sweep(queued)["state"] == "queued" and storage.get_sweep(queued)["control_request"] == "pause"
    storage.request_sweep_control(done, "pause")  # asked while it ran; it ended meanwhile
    Engine(storage, None, settings, EventBroker()).act_on_control_requests()
    assert storage.get_sweep(queued)["state"] == "paused" and storage.get_sweep(queued)["control_request"] is None
    note = storage.get_sweep(done)["control_note"]
    assert storage.get_sweep(done)["state"] == "done" and "refused by bench A" in note, note
    assert storage.claim_job("A", "me") is None  # a paused sweep's job waits


def test_other_benches_progress_is_published_once_with_its_bench(storage):
    broker = EventBroker()
    published: list[tuple[str, dict]] = []
    broker.publish = lambda kind, data: published.append((kind, data))  # type: ignore[method-assign]
    watch = LabWatch(storage, broker, "A")
    theirs = storage.create_job("identification", IDENT, bench="B")
    storage.create_job("identification", IDENT, bench="A")  # this bench's engine publishes its own
    sweep = _sweep(storage, "B")
    watch.tick()
    watch.tick()  # nothing new: nothing again
    storage.update_sweep(sweep, state="running")
    watch.tick()
    kinds = [(k, d.get("job_id") or d.get("sweep_id"), d["state"], d["bench"]) for k, d in published]
    assert kinds == [
        ("job.state", theirs, "queued", "B"),
        ("sweep.progress", sweep, "queued", "B"),
        ("sweep.progress", sweep, "running", "B"),
    ]


def _date_heartbeat(storage: Storage, bench: str, offset_s: float) -> None:
    """The bench's last heartbeat moved `offset_s` from now on the database's clock (as software from before
    issue 25, which stamped it with its own PC's clock, left it)."""
    Lab(storage, bench, "holder", 8001, "1.0").claim()
    moved = (datetime.fromisoformat(storage.database_now()) + timedelta(seconds=offset_s)).isoformat(
        timespec="milliseconds"
    )
    with storage.transaction() as conn:
        conn.execute("UPDATE benches SET last_seen = ? WHERE name = ?", (moved, bench))


def test_liveness_is_the_age_of_the_heartbeat_on_the_databases_clock(storage):
    lab = Lab(storage, "A", "me", 8000, "1.0", stale_s=5.0)
    lab.claim()
    assert 0 <= storage.get_bench("A")["seen_s"] < 5.0  # stamped by the database: no PC clock involved
    _date_heartbeat(storage, "B", -10.0)
    benches = {b["name"]: b for b in lab.overview()}
    assert benches["A"]["online"] and not benches["B"]["online"]
    assert 9.5 < storage.get_bench("B")["seen_s"] < 60.0
    assert benches["B"]["seen"].startswith("not seen since")


def test_a_heartbeat_that_cannot_be_proven_stale_is_not_taken_over(storage):
    _date_heartbeat(storage, "B", +30.0)  # dated ahead of the database's clock: its age cannot prove it dead
    with pytest.raises(BenchInUse) as refused:
        Lab(storage, "B", "second", 8002, "1.0", stale_s=0.5).claim(poll_s=0.1)
    assert "ahead of the database's clock: not provably stale" in str(refused.value)
    assert storage.get_bench("B")["instance"] == "holder"


def test_the_databases_clock_reads_as_the_timestamps_python_writes(storage):
    # the same UTC ISO form (so they compare as text), and on one host the same time within a wide margin
    now = storage.database_now()
    python_now = datetime.now(timezone.utc)
    assert len(now) == len(python_now.isoformat(timespec="milliseconds")) and now.endswith("+00:00"), now
    assert abs((datetime.fromisoformat(now) - python_now).total_seconds()) < 60
