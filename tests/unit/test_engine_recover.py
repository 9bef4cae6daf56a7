"""A database with jobs a previous process left queued (killed before they ran) still starts: recover
marks them failed with the reason (found by the README test's database with earlier rows)."""

from service.runs.engine import Engine
from service.runs.events import EventBroker
from service.settings import load_settings
from service.store.storage import Storage


def test_recover_fails_jobs_left_queued(db_location):  # on SQLite and PostgreSQL (tests/conftest.py)
    storage = Storage(db_location)
    job_id = storage.create_job("identification", {"operating_point": {}, "method": "adaptive", "options": {}})
    settings = load_settings(environ={}, overrides={"server.db_path": db_location})
    Engine(storage, None, settings, EventBroker()).recover()
    job = storage.get_job(job_id)
    assert job["state"] == "failed" and "stopped while this job was queued" in job["error"]


class _Events:
    def __init__(self):
        self.published: list[tuple[str, dict]] = []

    def publish(self, event_type: str, data: dict) -> None:
        self.published.append((event_type, data))


def test_a_sweep_waiting_for_the_database_shows_paused_with_why_while_it_waits(tmp_path):
    """The database cannot take the pause, so the engine holds it: where the database can still be read
    (a full disk reads), the sweep is seen paused with the reason, and as stored once the wait ends."""
    storage = Storage(str(tmp_path / "r.db"))
    sweep_id = storage.create_sweep("probe", 6, {}, {}, 2, "b", "v")
    settings = load_settings(environ={}, overrides={"server.db_path": str(tmp_path / "r.db")})
    events = _Events()
    engine = Engine(storage, None, settings, events)
    why = "database r.db: its disk is full (database or disk is full) at 2026-11-24T00:00:00Z"
    with engine.waiting_for_storage(sweep_id, why):
        seen = engine.as_seen(storage.get_sweep(sweep_id))
        assert (seen["state"], seen["pause_reason"]) == ("paused", why)
        engine.publish_sweep(sweep_id)
        assert events.published[-1][1]["state"] == "paused" and events.published[-1][1]["pause_reason"] == why
        assert storage.get_sweep(sweep_id)["state"] == "queued"  # nothing written
    assert engine.as_seen(storage.get_sweep(sweep_id)) == storage.get_sweep(sweep_id)
